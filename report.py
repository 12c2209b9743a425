"""Tables and learning curves from results/: the paper's metric per task and method, by one command.

    python report.py results/cartpole_tables            # -> results/cartpole_tables/report.md, curves.png, scores.png
    python report.py results                               # every experiment under results/
    python report.py results/cartpole_tables --out docs # write them to docs/ instead
    python report.py --runs runs/<run> [runs/<run> ...] --out docs/curve.png   # the training and evaluation
                                                           # returns of single runs, in one figure
    python report.py --runs runs/<run> [runs/<run> ...] --key losses/kl charts/imagined_return --out kl.png
                                                           # any logged metrics of single runs, a panel each
    python report.py results/pixels_dreamer --key eval/episodic_return \
        --reference results/pixels_dreamer/reference.json  # against Dreamer v1's published curves
    python report.py results/families_state --levels results/families_state/references.json  # against a random
                                                           # policy's and the scripted expert's levels
    python report.py results/walker_tables --tasks walk stand_walk  # only these tasks' columns (shell-style
                                                           # patterns too): not the experiment's pilots and Ms
    python report.py results/walker_tables --tasks walk stand_walk --methods dreamer uniform rrama vrama \
        --out results/walker_tables/paper_rows            # only these rows (the paper's), e.g. for a figure

An experiment folder holds one folder per run, named <cell>__<method>__s<seed> as sweep.py writes them, each with
args.json and metrics.jsonl. A folder named otherwise is grouped by its args.json (env id, method, seed). A
--task-sequence run has one metrics.jsonl per task in <k>_<task>/, and each task is its own column, <cell>/<k>_<task>.

The number per run is the paper's: the average training-episode return over the whole run (the mean of
`charts/episodic_return`; --key picks another key). Per task and method the table gives:
- the mean ± standard error over seeds, as the paper does (s.e. = sample standard deviation, ddof 1, / sqrt(n));
- the interquartile mean (IQM) with a 95% stratified-bootstrap confidence interval (rliable), because 2-3 seeds
  with mean ± s.e. alone mislead. The IQM drops int(n/4) runs at each end, so with fewer than 4 seeds it equals
  the mean. The bootstrap is seeded, so the report is the same on every run of this command.
A second table answers "does it beat Dreamer, and uniform mixing?": per task, each method's probability of
improvement P(X > Y) over each (and over the --against methods), with its 95% bootstrap CI and the exact two-sided
rank test's p (Mann-Whitney: with 3-5 seeds, the test to read). A third gives the differences of means against the
same columns (and a preset's row against the same method without the preset), each with a 95% Welch t interval;
they are printed too, one line each. Runs stopped before their --total-steps are marked unfinished in the tables; a
run with a non-finite value is left out, with a warning. A fourth says what the prior-data methods mixed into their
batches (from the runs' addressing/ logs): the share of other tasks' chunks, the returns and reward sums of what was
picked against what could have been, how peaked q is, and what the bandit objective gained.
scores.png shows every seed's number as a dot beside its method's mean ± s.e. The curves (curves.png) show, per
task, one line per method. Each run's returns are averaged in --bins equal bins of environment steps; the line is
the mean over seeds of those bin averages, and the band is ± one s.e.
--reference adds a published curve (tools/dreamer_v1_reference.py writes Dreamer v1's): drawn as its mean ± std
band, and a table of each run's value at the reference's checkpoints (the mean over the reference's window up to
each, or the logged step nearest each, within 10%) against the reference's mean ± 2 std.
--levels adds fixed policies' levels per task (tools/family_references.py writes a random policy's and the scripted
expert's): dotted lines on the curves, and a table of each method's last values against them.
"""
import argparse
import fnmatch
import glob
import json
import os
import re
import shlex
import sys
import warnings

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from sweep import OneLineParser  # noqa: E402 (argparse's errors as one line, as sweep.py's)

METHOD_NAMES = {"dreamer": "Dreamer", "uniform": "No addressing (uniform)", "rrama": "RRAMa", "rbrama": "RbRAMa",
                "vrama": "VRAMa"}  # the paper's row names, in its order
PRESET_NAMES = {"authors-code": "authors' code"}  # a run made with --preset P is method "<method>@P"


def fail(message: str):
    """A bad input: one line on stderr, `error: ...`, and exit code 2, before anything is written."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def method_name(method: str) -> str:
    """A row's name: the paper's name of the method, and the preset it ran with (`rrama@authors-code`)."""
    base, _, preset = method.partition("@")
    name = METHOD_NAMES.get(base, f"`{base}`")
    return f"{name}, {PRESET_NAMES.get(preset, preset)}" if preset else name


def read_metrics(metrics_path: str) -> dict:
    """key -> {step: value} of a metrics.jsonl. A resumed run can log a step twice: the last line of a step wins."""
    by_key = {}
    with open(metrics_path) as f:
        for line in f:
            row = json.loads(line)
            for k, v in row.items():
                if k != "step":
                    by_key.setdefault(k, {})[row["step"]] = v
    return by_key


def read_series(metrics_path: str, key: str):
    """(steps, values) of one key, in step order."""
    return series(read_metrics(metrics_path), key)


def series(by_key: dict, key: str):
    """(steps, values) of one key of read_metrics' dict, in step order."""
    by_step = by_key.get(key, {})
    steps = sorted(by_step)
    return np.array(steps, dtype=float), np.array([by_step[s] for s in steps], dtype=float)


def load_experiment(folder: str, key: str) -> list:
    """One dict per (run, task) of an experiment folder: task, method, seed, run name, steps and values of `key`."""
    runs = []
    for run_path in sorted(glob.glob(os.path.join(folder, "*", "args.json"))):
        run_path = os.path.dirname(run_path)
        name = os.path.basename(run_path)
        with open(os.path.join(run_path, "args.json")) as f:
            saved = json.load(f)
        parts = re.fullmatch(r"(.+)__(.+)__s(\d+)", name)
        if parts:
            cell, method, seed = parts[1], parts[2], int(parts[3])
        else:
            cell, method, seed = saved.get("task_sequence") or saved["env_id"], saved["method"], saved["seed"]
        if saved.get("preset"):  # another configuration of the method: its own row
            method = f"{method}@{saved['preset']}"
        tasks = [(cell, os.path.join(run_path, "metrics.jsonl"))]
        if not os.path.exists(tasks[0][1]):  # a --task-sequence run: one metrics.jsonl per task
            tasks = [(f"{cell}/{os.path.basename(os.path.dirname(p))}", p)
                     for p in sorted(glob.glob(os.path.join(run_path, "*", "metrics.jsonl")))]
        for task, metrics_path in tasks:
            by_key = read_metrics(metrics_path)  # read once: the key's series and the run's last step
            steps, values = series(by_key, key)
            if len(values) == 0:
                print(f"warning: {metrics_path}: no {key}, left out", file=sys.stderr)
                continue
            if not np.isfinite(values).all():  # one NaN would blank the run's mean and every cell it enters
                print(f"warning: {metrics_path}: a non-finite {key}, left out", file=sys.stderr)
                continue
            # a run stopped before its --total-steps (each task of a sequence trains to it) averages fewer, and
            # usually earlier, weaker episodes: it still counts, marked in the tables
            total_steps = saved.get("total_steps")
            last_step = max(max(by_step) for by_step in by_key.values())  # over every key: some log
            finished = total_steps is None or last_step >= total_steps  # per round or per evaluation, not at the end
            if not finished:
                print(f"warning: {metrics_path}: stopped at step {last_step:,} of --total-steps "
                      f"{total_steps:,}: marked unfinished", file=sys.stderr)
            # the name the run's episodes carry (addressing/pick_fraction/<name>): <k>_<name> of a sequence's folder
            current = (os.path.basename(os.path.dirname(metrics_path)).split("_", 1)[1] if task != cell else
                       (saved.get("task_sequence") or saved["env_id"]).split(",")[0].split("/")[-1])
            runs.append({"task": task, "method": method, "seed": seed, "name": name, "steps": steps, "values": values,
                         "metrics_path": metrics_path, "current_task": current, "total_steps": total_steps,
                         "last_step": last_step, "finished": finished})
    return runs


