"""Before any kitchen training: how often does Dreamer's initial policy ever see a positive reward?

For each start (--kitchen-start fixed and random) this plays episodes with a freshly initialised agent of
rama_dreamer.py (one new agent per episode, seeded by the episode's index), acting as it collects: a sample of its
tanh-normal actor plus the exploration noise (0.3), action repeat 2. Beside it, uniformly random actions (the prefill
episode). It reports the share of episodes with any positive reward, the share that moved the object at all, and the
returns. State vector, the learning check's sizes (MLPs of 200).

    python tools/kitchen_precheck.py --episodes 50 --out results/kitchen_tables/precheck.json
"""
import argparse
import json
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import rama_dreamer as rd  # noqa: E402

MOVED_CM = 0.5  # the object counts as moved when its distance to the zone changed by more than this


def play(args: rd.Args, policy: str, seed: int) -> dict:
    """One episode; policy "dreamer-init" (a fresh agent's collecting actions) or "uniform" (the prefill's)."""
    env = rd.make_env(args, "kitchen/bluebox", seed)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    actor = rd.Policy(rd.Agent(env.observation_space.shape, env.action_space.shape[0], args), "cpu")
    actor.reset(1)
    obs, _ = env.reset(seed=seed)
    start = env.unwrapped.distance_cm()
    rewards, done = [], False
    while not done:
        if policy == "uniform":
            action = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
        else:
            action = actor.act(obs[None], args.expl_noise, rng)[0]
        obs, reward, terminated, truncated, _ = env.step(action)
        rewards.append(float(reward))
        done = terminated or truncated
    moved = abs(env.unwrapped.distance_cm() - start) > MOVED_CM or terminated
    env.close()
    return {"return": float(np.sum(rewards)), "positive": bool(max(rewards) > 1e-3), "moved": bool(moved),
            "best_step": float(max(rewards))}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=50, help="episodes per start and policy")
    parser.add_argument("--out", default="results/kitchen_tables/precheck.json", help="where the summary goes (JSON)")
    cli = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s)")
    summary = {}
    for start in ("fixed", "random"):
        args = rd.resolve_defaults(rd.Args(env_id="kitchen/bluebox", obs_type="state", mlp_units=200,
                                           kitchen_start=start))
        for policy in ("dreamer-init", "uniform"):
            t0 = time.time()
            episodes = [play(args, policy, seed) for seed in range(cli.episodes)]
            returns = np.array([e["return"] for e in episodes])
            row = {"episodes": cli.episodes, "any_positive_reward": float(np.mean([e["positive"] for e in episodes])),
                   "object_moved": float(np.mean([e["moved"] for e in episodes])),
                   "mean_return": float(returns.mean()), "min_return": float(returns.min()),
                   "max_return": float(returns.max()), "positive_return": float(np.mean(returns > 0.5))}
            summary[f"{start}/{policy}"] = row
            print(f"{start:6s} {policy:12s} any r>0 {row['any_positive_reward']:.2f} | "
                  f"moved {row['object_moved']:.2f} | return {row['mean_return']:+.2f} "
                  f"[{row['min_return']:+.1f}, {row['max_return']:+.1f}] | "
                  f"return > 0.5: {row['positive_return']:.2f} | {time.time() - t0:.0f} s", flush=True)
    os.makedirs(os.path.dirname(cli.out) or ".", exist_ok=True)
    with open(cli.out, "w") as f:
        json.dump(summary, f, indent=1)
    print(f"wrote {cli.out}")


if __name__ == "__main__":
    main()
