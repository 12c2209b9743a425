"""What a random policy and the scripted expert score on the families of sweeps/families_state.toml: the yardsticks
of its learning checks, from the state vector, through the training scripts' own envs (action repeat 2, the default
time limits, Meta-World on the `new` task vectors of seed 1).

    python tools/family_references.py                  # -> results/families_state/references.json (and a table)
    python tools/family_references.py --episodes 20 --out /tmp/references.json
    python tools/family_references.py --table2         # Table 2's tasks at the Meta-World default schedule
                                                       # -> results/metaworld_table2/references.json
    python tools/family_references.py --kitchen --episodes 50   # the kitchen tables' cells, from the fixed start
                                                       # -> results/kitchen_tables/references.json
"""
import argparse
import json
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import rama_dreamer  # noqa: E402
import rama_metaworld  # noqa: E402

# the cells of sweeps/families_state.toml: (cell, script module, env id, its other flags)
FAMILIES = [("kitchen_bluebox", rama_dreamer, "kitchen/bluebox", {"kitchen_start": "random"}),
            ("metaworld_drawer_close", rama_metaworld, "metaworld/drawer-close",
             {"task_set": "new", "action_repeat": 2}),
            ("metaworld_push", rama_metaworld, "metaworld/push", {"task_set": "new", "action_repeat": 2})]
# sweeps/metaworld_table2.toml's cells (named by task) at rama_metaworld.py's default schedule (action repeat 1)
TABLE2 = [(name.replace("-", "_"), rama_metaworld, f"metaworld/{name}", {"task_set": "new"})
          for name in ("push", "dial-turn", "drawer-close")]
# sweeps/kitchen_tables.toml's cells: Box and Box -> Cone (whose runs act on the cone; box_cone_wm is its ablation,
# the same env), the paper's fixed start
KITCHEN = [("box", rama_dreamer, "kitchen/bluebox", {"kitchen_start": "fixed"}),
           ("box_cone", rama_dreamer, "kitchen/bluecone", {"kitchen_start": "fixed"}),
           ("box_cone_wm", rama_dreamer, "kitchen/bluecone", {"kitchen_start": "fixed"})]


def expert(S, env):
    """The family's scripted expert, acting on the unwrapped env's state."""
    if S is rama_metaworld:
        return lambda obs: S.expert_action(env.unwrapped)[None]
    from kitchen_env import scripted_action

    return lambda obs: scripted_action(env.unwrapped)[None]


def score(S, env_id: str, flags: dict, policy: str, episodes: int, seed: int = 1) -> dict:
    """Mean return and success rate (mean ± s.e. over episodes) of one policy, episode seeds as a run's would be."""
    args = S.resolve_defaults(S.Args(env_id=env_id, obs_type="state", seed=seed, **flags))
    envs = S.make_envs(args, env_id, seed, 1)
    rng = np.random.default_rng(seed)
    act = (lambda obs: rng.uniform(-1, 1, (1, *envs.single_action_space.shape)).astype(np.float32)) \
        if policy == "random" else expert(S, envs.envs[0])
    returns, successes = [], []
    for k in range(episodes):
        (episode,), _ = S.run_episodes(envs, act, [seed * 1_000_003 + k], env_id.split("/")[1])
        returns.append(float(episode["return"]))
        successes.append(float(episode.get("success", False)))
    envs.close()
    se = lambda x: float(np.std(x, ddof=1) / np.sqrt(len(x))) if len(x) > 1 else float("nan")  # noqa: E731
    return {"return": float(np.mean(returns)), "return_se": se(returns), "success_rate": float(np.mean(successes)),
            "success_rate_se": se(successes), "episodes": episodes}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=10, help="episodes per policy and family")
    parser.add_argument("--table2", action="store_true",
                        help="score Table 2's tasks (push, dial-turn, drawer-close) instead")
    parser.add_argument("--kitchen", action="store_true", help="score the kitchen tables' cells instead")
    parser.add_argument("--out", default=None, help="the JSON to write (default: the chosen set's results folder)")
    cli = parser.parse_args()
    folder, cells = (("metaworld_table2", TABLE2) if cli.table2 else ("kitchen_tables", KITCHEN) if cli.kitchen
                     else ("families_state", FAMILIES))
    cli.out = cli.out or os.path.join(ROOT, "results", folder, "references.json")
    scored = {}  # cells on one env with one set of flags (box_cone and its ablation box_cone_wm) are scored once

    def score_once(S, env_id: str, flags: dict, policy: str) -> dict:
        key = (S.__name__, env_id, tuple(sorted(flags.items())), policy)
        if key not in scored:
            scored[key] = score(S, env_id, flags, policy, cli.episodes)
        return scored[key]

    table = {cell: {policy: score_once(S, env_id, flags, policy) for policy in ("random", "expert")}
             for cell, S, env_id, flags in cells}
    os.makedirs(os.path.dirname(cli.out), exist_ok=True)
    with open(cli.out, "w") as f:
        json.dump(table, f, indent=2)
    print("| family | policy | return (mean ± s.e.) | success rate |\n| --- | --- | --- | --- |")
    for cell, row in table.items():
        for policy, s in row.items():
            print(f"| {cell} | {policy} | {s['return']:.1f} ± {s['return_se']:.1f} | {s['success_rate']:.2f} |")
    print(f"wrote {cli.out}")


if __name__ == "__main__":
    main()
