"""A run's checkpoint evaluated with each evaluation action: Dreamer v1's mode estimate (`sample-mode`, the most
likely of 100 samples of the tanh-normal actor) against the tanh of its Gaussian mean (`mean`), and against the
exploring policy the run collects with (`explore`: a sample plus --expl-noise). The same episode seeds, hence the
same task vectors on Meta-World, for each, on the run's own evaluation env (seed + 10,000).

    python tools/eval_actions.py runs/families_state/metaworld_drawer_close__dreamer__s1 --episodes 10
    python tools/eval_actions.py runs/<...>/<run folder> --rules mean sample-mode

Why: it tells whether a run's evaluation return differs from its training return because of the evaluation action
(with the actor's std near its initial 5, the most likely sample of a tanh-normal is a saturated action) or because
the policy itself changed. Single-task runs (a folder with checkpoint.pt, or a sweep folder holding one).
"""
import argparse
import glob
import json
import os
import sys

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import rama_dreamer  # noqa: E402
import rama_metaworld  # noqa: E402

RULES = ("sample-mode", "mean", "explore")


def run_folder(path: str) -> str:
    """The folder holding args.json and checkpoint.pt: PATH itself, or the one run folder inside a sweep's folder."""
    found = [path] if os.path.exists(os.path.join(path, "checkpoint.pt")) else \
        [os.path.dirname(p) for p in glob.glob(os.path.join(path, "*", "checkpoint.pt"))]
    if len(found) != 1:
        sys.exit(f"error: {path}: {'no' if not found else 'more than one'} run folder with checkpoint.pt")
    return found[0]


def evaluate(path: str, rules: list, episodes: int) -> tuple:
    """({rule: {"returns": [...], "successes": [...]}} over `episodes` episodes of the run's evaluation env, the
    checkpoint's update count). The run's args come as --resume reads them (older runs' ADDED_FLAGS included)."""
    with open(os.path.join(path, "args.json")) as f:
        S = rama_metaworld if json.load(f)["env_id"].startswith("metaworld/") else rama_dreamer
    args, _ = S.resolve_run(S.Args(resume=path, device="cpu", cuda_graph=False), {"resume", "device", "cuda_graph"})
    payload = S.read_checkpoint(os.path.join(path, "checkpoint.pt"), args)
    envs = S.make_envs(args, args.env_id, args.seed + 10_000, 1)
    agent = S.Agent(envs.single_observation_space.shape, envs.single_action_space.shape[0], args)
    agent.load_state_dict(payload["agent"])
    agent.eval()
    results = {}
    for rule in rules:
        policy = S.Policy(agent, torch.device("cpu"), "mean" if rule == "explore" else rule)
        rng = np.random.default_rng(args.seed)
        noise = args.expl_noise if rule == "explore" else None
        returns, successes = [], []
        for k in range(episodes):
            policy.reset()
            torch.manual_seed(k)  # the actor's samples: the same stream for every rule
            (episode,), _ = S.run_episodes(envs, lambda o: policy.act(o, noise, rng), [args.seed * 1_000_003 + k],
                                           args.env_id.split("/")[1])
            returns.append(float(episode["return"]))
            successes.append(float(episode.get("success", np.nan)))
        results[rule] = {"returns": returns, "successes": successes}
    envs.close()
    return results, payload["state"].get("updates")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", help="a run folder (with args.json and checkpoint.pt), or a sweep folder holding one")
    parser.add_argument("--episodes", type=int, default=10, help="episodes per evaluation action")
    parser.add_argument("--rules", nargs="+", default=list(RULES), choices=RULES, help="the actions to compare")
    cli = parser.parse_args()
    if cli.episodes < 1:
        sys.exit("error: --episodes must be >= 1")
    path = run_folder(cli.run)
    try:
        results, updates = evaluate(path, cli.rules, cli.episodes)
    except (rama_dreamer.UsageError, rama_metaworld.UsageError) as e:  # a bad checkpoint or args.json
        sys.exit(f"error: {e}")
    print(f"{path}: checkpoint after {updates} updates, {cli.episodes} episodes per action (same seeds)")
    print("| action | return (mean ± s.e.) | success rate |\n| --- | --- | --- |")
    for rule, r in results.items():
        x, s = np.array(r["returns"]), np.array(r["successes"])
        se = x.std(ddof=1) / np.sqrt(len(x)) if len(x) > 1 else float("nan")
        success = "–" if np.isnan(s).all() else f"{np.nanmean(s):.2f}"
        print(f"| {rule} | {x.mean():.1f} ± {se:.1f} | {success} |")


if __name__ == "__main__":
    main()
