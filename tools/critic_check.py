"""Does a run's critic stay below what any return can reach, and does the agent stay solved? One row per run.

Meta-World pays at most 10 per env step, so no discounted return can pass 10 · repeat · scale / (1 − γ) (2,000 at
action repeat 2, reward scale 1, γ 0.99). From each run's metrics.jsonl (the imagine/* diagnostics of
rama_metaworld.py, in the units the agent learns) this tabulates the value at the first imagined step against that
bound (its peak, and its mean over the second half of the run's updates), the peak imagined reward against the most
one step pays, the actor's peak gradient norm, the episodes that failed after the first
success, and the success rate of the last 10 episodes.

    python tools/critic_check.py results/metaworld_drawer_close      # -> results/metaworld_drawer_close/critic.md
"""
import argparse
import glob
import json
import os

MAX_REWARD_PER_ENV_STEP = 10.0  # Meta-World v3's reward range is [0, 10]


def check_run(folder: str) -> dict:
    with open(os.path.join(folder, "args.json")) as f:
        args = json.load(f)
    with open(os.path.join(folder, "metrics.jsonl")) as f:
        rows = [json.loads(line) for line in f]
    scale = args.get("reward_scale", 1.0)
    step_max = MAX_REWARD_PER_ENV_STEP * args["action_repeat"] * scale  # the most one agent step can pay
    bound = step_max / (1 - args["gamma"])
    updates = [r for r in rows if "imagine/value_first" in r]
    episodes = [r for r in rows if "charts/success_rate" in r]
    solved = [r["charts/success_rate"] > 0 for r in episodes]
    first = solved.index(True) if any(solved) else len(solved)
    last = solved[-10:]
    return {"run": os.path.basename(folder), "bound": bound,
            "value": max(r["imagine/value_first"] for r in updates) / bound if updates else float("nan"),
            "late": sum(r["imagine/value_first"] for r in updates[len(updates) // 2:]) / bound
            / max(len(updates) - len(updates) // 2, 1),
            "reward": max(r["imagine/reward_max"] for r in updates) / step_max if updates else float("nan"),
            "grad": max(r["losses/actor_grad_norm"] for r in updates) if updates else float("nan"),
            "failed": sum(not s for s in solved[first:]), "episodes": len(solved),
            "last10": sum(last) / max(len(last), 1)}


def table(rows: list) -> str:
    lines = ["| run | bound | value / bound: peak | second half | peak reward / max | peak actor grad norm | "
             "failed after first success | last 10 solved |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['run']} | {r['bound']:,.0f} | {r['value']:.2f} | {r['late']:.2f} | {r['reward']:.2f} | "
                     f"{r['grad']:.0f} | "
                     f"{r['failed']} of {r['episodes']} | {r['last10']:.1f} |")
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("experiment", help="an experiment folder of results/ (one folder per run)")
    parser.add_argument("--out", default=None, help="the markdown table (default: <experiment>/critic.md)")
    cli = parser.parse_args()
    folders = sorted(os.path.dirname(p) for p in glob.glob(os.path.join(cli.experiment, "*", "metrics.jsonl")))
    if not folders:
        parser.error(f"{cli.experiment}: no <run>/metrics.jsonl inside")
    text = table([check_run(f) for f in folders])
    out = cli.out or os.path.join(cli.experiment, "critic.md")
    with open(out, "w") as f:
        f.write(text)
    print(text + f"wrote {out}")


if __name__ == "__main__":
    main()
