"""Learning curves from run folders' metrics.jsonl: training and evaluation returns against environment steps.

    python plot_curves.py runs/<run> [runs/<other run> ...] --out docs/curve.png
"""
import argparse
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def read_series(run_path: str, key: str):
    path = os.path.join(run_path, "metrics.jsonl")
    if not os.path.isfile(path):
        sys.exit(f"error: {run_path}: no metrics.jsonl (not a run folder)")
    steps, values = [], []
    with open(path) as f:
        for line in f:
            row = json.loads(line)
            if key in row:
                steps.append(row["step"])
                values.append(row[key])
    return steps, values


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="run folders (each holding metrics.jsonl)")
    parser.add_argument("--out", default="curve.png", help="the PNG to write")
    parser.add_argument("--title", default=None, help="figure title (default: the first run's name)")
    args = parser.parse_args()
    fig, ax = plt.subplots(figsize=(7, 4))
    for run_path in args.runs:
        label = os.path.basename(os.path.normpath(run_path))
        for key, style in (("charts/episodic_return", dict(alpha=0.5, lw=1)), ("eval/episodic_return", dict(marker="o"))):
            steps, values = read_series(run_path, key)
            if steps:
                ax.plot(steps, values, label=f"{key.split('/')[0]} — {label}"[:70], **style)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return")
    ax.set_title(args.title or os.path.basename(os.path.normpath(args.runs[0]))[:80], fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