def key_means(metrics_path: str) -> dict:
    """Each key's mean over the steps it was logged at."""
    return {k: float(np.mean(list(v.values()))) for k, v in read_metrics(metrics_path).items()}


def mean_se(scores) -> tuple:
    """Mean and standard error (sample std with ddof 1, over sqrt(n)); the s.e. of one score is nan."""
    scores = np.asarray(scores, dtype=float)
    se = scores.std(ddof=1) / np.sqrt(len(scores)) if len(scores) > 1 else float("nan")
    return float(scores.mean()), float(se)


def bootstrap_ci(groups: list, statistic, reps: int, seed: int) -> tuple:
    """statistic over score lists of one task (one list, or two for a comparison) and its 95% stratified-bootstrap
    CI (rliable; each list resampled on its own): (point, low, high)."""
    from rliable import library as rly  # imported here: it pulls in arch, statsmodels and pandas (seconds)

    matrices = [np.asarray(g, dtype=float)[:, None] for g in groups]  # (runs, tasks=1) each: rliable's layout
    # rliable 1.2.0 resamples with numpy's global generator (StratifiedBootstrap.update_indices calls
    # np.random.choice) and ignores its random_state, so seed the global one, fresh per cell, and restore it after
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():  # arch warns that rliable passes random_state, which is deprecated there
            warnings.simplefilter("ignore", FutureWarning)
            point, interval = rly.get_interval_estimates(
                {"m": matrices[0] if len(matrices) == 1 else tuple(matrices)},
                lambda *x: np.array([statistic(*x)]), reps=reps, random_state=np.random.RandomState(seed))
    finally:
        np.random.set_state(saved)
    return float(point["m"][0]), float(interval["m"][0, 0]), float(interval["m"][1, 0])


def iqm_ci(scores, reps: int, seed: int) -> tuple:
    """IQM and its 95% stratified-bootstrap CI over runs of one task: (iqm, low, high)."""
    from rliable import metrics

    return bootstrap_ci([scores], metrics.aggregate_iqm, reps, seed)


def improvement_ci(scores_x, scores_y, reps: int, seed: int) -> tuple:
    """P(X > Y), the probability that a run of X scores higher than a run of Y (ties count half: rliable's
    probability of improvement, the Mann-Whitney U over n_x·n_y), with its 95% CI: (p, low, high)."""
    from rliable import metrics

    return bootstrap_ci([scores_x, scores_y], metrics.probability_of_improvement, reps, seed)


def rank_test(scores_x, scores_y) -> float:
    """The two-sided Mann-Whitney (Wilcoxon rank-sum) p-value of X against Y, exact: from the U distribution when no
    two scores tie, else by permutation (every split enumerated for a few runs; seeded beyond). With few runs the
    bootstrap CI of P(X > Y) is too narrow to read as a test (no overlap gives [1, 1] at any size); the rank test's
    smallest p is 2 / C(n_x + n_y, n_x): 0.10 for 3 runs against 3, 0.029 for 4 against 4, 0.008 for 5 against 5."""
    from scipy.stats import PermutationMethod, mannwhitneyu

    pooled = np.concatenate([np.asarray(scores_x, float), np.asarray(scores_y, float)])
    tied = len(np.unique(pooled)) < len(pooled)  # scipy's "exact" ignores ties; a permutation test does not
    method = PermutationMethod(rng=np.random.default_rng(0)) if tied else "exact"
    return float(mannwhitneyu(scores_x, scores_y, alternative="two-sided", method=method).pvalue)


def welch_ci(scores_x, scores_y) -> tuple:
    """mean(X) − mean(Y) with its 95% Welch t confidence interval (unequal variances; the Welch-Satterthwaite
    degrees of freedom): (difference, low, high). The bounds are nan with fewer than 2 runs on a side, or when
    neither side varies."""
    from scipy.stats import ttest_ind

    x, y = np.asarray(scores_x, dtype=float), np.asarray(scores_y, dtype=float)
    difference = float(x.mean() - y.mean())
    if min(len(x), len(y)) < 2 or x.var() + y.var() == 0:
        return difference, float("nan"), float("nan")
    interval = ttest_ind(x, y, equal_var=False).confidence_interval(0.95)
    return difference, float(interval.low), float(interval.high)


def method_order(methods) -> list:
    """The paper's rows in its order, then each preset's in that order, then any other."""
    presets = sorted({m.partition("@")[2] for m in methods} - {""})
    known = [m if not preset else f"{m}@{preset}" for preset in [""] + presets for m in METHOD_NAMES]
    return [m for m in known if m in methods] + sorted(m for m in methods if m not in known)


def fmt(x: float, decimals: int) -> str:
    return "–" if np.isnan(x) else f"{x:,.{decimals}f}"


