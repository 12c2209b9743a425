"""Does a run's critic stay below what any return can reach, and does the agent stay solved? One row per run.

Meta-World pays at most 10 per env step, so no discounted return can pass 10 · repeat · scale / (1 − γ) (2,000 at
action repeat 2, reward scale 1, γ 0.99). From each run's metrics.jsonl (the imagine/* diagnostics of
rama_metaworld.py, in the units the agent learns) this tabulates the value at the first imagined step against that
bound (its peak, and its mean over the second half of the run's updates), the peak imagined reward against the most
one step pays, the actor's peak gradient norm, how many of the agent's episodes (after the random prefill) failed after
its first success, and the success rate of the last 10 episodes; above that, one row per cell.

    python tools/critic_check.py results/metaworld_drawer_close      # -> results/metaworld_drawer_close/critic.md
    python tools/critic_check.py results/metaworld_drawer_close --plot baseline__dreamer__s1 slow_target__dreamer__s1 \\
        reward_scale__dreamer__s1                                    # and critic.png: these runs' curves
"""
import argparse
import glob
import json
import os

MAX_REWARD_PER_ENV_STEP = 10.0  # Meta-World v3's reward range is [0, 10]


def read_run(folder: str):
    """A run's args.json and its metrics.jsonl rows, and its bound: the most one agent step pays and the most any
    discounted return can reach."""
    with open(os.path.join(folder, "args.json")) as f:
        args = json.load(f)
    with open(os.path.join(folder, "metrics.jsonl")) as f:
        rows = [json.loads(line) for line in f]
    step_max = MAX_REWARD_PER_ENV_STEP * args["action_repeat"] * args.get("reward_scale", 1.0)
    return args, rows, step_max, step_max / (1 - args["gamma"])


def check_run(folder: str) -> dict:
    args, rows, step_max, bound = read_run(folder)
    updates = [r for r in rows if "imagine/value_first" in r]
    episodes = [r for r in rows if "charts/success_rate" in r]
    solved = [r["charts/success_rate"] > 0 for r in episodes]
    acted = solved[args.get("prefill_episodes", 1):]  # the agent's own episodes: the prefill acts at random
    first = acted.index(True) if any(acted) else len(acted)
    last = solved[-10:]
    return {"run": os.path.basename(folder), "bound": bound,
            "value": max(r["imagine/value_first"] for r in updates) / bound if updates else float("nan"),
            "late": sum(r["imagine/value_first"] for r in updates[len(updates) // 2:]) / bound
            / max(len(updates) - len(updates) // 2, 1),
            "reward": max(r["imagine/reward_max"] for r in updates) / step_max if updates else float("nan"),
            "grad": max(r["losses/actor_grad_norm"] for r in updates) if updates else float("nan"),
            "failed": sum(not s for s in acted[first:]), "episodes": len(acted), "solved": any(acted),
            "last10": sum(last) / max(len(last), 1)}


def plot(folders: list, out: str):
    """Per run, against env steps: the value at the first imagined step over its bound, the actor's gradient norm
    (log scale), the actor's std, and the training return."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("value at the first imagined step / bound", "imagine/value_first"),
              ("actor gradient norm", "losses/actor_grad_norm"), ("actor std", "imagine/actor_std"),
              ("training return", "charts/episodic_return")]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4))
    for folder in folders:
        _, rows, _, bound = read_run(folder)
        for ax, (title, key) in zip(axes, panels):
            points = [(r["step"], r[key] / (bound if key == "imagine/value_first" else 1)) for r in rows if key in r]
            ax.plot(*zip(*points), label=os.path.basename(folder), lw=1.3)
    for ax, (title, key) in zip(axes, panels):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("environment steps")
        ax.grid(alpha=0.3)
    axes[0].axhline(1.0, color="k", ls=":", lw=1)
    axes[1].set_yscale("log")
    axes[-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


def table(rows: list) -> str:
    lines = ["| run | bound | value / bound: peak | second half | peak reward / max | peak actor grad norm | "
             "agent's episodes failed after its first success | last 10 solved |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        failed = f"{r['failed']} of {r['episodes']}" if r["solved"] else "never solved"
        lines.append(f"| {r['run']} | {r['bound']:,.0f} | {r['value']:.2f} | {r['late']:.2f} | {r['reward']:.2f} | "
                     f"{r['grad']:.0f} | {failed} | {r['last10']:.1f} |")
    return "\n".join(lines) + "\n"


def cell_table(rows: list) -> str:
    """One row per cell (the run name before its first `__`): how many seeds never solved, how many of the agent's
    episodes failed after a first success (over all seeds), how many seeds solved all of their last 10, and the
    range of the value's peak over its bound and the largest actor gradient norm."""
    cells = {}
    for r in rows:
        cells.setdefault(r["run"].split("__")[0], []).append(r)
    lines = ["| cell | seeds | never solved | agent's episodes failed after a first success | seeds solving all of "
             "their last 10 | value / bound: peak | peak actor grad norm |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for cell, runs in cells.items():
        found = [r for r in runs if r["solved"]]
        failed = f"{sum(r['failed'] for r in found)} of {sum(r['episodes'] for r in found)}" if found else "–"
        values = [r["value"] for r in found]
        value = f"{min(values):.2f}-{max(values):.2f}" if found else "–"
        grad = f"{max(r['grad'] for r in runs):.0f}"
        lines.append(f"| {cell} | {len(runs)} | {len(runs) - len(found)} | {failed} | "
                     f"{sum(r['last10'] == 1.0 for r in runs)} of {len(runs)} | {value} | {grad} |")
    return "\n".join(lines) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("experiment", help="an experiment folder of results/ (one folder per run)")
    parser.add_argument("--out", default=None, help="the markdown table (default: <experiment>/critic.md)")
    parser.add_argument("--plot", nargs="+", default=None, metavar="RUN",
                        help="also draw these runs (folder names inside the experiment) into <experiment>/critic.png")
    cli = parser.parse_args()
    folders = sorted(os.path.dirname(p) for p in glob.glob(os.path.join(cli.experiment, "*", "metrics.jsonl")))
    if not folders:
        parser.error(f"{cli.experiment}: no <run>/metrics.jsonl inside")
    checked = [check_run(f) for f in folders]
    text = cell_table(checked) + "\n" + table(checked)
    out = cli.out or os.path.join(cli.experiment, "critic.md")
    with open(out, "w") as f:
        f.write(text)
    print(text + f"wrote {out}")
    if cli.plot:
        missing = [r for r in cli.plot if not os.path.isfile(os.path.join(cli.experiment, r, "metrics.jsonl"))]
        if missing:
            parser.error(f"--plot: no such run in {cli.experiment}: {', '.join(missing)}")
        plot([os.path.join(cli.experiment, r) for r in cli.plot], os.path.join(cli.experiment, "critic.png"))


if __name__ == "__main__":
    main()
