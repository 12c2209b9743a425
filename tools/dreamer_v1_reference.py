"""Dreamer v1's published evaluation curves as a reference for this project's pixel runs: mean and standard deviation
over the original's seeds at each step it logged, from danijar/dreamer's `scores/dreamer.json` (5 seeds per task,
action repeat 2, 64x64 pixels, evaluation return), for the tasks of sweeps/pixels_dreamer.toml. The file's values
are binned: each is a seed's mean over the evaluations of the 100k env steps up to its step (v1 evaluates one
episode every 10k steps), so report.py averages a run's evaluations over the same windows.

    git clone https://github.com/danijar/dreamer /tmp/dreamer   # the file is in its repository, scores/dreamer.json
    python tools/dreamer_v1_reference.py /tmp/dreamer/scores/dreamer.json   # -> results/pixels_dreamer/reference.json

report.py draws it as a band behind the curves and tabulates the runs against it (`--reference`).
"""
import argparse
import json
import os

import numpy as np

TASKS = {"walker-stand": "dmc_walker_stand", "cartpole-balance": "dmc_cartpole_balance"}  # this project's: theirs


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scores", help="danijar/dreamer's scores/dreamer.json")
    parser.add_argument("--out", default="results/pixels_dreamer/reference.json")
    parser.add_argument("--max-step", type=float, default=1_005_000, help="the last step kept")
    args = parser.parse_args()
    with open(args.scores) as f:
        scores = json.load(f)
    tasks = {}
    for ours, theirs in TASKS.items():
        runs = [r for r in scores if r["task"] == theirs and r["method"] == "dreamer"]
        steps = sorted({x for r in runs for x in r["xs"] if x <= args.max_step})
        # each seed's value at each step it logged (a seed whose log stops early counts only where it has one)
        values = [[r["ys"][r["xs"].index(s)] for r in runs if s in r["xs"]] for s in steps]
        tasks[ours] = {"steps": steps, "mean": [round(float(np.mean(v)), 1) for v in values],
                       "std": [round(float(np.std(v)), 1) for v in values], "seeds": [len(v) for v in values]}
    # the file's steps (5k, 105k, 205k, ...) are the bin edges of danijar/dreamer's plotting.py (`binning`, bins of
    # 100k): v1 evaluates one episode every 10k env steps from 5k, so each value past the first is a seed's mean over
    # the ten evaluations in the 100k steps up to its step. "window" tells report.py to average a run's so too.
    reference = {"name": "Dreamer v1", "key": "eval/episodic_return", "checkpoints": [105_000, 205_000],
                 "window": 100_000,
                 "source": "danijar/dreamer scores/dreamer.json (commit 56d4d44): per step, each seed's mean "
                           "evaluation return over the 100k env steps up to it, then the mean and the population "
                           "standard deviation over the seeds", "tasks": tasks}
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(reference, f, indent=1)
    for ours, t in tasks.items():
        print(ours, ", ".join(f"{int(s)}: {m} ± {d} ({n})" for s, m, d, n in
                              zip(t["steps"], t["mean"], t["std"], t["seeds"]) if s in reference["checkpoints"]))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