def write_report(folder: str, out: str, key: str, reps: int, seed: int, bins: int, decimals: int, options: str,
                 beside: tuple = (), reference: dict = None, levels: dict = None, against: tuple = (),
                 only_tasks: tuple = (), same_tasks: dict = None, only_methods: tuple = (), title: str = None):
    runs, same_tasks = load_experiment(folder, key), same_tasks or {}  # same_tasks: {cell: the task it counts as}
    if not runs:
        fail(f"{folder}: no run folders with {key} (expected <run>/args.json and metrics.jsonl)")
    if same_tasks:  # --same-task: a preset's own cells (walk_authors) are columns of the task they ran (walk)
        found = sorted({r["task"] for r in runs})
        for cell in (a for a in same_tasks if a not in found):  # a grid's later cell may not have run yet
            print(f"warning: --same-task {cell}={same_tasks[cell]}: no task {cell} in {folder} (yet? there: "
                  f"{', '.join(found)})", file=sys.stderr)
        runs = [dict(r, task=same_tasks.get(r["task"], r["task"])) for r in runs]
        seen = {}
        for r in runs:  # a merged run must be a row of its own (its method carries the preset): never two seeds in one
            clash = seen.setdefault((r["task"], r["method"], r["seed"]), r["name"])
            if clash != r["name"]:
                fail(f"--same-task: {clash} and {r['name']} would be the same run of {r['task']} "
                         f"({r['method']}, seed {r['seed']}); merge only cells whose methods differ (another --preset)")
    if only_tasks:  # --tasks: the tables' columns only (an experiment also keeps its pilots and its Ms' runs)
        found = sorted({r["task"] for r in runs})
        runs = [r for r in runs if any(fnmatch.fnmatchcase(r["task"], pattern) for pattern in only_tasks)]
        if not runs:
            fail(f"--tasks {' '.join(only_tasks)}: no such task in {folder} (there: {', '.join(found)})")
    experiment = os.path.basename(os.path.normpath(folder))
    tasks = sorted({r["task"] for r in runs})
    for other in beside:  # --beside: another experiment's runs of the same tasks join the tables (--same-task too)
        name = os.path.basename(os.path.normpath(other))  # its runs named `experiment/run` in the Runs table
        joined = [dict(r, name=f"{name}/{r['name']}", task=same_tasks.get(r["task"], r["task"]))
                  for r in load_experiment(other, key)]
        runs += [r for r in joined if r["task"] in tasks]
    methods = method_order({r["method"] for r in runs})
    def refuse_missing(flag: str, named: tuple):
        missing = [m for m in named if m not in methods]
        if missing:
            fail(f"{flag} {' '.join(missing)}: no such method in {folder} (there: {', '.join(methods)})")

    refuse_missing("--methods", only_methods)
    if only_methods:  # the tables' rows and the curves' lines only, in the paper's order
        runs = [r for r in runs if r["method"] in only_methods]
        methods = [m for m in methods if m in only_methods]
        tasks = [t for t in tasks if any(r["task"] == t for r in runs)]
    refuse_missing("--against", against)  # among the rows --methods keeps
    note = " (the paper's metric)" if key == "charts/episodic_return" else ""
    header = ["method"] + [f"{t}: {h}" for t in tasks for h in ("mean ± s.e. (seeds)", "IQM [95% CI]")]
    lines = [f"# {experiment}", "",
             f"Per run: the average of `{key}` over the whole run{note}. Per task and method: the mean "
             f"± standard error over seeds, and the interquartile mean with a 95% stratified-bootstrap confidence "
             f"interval (rliable, {reps} resamples, seed {seed}). With fewer than 4 seeds the IQM equals the mean.",
             f"Made by `python report.py {folder}{options}` from the results alone"
             + (f" (with the runs of {', '.join(f'`{b}`' for b in beside)} of the same tasks)." if beside else "."),
             "",
             "| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    scores = {}  # (task, method) -> each seed's run average, the number both tables start from
    unfinished = {}  # (task, method) -> how many of its runs stopped before their --total-steps
    for r in runs:
        scores.setdefault((r["task"], r["method"]), []).append(r["values"].mean())
        unfinished[(r["task"], r["method"])] = unfinished.get((r["task"], r["method"]), 0) + (not r["finished"])
    for method in methods:
        row = [method_name(method)]
        for task in tasks:
            if (task, method) not in scores:
                row += ["–", "–"]
                continue
            cell = scores[(task, method)]
            mean, se = mean_se(cell)
            iqm, low, high = iqm_ci(cell, reps, seed)
            stopped = unfinished[(task, method)]
            row += [f"{fmt(mean, decimals)} ± {fmt(se, decimals)} ({len(cell)}"
                    + (f"; {stopped} unfinished)" if stopped else ")"),
                    f"{fmt(iqm, decimals)} [{fmt(low, decimals)}, {fmt(high, decimals)}]"]
        lines.append("| " + " | ".join(row) + " |")
    if any(unfinished.values()):
        lines += ["", "*unfinished*: runs stopped before their `--total-steps` (the Runs table says where); their "
                  "averages hold fewer, mostly earlier episodes."]
    lines += ["", "Each seed's run average, and the mean ± s.e. over seeds:", "", "![scores per run](scores.png)"]
    lines += improvement_table(scores, tasks, methods, reps, seed, against)
    differences = welch_differences(scores, tasks, methods, against)
    lines += difference_table(differences, tasks, methods, decimals, against)
    lines += diagnostics_table(runs, tasks, methods, decimals)
    lines += pick_task_table(runs, tasks, methods)
    lines += pick_source_table(runs, tasks, methods)
    lines += stalled_table(runs, tasks, methods)
    lines += reference_table(runs, tasks, methods, reference, decimals) if reference else []
    lines += levels_table(runs, tasks, methods, key, levels, decimals) if levels else []
    figure = "curves.png"
    lines += ["", f"![learning curves]({figure})", "", "## Runs", "",
              "| run | task | episodes | last env step | average return |", "| --- | --- | --- | --- | --- |"]
    lines += [f"| {r['name']} | {r['task']} | {len(r['values'])} | {int(r['steps'][-1]):,}"
              + ("" if r["finished"] else f" (unfinished: stopped at {r['last_step']:,} of {r['total_steps']:,})")
              + f" | {fmt(r['values'].mean(), decimals)} |" for r in runs]
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "report.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    plot_curves(runs, tasks, methods, key, bins, title or f"{experiment}: {key} (mean ± s.e. over seeds)",
                os.path.join(out, figure), reference, levels)
    plot_scores(scores, tasks, methods, f"{experiment}: the average of {key} per run", key,
                os.path.join(out, "scores.png"))
    for task, method, column, cell, ref in differences:  # the intervals the docs quote, on the terminal too
        print(f"{task}: {method_name(method)} − {method_name(ref)}{' (paper text)' if column == PAPER_TEXT else ''}: "
              f"{difference_text(cell, decimals)} (Welch 95%)")
    print(f"wrote {os.path.join(out, 'report.md')}, {os.path.join(out, figure)} and {os.path.join(out, 'scores.png')}")


def comparison_references(methods: list, against: tuple = ()) -> list:
    """The columns every row is compared with: Dreamer, uniform mixing, uniform mixing under each preset (the same
    configuration as the preset's rows), and the methods given with --against."""
    references = [m for m in ["dreamer", "uniform"] + [m for m in methods if m.startswith("uniform@")] if m in methods]
    return references + [m for m in against if m not in references]


PAPER_TEXT = "paper text"  # the column of a preset's row against the same method without the preset


def comparison_columns(methods: list, against: tuple = ()) -> list:
    """comparison_references, then PAPER_TEXT when some preset's method also ran without the preset (and is not a
    column already: uniform mixing's is its own)."""
    references = comparison_references(methods, against)
    return references + [PAPER_TEXT] * any(compared_with(m, PAPER_TEXT, references) in methods for m in methods)


def compared_with(method: str, column: str, references: list):
    """The method a row is compared with in a column: the column's method, or for PAPER_TEXT the row's method without
    its preset (None for a row without a preset, or when that method is a column of its own)."""
    if column != PAPER_TEXT:
        return column
    base = method.partition("@")[0]
    return base if base != method and base not in references else None


def comparisons(scores: dict, tasks: list, methods: list, against: tuple = ()):
    """(task, method, column, scores of the row, scores of the method compared with) for every cell of the comparison
    tables that has runs on both sides."""
    columns = comparison_columns(methods, against)
    for task in tasks:
        for method in methods:
            for column in columns:
                ref = compared_with(method, column, columns)
                x, y = scores.get((task, method)), scores.get((task, ref))
                if method != ref and x and y:
                    yield task, method, column, x, y, ref


def comparison_table(cells: dict, tasks: list, methods: list, columns: list, name, intro: str) -> list:
    """Markdown lines of a comparison table: a row per method, a column per task and comparison column; cells:
    (task, method, column) -> its text ("–" where absent); name(column) -> the column's header."""
    header = ["method"] + [f"{t}: {name(c)}" for t in tasks for c in columns]
    lines = ["", intro, "", "| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for method in methods:
        lines.append("| " + " | ".join([method_name(method)] + [cells.get((t, method, c), "–") for t in tasks
                                                                 for c in columns]) + " |")
    return lines


def improvement_table(scores: dict, tasks: list, methods: list, reps: int, seed: int, against: tuple = ()) -> list:
    """Markdown lines: per task, each method's probability of improvement over Dreamer and over uniform mixing (and
    over the --against methods, and a preset's over the same method without it), with its bootstrap CI and the rank
    test's p. scores: (task, method) -> the run averages of its seeds."""
    columns = comparison_columns(methods, against)
    if not columns or len(methods) < 2:
        return []
    cells = {}
    for task, method, column, x, y, _ in comparisons(scores, tasks, methods, against):
        p, low, high = improvement_ci(x, y, reps, seed)  # probabilities: 2 decimals, whatever --decimals
        cells[(task, method, column)] = f"{p:.2f} [{low:.2f}, {high:.2f}], p {rank_test(x, y):.2g}"
    intro = ("Does a method beat Dreamer, or uniform mixing? P(X > Y) is the probability that a run of the row's "
             "method scores higher than a run of the column's (ties count half; rliable's probability of "
             f"improvement), with its 95% stratified-bootstrap CI (percentile, {reps} resamples, seed {seed}), and "
             "p, the two-sided Mann-Whitney rank test's (exact). 0.5 is no difference. Read p, not the CI, as the "
             "test: over so few runs the bootstrap CI is too narrow (when no run of one method scores below a run of "
             "the other, every resample gives the same P, so the CI is [1.00, 1.00] even for 2 runs against 2). The "
             "smallest possible p is 0.10 for 3 runs against 3, 0.029 for 4 against 4, 0.008 for 5 against 5."
             + PAPER_TEXT_NOTE * (PAPER_TEXT in columns))
    return comparison_table(cells, tasks, methods, columns, lambda c: f"P(> {column_name(c)})", intro)


PAPER_TEXT_NOTE = (" *paper text*: a preset's row against the same method without the preset (uniform mixing's is "
                   "its uniform column).")


def column_name(column: str) -> str:
    return column if column == PAPER_TEXT else method_name(column)


def welch_differences(scores: dict, tasks: list, methods: list, against: tuple = ()) -> list:
    """Every difference of means the report gives, one per cell of the comparison tables: (task, method, column,
    (difference, low, high) with its Welch 95% CI, the method compared with)."""
    return [(task, method, column, welch_ci(x, y), ref)
            for task, method, column, x, y, ref in comparisons(scores, tasks, methods, against)]


def difference_table(differences: list, tasks: list, methods: list, decimals: int, against: tuple = ()) -> list:
    """Markdown lines: per task, each method's mean minus each comparison column's, with its Welch 95% CI."""
    columns = comparison_columns(methods, against)
    if not differences:
        return []
    cells = {(task, method, column): difference_text(cell, decimals) for task, method, column, cell, _ in differences}
    intro = ("Differences of means: the row's mean over seeds minus the column's, with its 95% Welch t confidence "
             "interval (unequal variances, Welch-Satterthwaite degrees of freedom; – bounds with fewer than 2 runs on "
             "a side)." + PAPER_TEXT_NOTE * (PAPER_TEXT in columns))
    return comparison_table(cells, tasks, methods, columns, lambda c: f"− {column_name(c)}", intro)


def difference_text(cell: tuple, decimals: int) -> str:
    """(difference, low, high) -> "+2.0 [-1.5, 5.5]"."""
    difference, low, high = cell
    return f"{difference:+,.{decimals}f} [{fmt(low, decimals)}, {fmt(high, decimals)}]"


def run_diagnostics(means: dict, current_task: str) -> dict:
    """What one run's mixed batches borrowed, from its metrics' means over rounds (nan where it logged nothing)."""
    get = lambda k: means.get(f"addressing/{k}", float("nan"))  # noqa: E731
    picked_any = any(k.startswith("addressing/pick_fraction/") for k in means)
    own_share = means.get(f"addressing/pick_fraction/{current_task}", 0.0)
    return {"mixed": get("mixed_batches"), "other_tasks": 1.0 - own_share if picked_any else float("nan"),
            "picked_return": get("picked_return"), "candidate_return": get("candidate_return"),
            "picked_chunk": get("picked_chunk_reward"), "candidate_chunk": get("candidate_chunk_reward"),
            "entropy": get("entropy") / get("entropy_uniform"),
            "bandit_gain": get("bandit_reward_q") - get("bandit_reward_uniform")}


def diagnostics_table(runs: list, tasks: list, methods: list, decimals: int) -> list:
    """Markdown lines: per task and prior-data method, what its mixed batches borrowed, the mean over seeds of each
    run's mean over its rounds of updates (the addressing/ keys); none when no run logged them."""
    cells = {}  # (task, method) -> [run_diagnostics of each seed]
    for r in runs:
        if r["method"] != "dreamer":
            cells.setdefault((r["task"], r["method"]), []).append(run_diagnostics(key_means(r["metrics_path"]),
                                                                                  r["current_task"]))
    if not cells or all(np.isnan(d["mixed"]) for diags in cells.values() for d in diags):
        return []

    def mean(diags, key, digits):
        values = [d[key] for d in diags if not np.isnan(d[key])]
        return fmt(float(np.mean(values)), digits) if values else "–"

    lines = ["", "What the prior-data methods mixed in (the addressing/ logs: each run's mean over its rounds of "
             "updates, then the mean over its seeds). *Mixed batches*: the fraction of updates whose batch took "
             "chunks of M (p). *From other tasks*: the fraction of those chunks from episodes of another task than "
             "the run's own. *Return, picked / M*: the stored return of the episodes the picks came from, against "
             "M's (the scored candidates' for the addressed methods). *Chunk reward*: the same for the picked chunks' "
             "stored reward sums. *Entropy*: q's entropy over the m scored chunks as a fraction of a uniform q's "
             "(1: no preference). *Bandit gain*: RRAMa's and RbRAMa's predicted reward sum of a pick under q minus a "
             "uniform pick's (what their objective raises).", "",
             "| task | method | runs | mixed batches | from other tasks | return, picked / M | chunk reward, picked / "
             "candidates | entropy / uniform's | bandit gain |", "|" + " --- |" * 9]
    for task in tasks:
        for method in methods:
            diags = cells.get((task, method))
            if not diags:
                continue
            lines.append(f"| {task} | {method_name(method)} | {len(diags)} | "
                         f"{mean(diags, 'mixed', 2)} | {mean(diags, 'other_tasks', 2)} | "
                         f"{mean(diags, 'picked_return', decimals)} / {mean(diags, 'candidate_return', decimals)} | "
                         f"{mean(diags, 'picked_chunk', decimals)} / {mean(diags, 'candidate_chunk', decimals)} | "
                         f"{mean(diags, 'entropy', 2)} | {mean(diags, 'bandit_gain', decimals)} |")
    return lines


def stalled_rounds(metrics_path: str) -> tuple:
    """(the share of a run's rounds whose mean gradient norm of f_φ was below 1% of its first round's, the env step of
    the first such round or None); (nan, None) for a run without f_φ. Below 1%, f_φ has all but stopped learning:
    its GRU's update gates sit at exactly 0 or 1 (tools/addressing_offline.py's pinned gates)."""
    steps, norms = read_series(metrics_path, "addressing/grad_norm")
    if len(norms) == 0:
        return float("nan"), None
    stalled = norms < 0.01 * norms[0]
    return float(stalled.mean()), int(steps[stalled][0]) if stalled.any() else None


def stalled_table(runs: list, tasks: list, methods: list) -> list:
    """Markdown lines: per task and addressed method, the mean over seeds of stalled_rounds' share, and each seed's
    first stalled round; none when no run logged f_φ's gradient."""
    cells = {}  # (task, method) -> [(share, first step) of each seed]
    for r in runs:
        share, first = stalled_rounds(r["metrics_path"])  # nan for a run without f_φ (Dreamer, uniform)
        if not np.isnan(share):
            cells.setdefault((r["task"], r["method"]), []).append((share, first))
    if not cells:
        return []
    lines = ["", "Did f_φ keep learning? *Stalled rounds*: the share of a run's rounds of updates whose mean gradient "
             "norm of f_φ was below 1% of its first round's (the mean over seeds); *first stalled*: the env step of "
             "each seed's first such round (– if none).", "",
             "| task | method | runs | stalled rounds | first stalled (each seed) |", "|" + " --- |" * 5]
    for task in tasks:
        for method in methods:
            diags = cells.get((task, method))
            if diags:
                firsts = "; ".join("–" if first is None else f"{first:,}" for _, first in diags)
                lines.append(f"| {task} | {method_name(method)} | {len(diags)} | "
                             f"{fmt(float(np.mean([share for share, _ in diags])), 2)} | {firsts} |")
    return lines


def pick_source_table(runs: list, tasks: list, methods: list) -> list:
    """Markdown lines: per task and prior-data method, the share of the mixed batches' picks by the policy that
    collected the picked episode (addressing/pick_source/<policy>: `expert` and `random` for a scripted M, `agent`
    for a learning run's episodes), each run's mean over its rounds, then the mean over seeds; none when no run
    logged them (runs before 2026-12-07, or an M of one policy)."""
    return share_table(runs, tasks, methods, "addressing/pick_source/", "Where the picks came from: the share of the "
                       "mixed batches' borrowed chunks by the policy that collected their episode (each run's mean "
                       "over its rounds, then the mean over its seeds).")


def pick_task_table(runs: list, tasks: list, methods: list) -> list:
    """Markdown lines: the same by the task of the picked episode (addressing/pick_fraction/<task>), where M holds
    episodes of three tasks or more (with two, "from other tasks" in the diagnostics table says it all)."""
    return share_table(runs, tasks, methods, "addressing/pick_fraction/", "Which tasks the picks came from: the "
                       "share of the mixed batches' borrowed chunks by the task of their episode (each run's mean "
                       "over its rounds, then the mean over its seeds).", min_sources=3)


def share_table(runs: list, tasks: list, methods: list, prefix: str, intro: str, min_sources: int = 1) -> list:
    """Markdown lines: per task and prior-data method, the mean over seeds of each run's mean over its rounds of the
    metrics named prefix + <source>, a column per source (a run that never logged a source counts 0 for it); none
    when fewer than min_sources sources were logged."""
    cells = {}  # (task, method) -> [each seed's {source: mean share}]
    for r in runs:
        means = key_means(r["metrics_path"]) if r["method"] != "dreamer" else {}
        shares = {k[len(prefix):]: v for k, v in means.items() if k.startswith(prefix)}
        if shares:
            cells.setdefault((r["task"], r["method"]), []).append(shares)
    sources = sorted({name for diags in cells.values() for shares in diags for name in shares})
    if len(sources) < max(min_sources, 1):
        return []
    lines = ["", intro, "", "| task | method | runs | " + " | ".join(sources) + " |",
             "|" + " --- |" * (3 + len(sources))]
    for task in tasks:
        for method in methods:
            diags = cells.get((task, method))
            if diags:
                shares = [fmt(float(np.mean([d.get(name, 0.0) for d in diags])), 2) for name in sources]
                lines.append(f"| {task} | {method_name(method)} | {len(diags)} | " + " | ".join(shares) + " |")
    return lines


def reference_table(runs: list, tasks: list, methods: list, reference: dict, decimals: int) -> list:
    """Each task's runs at the reference's checkpoints against the reference's mean ± std, and how many seeds lie
    within its mean ± 2 std. A run's value at a checkpoint c: the mean of its values logged in (c - window, c] when
    the reference is binned so (its "window"), else its value at the logged step nearest c (within 10% of it)."""
    window = reference.get("window")
    how = (f"mean of its values logged in the {window:,.0f} env steps up to each checkpoint, as the reference's are"
           if window else "value at its logged step nearest each checkpoint (within 10%)")
    lines = ["", f"## Against {reference['name']}", "",
             f"Each run's `{reference['key']}`: the {how}; against {reference['name']}'s mean ± std over its seeds "
             f"({reference['source']}). A run within the reference's mean ± 2 std is consistent with it.", "",
             "| task | method | checkpoint | runs: mean ± std (seeds) | steps used | reference: mean ± std (seeds) | "
             "runs within ± 2 std |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for task in tasks:
        ref = task_reference(runs, task, reference)
        for method in methods if ref else []:
            for checkpoint in reference["checkpoints"]:
                i = ref["steps"].index(checkpoint)
                low, high = ref["mean"][i] - 2 * ref["std"][i], ref["mean"][i] + 2 * ref["std"][i]
                picked, used = [], set()  # each run's value at the checkpoint; the steps it came from
                for r in (r for r in runs if r["task"] == task and r["method"] == method):
                    near = (r["steps"] > checkpoint - window) & (r["steps"] <= checkpoint) if window else \
                        np.arange(len(r["steps"])) == np.argmin(np.abs(r["steps"] - checkpoint))
                    if near.any() and (window or abs(r["steps"][near][0] - checkpoint) <= 0.1 * checkpoint):
                        picked.append(r["values"][near].mean())
                        used.update(int(s) for s in r["steps"][near])
                if not picked:
                    continue
                values = np.array(picked)
                lines.append(f"| {task} | {method_name(method)} | {checkpoint:,} | {fmt(values.mean(), decimals)} ± "
                             f"{fmt(values.std(), decimals)} ({len(values)}) | "
                             f"{', '.join(f'{s:,}' for s in sorted(used))} | "
                             f"{fmt(ref['mean'][i], decimals)} ± {fmt(ref['std'][i], decimals)} ({ref['seeds'][i]}) | "
                             f"{int(((values >= low) & (values <= high)).sum())} of {len(values)} |")
    return lines


def task_reference(runs: list, task: str, reference: dict = None):
    """The reference's curve of a task (by the name its runs' episodes carry), or None."""
    current = {r["current_task"] for r in runs if r["task"] == task}
    return next((reference["tasks"][c] for c in current if c in reference["tasks"]), None) if reference else None


LAST_VALUES = 10  # --levels: a run is scored by the mean of its last this many values of the key


def task_levels(levels: dict, task: str, key: str) -> dict:
    """A task's fixed-policy levels for `key` (--levels, as tools/family_references.py writes them): {policy: (value,
    s.e., episodes)}; a key's level is the entry named by its last part without `episodic_` (return, success_rate)."""
    name = key.split("/")[-1].removeprefix("episodic_")
    return {policy: (entry[name], entry.get(f"{name}_se", float("nan")), entry.get("episodes", 0))
            for policy, entry in (levels or {}).get(task, {}).items() if name in entry}


def levels_table(runs: list, tasks: list, methods: list, key: str, levels: dict, decimals: int) -> list:
    """Each task's runs, scored by their last values, against fixed policies' levels (a random policy, a scripted
    expert): the mean ± s.e. over seeds, and the fraction of the way from `random` to `expert` when both are given."""
    lines = ["", "## Against fixed policies", "",
             f"Each run's mean of its last {LAST_VALUES} values of `{key}`; per method the mean ± s.e. over seeds, "
             f"against the levels of fixed policies (value ± s.e. over their episodes). `random → expert`: "
             f"(runs − random) / (expert − random), 0 at the random policy's level and 1 at the expert's.", "",
             "| task | method | runs: last values, mean ± s.e. (seeds) | last env steps | fixed policies | "
             "random → expert |", "| --- | --- | --- | --- | --- | --- |"]
    for task in tasks:
        levels_here = task_levels(levels, task, key)
        for method in methods if levels_here else []:
            cell = [r for r in runs if r["task"] == task and r["method"] == method]
            if not cell:
                continue
            mean, se = mean_se([r["values"][-LAST_VALUES:].mean() for r in cell])
            shown = ", ".join(f"{policy} {fmt(v, decimals)} ± {fmt(e, decimals)} ({n})"
                              for policy, (v, e, n) in levels_here.items())
            fraction = "–"
            if {"random", "expert"} <= set(levels_here) and levels_here["expert"][0] != levels_here["random"][0]:
                fraction = fmt((mean - levels_here["random"][0]) / (levels_here["expert"][0] -
                                                                    levels_here["random"][0]), 2)
            last_steps = ", ".join(f"{int(r['steps'][-1]):,}" for r in cell)
            lines.append(f"| {task} | {method_name(method)} | {fmt(mean, decimals)} ± {fmt(se, decimals)} ({len(cell)})"
                         f" | {last_steps} | {shown} | {fraction} |")
    return lines


def task_panels(count: int, panel_width: float, panel_height: float, extra_width: float = 0.0, **subplots_kw):
    """A figure with one panel per task, three to a row: (fig, axes (rows, cols))."""
    cols = min(3, count)
    rows = (count + cols - 1) // cols
    return plt.subplots(rows, cols, figsize=(panel_width * cols + extra_width, panel_height * rows), squeeze=False,
                        **subplots_kw)


def method_colour(methods: list, method: str) -> str:
    """A method keeps its colour in every panel and in both figures."""
    return f"C{methods.index(method) % 10}"


def metric_label(key: str) -> str:
    """charts/episodic_return -> episodic return."""
    return key.split("/")[-1].replace("_", " ")


def save_panels(fig, axes, used: int, title: str, path: str):
    """A figure of task panels to a PNG: the panels past the first `used` blanked, the title on top."""
    for ax in axes.flat[used:]:
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_curves(runs: list, tasks: list, methods: list, key: str, bins: int, title: str, path: str,
                reference: dict = None, levels: dict = None):
    """One panel per task; per method, the mean over seeds of each run's bin averages, with a ± s.e. band; a
    reference curve of the task, if given, as a grey mean ± std band; fixed policies' levels as dotted lines."""
    fig, axes = task_panels(len(tasks), 5, 3.5)
    for ax, task in zip(axes.flat, tasks):
        edges = np.linspace(0, max(r["steps"].max() for r in runs if r["task"] == task), bins + 1)
        centres = (edges[:-1] + edges[1:]) / 2
        for method in methods:
            curves = []  # (runs, bins): each run's mean return per bin, nan where it has no episode
            for r in (r for r in runs if r["task"] == task and r["method"] == method):
                which = np.clip(np.searchsorted(edges, r["steps"], side="left") - 1, 0, bins - 1)
                sums, counts = np.bincount(which, r["values"], bins), np.bincount(which, minlength=bins)
                curves.append(np.where(counts > 0, sums / np.maximum(counts, 1), np.nan))
            if not curves:
                continue
            curves = np.array(curves)
            n = (~np.isnan(curves)).sum(0)
            with warnings.catch_warnings():  # bins with no run are nan and are not drawn
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = np.nanmean(curves, 0)
                se = np.where(n > 1, np.nanstd(curves, 0, ddof=1) / np.sqrt(np.maximum(n, 1)), 0.0)
            keep = n > 0  # bins where some run ended an episode: joined by the line
            colour = method_colour(methods, method)
            ax.plot(centres[keep], mean[keep], color=colour, label=f"{method_name(method)} ({len(curves)})",
                    marker="." if keep.sum() < 20 else None)
            ax.fill_between(centres[keep], (mean - se)[keep], (mean + se)[keep], color=colour, alpha=0.2)
        ref = task_reference(runs, task, reference)
        if ref:
            ref_steps, mean, std = (np.array(ref[k]) for k in ("steps", "mean", "std"))
            shown = ref_steps <= edges[-1] * 1.05  # the reference as far as the runs go
            ax.plot(ref_steps[shown], mean[shown], "k--", label=f"{reference['name']} (mean ± std)")
            ax.fill_between(ref_steps[shown], (mean - std)[shown], (mean + std)[shown], color="grey", alpha=0.25)
        for i, (policy, (value, _, episodes)) in enumerate(task_levels(levels, task, key).items()):
            ax.axhline(value, color=f"{0.6 * (i % 2)}", linestyle=":", label=f"{policy} policy ({episodes} episodes)")
        ax.set_title(task, fontsize=9)
        ax.set_xlabel("environment steps")
        ax.set_ylabel(metric_label(key))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    save_panels(fig, axes, len(tasks), title, path)


def plot_scores(scores: dict, tasks: list, methods: list, title: str, key: str, path: str) -> dict:
    """One panel per task, one row per method (the tables' order, top down, the same row in every panel): a dot per
    seed's run average and the mean ± s.e. over seeds as a bar, so that a row's seeds can be read against every
    other row's. Returns what each panel drew: task -> [(method, its seeds' scores)]."""
    rows = {t: [(m, scores[(t, m)]) for m in methods if (t, m) in scores] for t in tasks}
    fig, axes = task_panels(len(tasks), 4.5, 0.3 * len(methods) + 1.2, extra_width=2.5, sharey=True)
    for ax, task in zip(axes.flat, tasks):
        for method, values in rows[task]:
            y, colour = -methods.index(method), method_colour(methods, method)
            mean, se = mean_se(values)
            ax.errorbar(mean, y, xerr=se if len(values) > 1 else None, fmt="|", color=colour, markersize=14,
                        capsize=3)
            ax.plot(values, [y] * len(values), "o", color=colour, alpha=0.6, markersize=4)
        ax.set_title(task, fontsize=9)
        ax.set_xlabel(metric_label(key) + " (average over the run)", fontsize=8)
        ax.grid(alpha=0.3, axis="x")
    axes[0, 0].set_yticks([-i for i in range(len(methods))])
    axes[0, 0].set_yticklabels([method_name(m).replace("`", "") for m in methods])
    for ax in axes[:, 0]:  # the shared labels, on each row of panels
        ax.tick_params(axis="y", labelsize=7)
    axes[0, 0].set_ylim(-len(methods) + 0.5, 0.5)
    save_panels(fig, axes, len(tasks), title, path)
    return rows


def plot_runs(run_paths: list, out: str, title, keys=None):
    """Single runs' curves against environment steps, in one figure: their training and evaluation returns, or
    (keys) one panel per metric, e.g. losses/kl and charts/imagined_return beside the returns."""
    fig, axes = plt.subplots(1, len(keys or [None]), figsize=(7 if not keys or len(keys) == 1 else 4.5 * len(keys), 4),
                             squeeze=False)
    runs = []  # (metrics.jsonl, label) per run, checked once before any panel is drawn
    for run_path in run_paths:
        metrics_path = os.path.join(run_path, "metrics.jsonl")
        if not os.path.isfile(metrics_path):
            fail(f"{run_path}: no metrics.jsonl (not a run folder)")
        runs.append((metrics_path, os.path.basename(os.path.normpath(run_path))))
    for ax, key in zip(axes.flat, keys or [None]):
        drawn = 0
        for metrics_path, label in runs:
            lines = [(key, dict(lw=1), label)] if key else [
                ("charts/episodic_return", dict(alpha=0.5, lw=1), f"charts — {label}"),
                ("eval/episodic_return", dict(marker="o"), f"eval — {label}")]
            for series_key, style, series_label in lines:
                steps, values = read_series(metrics_path, series_key)
                if len(steps):
                    ax.plot(steps, values, label=series_label[:70], **style)
                    drawn += 1
        if key and not drawn:
            fail(f"--key {key}: no run's metrics.jsonl logs it")
        ax.set_xlabel("environment steps")
        ax.set_ylabel(metric_label(key) if key else "episode return")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title or runs[0][1][:80], fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    print(f"wrote {out}")


def addressing_figure(probs: np.ndarray, tasks: list, returns: np.ndarray, title: str, chunk_rewards=None):
    """The scripts' --address-plot-every picture (they import it from here): a heat map of q̂(j | x_i), rows =
    current chunks, columns = candidates sorted by task then stored return.
    Below it: each candidate's episode return and, if given, the chunk's own reward sum."""
    order = np.lexsort((returns, np.array(tasks)))
    rows = 2 if chunk_rewards is None else 3
    fig, axes = plt.subplots(rows, 1, figsize=(9, 3.5 + rows), sharex=True, height_ratios=[4] + [1] * (rows - 1))
    ax, ax_ret = axes[0], axes[1]
    # log-ratio to the uniform distribution: red = picked more often than uniform, blue = less
    ratio = np.log10(np.maximum(probs[:, order] * probs.shape[1], 1e-12))
    image = ax.imshow(ratio, aspect="auto", interpolation="nearest", cmap="RdBu_r", vmin=-2, vmax=2)
    fig.colorbar(image, ax=list(axes), label="log10(q̂(j | x_i) / uniform)")
    sorted_tasks = [tasks[i] for i in order]
    for i in range(1, len(order)):  # task boundaries
        if sorted_tasks[i] != sorted_tasks[i - 1]:
            for a in axes:
                a.axvline(i - 0.5, color="white" if a is ax else "gray", lw=1)
    for task in dict.fromkeys(sorted_tasks):
        idx = [i for i, t in enumerate(sorted_tasks) if t == task]
        ax.text(np.mean(idx), -0.8, task, ha="center", va="bottom", fontsize=8)
    ax.set_ylabel("current chunk x_i")
    ax.set_title(title, pad=14)
    ax_ret.plot(np.arange(len(order)), returns[order], lw=1)
    ax_ret.set_ylabel("episode\nreturn", fontsize=8)
    if chunk_rewards is not None:
        axes[2].scatter(np.arange(len(order)), chunk_rewards[order], s=1)
        axes[2].set_ylabel("chunk\nreward", fontsize=8)
    axes[-1].set_xlabel("candidate chunk j (sorted by task, then stored episode return)")
    return fig


def main():
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="*", help="experiment folders (results/<experiment>), or results/ itself")
    parser.add_argument("--out", default=None, help="where to write (default: each experiment's folder); "
                        "with --runs, the PNG to write (default curve.png)")
    parser.add_argument("--runs", nargs="+", default=None, help="instead: draw these run folders' curves in one PNG")
    parser.add_argument("--title", default=None, help="the figure's title: with --runs (default: the first run's "
                        "name), or the learning curves' of an experiment's report")
    parser.add_argument("--key", nargs="+", default=None, help="the metric (default charts/episodic_return; e.g. "
                        "eval/episodic_return, charts/success_rate); with --runs, one panel per key given (e.g. "
                        "losses/kl charts/imagined_return) instead of the returns")
    parser.add_argument("--reps", type=int, default=2000, help="bootstrap resamples per task and method")
    parser.add_argument("--seed", type=int, default=0, help="the bootstrap's seed")
    parser.add_argument("--bins", type=int, default=50, help="curves: bins of environment steps")
    parser.add_argument("--decimals", type=int, default=1, help="decimals in the tables")
    parser.add_argument("--reference", default=None, metavar="FILE", help="a published curve to draw and tabulate "
                        "against (JSON, as tools/dreamer_v1_reference.py writes it)")
    parser.add_argument("--levels", default=None, metavar="FILE", help="fixed policies' levels to draw and tabulate "
                        "against, per task (JSON, as tools/family_references.py writes it)")
    parser.add_argument("--beside", nargs="+", default=[], metavar="FOLDER",
                        help="other experiment folders whose runs of the same tasks join the tables (e.g. the same "
                             "grid under another --preset)")
    parser.add_argument("--tasks", nargs="+", default=[], metavar="PATTERN",
                        help="only these tasks (the <cell> of <cell>__<method>__s<seed>; shell-style patterns, e.g. "
                             "'walk*'): the tables' columns without an experiment's pilots and priors")
    parser.add_argument("--against", nargs="+", default=[], metavar="METHOD",
                        help="methods (as the report names them in its folders: vrama, vrama@authors-code) to compare "
                             "every row with, beside Dreamer and uniform mixing")
    parser.add_argument("--methods", nargs="+", default=[], metavar="METHOD",
                        help="only these rows (methods as the report names them in its folders: dreamer, uniform, "
                             "rrama@authors-code), in the tables and the curves")
    parser.add_argument("--same-task", nargs="+", default=[], metavar="CELL=TASK",
                        help="count CELL's runs as TASK's (e.g. walk_authors=walk: a cell of --preset runs, whose "
                             "rows stay apart by their method's preset, beside the same task's Dreamer and uniform; "
                             "in --beside folders too)")
    args = parser.parse_args()
    for name, least in (("reps", 1), ("bins", 1), ("decimals", 0)):  # checked before anything is written
        if getattr(args, name) < least:
            parser.error(f"argument --{name}: must be >= {least} (got {getattr(args, name)})")
    bad = [pair for pair in args.same_task if not re.fullmatch(r"[^=\s]+=[^=\s]+", pair)]
    if bad:
        parser.error(f"--same-task {bad[0]}: give CELL=TASK, e.g. walk_authors=walk")
    same_tasks = dict(pair.split("=") for pair in args.same_task)
    if args.runs and (args.against or args.methods):
        parser.error("--against and --methods: for the tables of an experiment folder, not with --runs")
    if args.runs:
        return plot_runs(args.runs, args.out or "curve.png", args.title, args.key)
    if args.key and len(args.key) > 1:
        parser.error("--key: one metric for the tables (several only with --runs)")
    args.key = args.key[0] if args.key else "charts/episodic_return"
    if not args.folders:
        parser.error("give experiment folders (results/<experiment>) or --runs")
    # the options that change the report, for its "Made by" line
    options = (f" --key {args.key}" if args.key != "charts/episodic_return" else "") + "".join(
        f" --{name} {getattr(args, name)}" for name in ("reps", "seed", "bins", "decimals")
        if getattr(args, name) != parser.get_default(name))
    options += f" --beside {' '.join(args.beside)}" if args.beside else ""  # one flag: a second --beside replaces
    options += f" --against {' '.join(args.against)}" if args.against else ""
    options += f" --tasks {' '.join(shlex.quote(t) for t in args.tasks)}" if args.tasks else ""
    options += f" --same-task {' '.join(args.same_task)}" if args.same_task else ""
    options += f" --methods {' '.join(args.methods)}" if args.methods else ""
    options += f" --title {shlex.quote(args.title)}" if args.title else ""
    reference = None
    if args.reference:
        try:
            with open(args.reference) as f:
                reference = json.load(f)
            assert {"name", "key", "checkpoints", "source", "tasks"} <= set(reference)
        except (OSError, ValueError, AssertionError) as e:
            fail(f"--reference {args.reference}: not a reference file ({type(e).__name__})")
        if reference["key"] != args.key:
            fail(f"--reference {args.reference} holds {reference['key']}: give --key {reference['key']}")
        options += f" --reference {args.reference}"
    levels = None
    if args.levels:
        try:
            with open(args.levels) as f:
                levels = json.load(f)
            assert isinstance(levels, dict) and all(isinstance(v, dict) and all(isinstance(p, dict) for p in v.values())
                                                    for v in levels.values())  # task -> policy -> {metric: value}
        except (OSError, ValueError, AssertionError) as e:
            fail(f"--levels {args.levels}: not a levels file ({type(e).__name__})")
        options += f" --levels {args.levels}"
    for folder in args.beside:
        if not glob.glob(os.path.join(folder, "*", "args.json")):
            fail(f"--beside {folder}: holds no run folders (<run>/args.json)")
    for folder in args.folders:
        if not os.path.isdir(folder):
            fail(f"{folder}: no such folder")
        # results/ itself holds experiments (folders of run folders) rather than run folders; a run folder kept there
        # beside them (results/gpu_pixel_cartpole) is left out, with a line saying so
        runs = glob.glob(os.path.join(folder, "*", "args.json"))
        experiments = sorted({os.path.dirname(os.path.dirname(p))
                              for p in glob.glob(os.path.join(folder, "*", "*", "args.json"))})
        if runs and experiments:
            print(f"{folder}: left out, run folders rather than experiments (report them with --runs): "
                  + " ".join(sorted(os.path.dirname(p) for p in runs)), file=sys.stderr)
        experiments = experiments or ([folder] if runs else [])
        if not experiments:
            fail(f"{folder}: holds no run folders (<run>/args.json) and no experiments")
        # --against names one experiment's methods and --tasks its tasks: refused before any report is written
        one_experiment = [f"--{name.replace('_', '-')}" for name in ("against", "tasks", "same_task", "methods")
                          if getattr(args, name)]
        if one_experiment and (len(experiments) > 1 or len(args.folders) > 1):
            fail(f"{' and '.join(one_experiment)}: give one experiment folder (it names that experiment's "
                     f"methods or tasks)")
        for experiment in experiments:
            out = args.out if args.out and len(experiments) == 1 else \
                os.path.join(args.out, os.path.basename(experiment)) if args.out else experiment
            write_report(experiment, out, args.key, args.reps, args.seed, args.bins, args.decimals,
                         options + (f" --out {out}" if args.out else ""), tuple(args.beside), reference, levels,
                         tuple(args.against), tuple(args.tasks), same_tasks, tuple(args.methods), args.title)


if __name__ == "__main__":
    main()
