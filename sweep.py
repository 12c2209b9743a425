"""Run an experiment grid (cells x methods x seeds, with dependencies) of the training scripts, from a TOML spec.

    python sweep.py sweeps/cartpole_tables.toml --dry-run                # print each run's command, run nothing
    python sweep.py sweeps/cartpole_tables.toml --workers 2              # 2 runs at a time, OMP_NUM_THREADS = cores / 2
    OMP_NUM_THREADS=1 python sweep.py sweeps/cartpole_tables.toml        # a given OMP_NUM_THREADS is kept: cores shared
    python sweep.py sweeps/cartpole_tables.toml --ray-address auto       # each run a Ray task on a running cluster
    python sweep.py sweeps/walker_tables.toml --workers 4 --max-runs 4   # a grid in parts: 4 runs still to do
    python sweep.py sweeps/walker_tables.toml --collect                  # copy done runs' results again, run nothing

The spec (see sweeps/*.toml) names the script, the flags common to every run, and cells. A cell has its own flags
(and may name its own `script`, e.g. rama_metaworld.py beside rama_dreamer.py cells),
its methods and seeds, and optionally `prior`: a cell above (`prior`) or one method's runs (`balance/dreamer`, which
may be this cell's own first method). Those runs, with the same seed, become --prior-dirs; a prior named by one
run only (a cell with one seed) serves every seed. A run starts only after
its priors have finished. Runs whose method is `dreamer` take no prior, so they do not wait.

Every run gets a fixed folder, runs/<experiment>/<cell>__<method>__s<seed>/, passed to the script as --run-dir (the
script makes its own timestamped run folder inside). Rerunning the same sweep is therefore safe:
- a run whose folder holds `DONE` is skipped, and so is one whose results/ are there (committed from another
  machine), unless a run still to do needs it as its prior: then it runs again here, for its episodes;
- a run that has started but is not done (killed, crashed, node lost) continues with --resume;
- the rest start fresh.
After a run finishes, its args.json and metrics.jsonl are copied to results/<experiment>/<run>/ (small, meant to be
committed; episodes and checkpoints stay in runs/). Then `DONE` is written and one progress line is printed.
A cell with `keep_episodes_min_return = R` (for a prior made from state vectors, whose episodes are small) also has
its runs' episodes with a return of at least R copied there (<run>/episodes/). Committed, they are that prior's data
on another machine, so the prior does not run again there (it would take hours). The runs that use it must filter
at R or above (--prior-min-return), since only those episodes are kept: the spec is refused otherwise.
The script's output goes to <run folder>/log.txt. Changing a spec's flags does not restart done runs, and --resume
keeps a run's saved flags: delete a run's folder to start it again. One exception, to raise a grid's budget: a done
run whose saved --total-steps is below the spec's is not done; it resumes with the spec's --total-steps (or, with
only its results here, runs again from the start). The runs that used it as their prior are not rerun.

Ray (`--ray-address auto` for a running cluster, `--ray-address local` to start a private local instance):
- each run is one Ray task that asks for the spec's `cpus` and `gpus`;
- dependencies are Ray object references, so Ray starts a run only after its priors have finished;
- a task lost to a node failure, or whose script was killed by a signal, is retried (--ray-retries). The retry
  finds the run's folder and resumes it.
- ASSUMED: a shared filesystem. The repository (with this script, the training scripts and the virtual
  environment), runs/ and results/ must be at the same paths on every node, because a task reads its priors'
  episodes and resumes its run folder through those paths.
"""
import argparse
import concurrent.futures
import dataclasses
import fnmatch
import glob
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import tomllib

ROOT = os.path.dirname(os.path.abspath(__file__))
METHODS = ("dreamer", "uniform", "vrama", "rrama", "rbrama")  # the scripts' --method choices
MANAGED = ("--run-dir", "--resume", "--seed", "--prior-dirs")  # the sweep sets these itself
SPEC_KEYS = {"experiment", "script", "flags", "seeds", "cpus", "gpus", "cells"}
CELL_KEYS = {"flags", "methods", "seeds", "prior", "prior_dirs", "method_flags", "cpus", "gpus",
             "keep_episodes_min_return", "script"}


class SpecError(Exception):
    """A bad spec: printed as one line, exit code 2."""


class RunFailed(Exception):
    """The script exited with an error: not retried (the same flags would fail again)."""


class RunKilled(RunFailed):
    """The script was killed by a signal (out of memory, preempted): Ray retries it, and the retry resumes."""


@dataclasses.dataclass
class Run:
    name: str  # <cell>__<method>__s<seed>: its folder name under runs/<experiment>/ and results/<experiment>/
    folder: str  # runs/<experiment>/<name>: the script's --run-dir; the script makes one run folder inside
    results: str  # results/<experiment>/<name>
    script: str
    flags: list
    prior_dirs: list  # folders from outside the sweep (the cell's `prior_dirs`)
    deps: list  # names of the runs whose run folders join --prior-dirs
    cpus: float
    gpus: float
    keep_episodes_min_return: float = None  # episodes at or above this return are copied to results/ too


def split_flags(flags) -> list:
    """Flags given as one string ("--a 1 --b") or as a list (["--a", "1", "--b"])."""
    return shlex.split(flags) if isinstance(flags, str) else [str(f) for f in flags]


def last_value(flags: list, name: str):
    """The value of the last `name VALUE` in flags (tyro takes the last one too), or None."""
    values = [flags[i + 1] for i, f in enumerate(flags[:-1]) if f == name]
    return values[-1] if values else None


def load_spec(path: str, runs_dir: str = "runs", results_dir: str = "results"):
    """Expand a spec into runs, in an order where every run comes after the runs it depends on."""
    try:
        with open(path, "rb") as f:
            spec = tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise SpecError(f"{path}: {e}") from None
    if set(spec) - SPEC_KEYS:
        raise SpecError(f"{path}: unknown keys {sorted(set(spec) - SPEC_KEYS)} (known: {sorted(SPEC_KEYS)})")
    experiment = spec.get("experiment", os.path.splitext(os.path.basename(path))[0])

    def script_of(where: str, table: dict, default: str) -> str:
        script = os.path.join(ROOT, table.get("script", default))
        if not os.path.isfile(script):
            raise SpecError(f"{where}: script {table.get('script')!r} is not a file next to sweep.py")
        return script

    spec_script = script_of(path, spec, "rama_dreamer.py")
    runs = {}
    for cell, c in spec.get("cells", {}).items():
        where = f"{path}: cell {cell!r}"
        if set(c) - CELL_KEYS:
            raise SpecError(f"{where}: unknown keys {sorted(set(c) - CELL_KEYS)} (known: {sorted(CELL_KEYS)})")
        if "__" in cell:
            raise SpecError(f"{where}: '__' separates a run name's parts; use another cell name")
        priors = [c["prior"]] if isinstance(c.get("prior"), str) else c.get("prior", [])
        if cell in priors:
            raise SpecError(f"{where}: prior {cell!r} is the cell itself; name one of its methods ({cell}/dreamer)")
        method_flags, script = c.get("method_flags", {}), script_of(where, c, spec_script)  # a cell may run another
        for method in c.get("methods", ["dreamer"]):
            if "__" in method:
                raise SpecError(f"{where}: method {method!r}: '__' separates a run name's parts; use another name")
            extra = split_flags(method_flags.get(method, []))
            if method not in METHODS and "--method" not in extra:
                raise SpecError(f"{where}: method {method!r} is not one of {METHODS}; for a variant, give its "
                                f"--method in method_flags.{method}")
            for seed in c.get("seeds", spec.get("seeds", [1])):
                # --exp-name first so the spec can override it; --method and --seed last so the run's name holds
                flags = (["--exp-name", cell] + split_flags(spec.get("flags", [])) + split_flags(c.get("flags", []))
                         + (["--method", method] if method in METHODS else []) + extra + ["--seed", str(seed)])
                for managed in MANAGED:
                    if managed in flags[:-2]:
                        raise SpecError(f"{where}: {managed} is set by the sweep (use `prior` or `prior_dirs`)")
                name = f"{cell}__{method}__s{seed}"
                deps, outside = [], [str(d) for d in c.get("prior_dirs", [])]
                if last_value(flags, "--method") == "dreamer":  # Dreamer takes no prior data (the script refuses it)
                    outside = []
                else:
                    for prior in priors:  # `cell` (all its methods) or `cell/method`, of runs expanded above
                        start = prior.replace("/", "__") + "__"
                        named = [r.name for r in runs.values() if r.name.startswith(start)]
                        same_seed = [n for n in named if n.endswith(f"__s{seed}")]
                        if not same_seed and len(named) == 1:  # a prior made once (one seed) serves every seed
                            same_seed = named
                        if not same_seed:  # only runs above can be priors, so dependencies never form a cycle
                            raise SpecError(f"{where}: prior {prior!r} names no run with seed {seed} above {name}")
                        deps += same_seed
                    wanted = last_value(flags, "--prior-min-return")
                    for dep in deps:  # kept episodes stand in for the run folder: the same M only at or above R
                        keep = runs[dep].keep_episodes_min_return
                        if keep is not None and (wanted is None or float(wanted) < keep):
                            raise SpecError(f"{where}: {name} filters its prior {dep} at --prior-min-return {wanted},"
                                            f" below that cell's keep_episodes_min_return = {keep}")
                runs[name] = Run(name, os.path.join(runs_dir, experiment, name),
                                 os.path.join(results_dir, experiment, name), script, flags, outside, deps,
                                 float(c.get("cpus", spec.get("cpus", 1))), float(c.get("gpus", spec.get("gpus", 0))),
                                 c.get("keep_episodes_min_return"))
    if not runs:
        raise SpecError(f"{path}: no cells")
    return experiment, list(runs.values())


def run_folder(folder: str):
    """The script's run folder inside a sweep run's folder (the script names it with a timestamp), or None."""
    found = glob.glob(os.path.join(folder, "*", "args.json"))
    if len(found) > 1:
        raise RunFailed(f"{folder}: {len(found)} run folders inside, expected one: delete the extra ones")
    return os.path.dirname(found[0]) if found else None


def kept_episodes(run: Run):
    """The run's episodes committed under results/ (keep_episodes_min_return), or None."""
    return run.results if glob.glob(os.path.join(run.results, "**", "[0-9]*.npz"), recursive=True) else None


def prior_data(run: Run):
    """Where a prior run's episodes are: its run folder here, else its episodes committed under results/."""
    return run_folder(run.folder) or kept_episodes(run)


def is_done(run: Run) -> bool:
    """Done here (DONE in its folder), or on another machine whose results were committed (results/ has args.json),
    and trained for at least the spec's --total-steps (a raised budget makes a done run not done)."""
    here, committed = os.path.exists(os.path.join(run.folder, "DONE")), os.path.join(run.results, "args.json")
    if not here and not os.path.exists(committed):
        return False
    wanted = last_value(run.flags, "--total-steps")
    try:
        with open(os.path.join(run_folder(run.folder), "args.json") if here else committed) as f:
            saved = json.load(f).get("total_steps")
    except (OSError, ValueError):  # no readable args.json to compare with: the run counts as done
        return True
    return wanted is None or saved is None or saved >= int(wanted)


def with_priors(runs: list, names: set, needed=lambda run: True) -> list:
    """The runs named, plus (recursively) the priors they depend on for which needed(prior) holds, in spec order."""
    by_name = {r.name: r for r in runs}
    chosen, stack = set(names), list(names)
    while stack:
        for dep in by_name[stack.pop()].deps:
            if dep not in chosen and needed(by_name[dep]):
                chosen.add(dep)
                stack.append(dep)
    return [r for r in runs if r.name in chosen]


def to_run(runs: list) -> list:
    """The runs not done, plus the done priors they need whose episodes are not here (done on another machine, with
    only their args and metrics committed): those run again, since their episodes are the prior data."""
    return with_priors(runs, {r.name for r in runs if not is_done(r)}, lambda prior: not prior_data(prior))


def select(runs: list, patterns: list) -> list:
    """The runs whose names match a pattern, and the priors they depend on."""
    return with_priors(runs, {r.name for r in runs if any(fnmatch.fnmatchcase(r.name, p) for p in patterns)})


def first_runs(runs: list, todo: list, count: int) -> list:
    """--max-runs: the first `count` runs of `todo`, lowest seed first (then in spec order, todo's own: the sort is
    stable), so that a grid cut short holds whole seeds; and the priors among `todo` that they need (beyond the count:
    without them they cannot run)."""
    chosen = sorted(todo, key=lambda r: int(last_value(r.flags, "--seed")))[:count]
    return with_priors(runs, {r.name for r in chosen}, lambda prior: prior in todo)


def command(run: Run, python: str = None) -> list:
    """The script's command line: --resume the run folder if the run has started, else the spec's flags."""
    python = python or sys.executable  # looked up when called: on Ray, the worker's interpreter
    started = run_folder(run.folder)
    if started:  # --resume reloads the saved flags; only --device and --total-steps come from the spec
        device, steps = last_value(run.flags, "--device"), last_value(run.flags, "--total-steps")
        return ([python, run.script, "--resume", started] + (["--device", device] if device else [])
                + (["--total-steps", steps] if steps else []))
    # a prior run's own folder, or its kept episodes, or its sweep folder when it has not started yet (--dry-run only)
    deps = [dataclasses.replace(run, folder=os.path.join(os.path.dirname(run.folder), d),
                                results=os.path.join(os.path.dirname(run.results), d)) for d in run.deps]
    priors = [prior_data(dep) or dep.folder for dep in deps] + run.prior_dirs
    return ([python, run.script, *run.flags, "--run-dir", run.folder]
            + (["--prior-dirs", *priors] if priors else []))


def save_results(run: Run):
    """Copy args.json and every metrics.jsonl (one per task of a --task-sequence run) to the run's results folder,
    and with keep_episodes_min_return, the episodes at or above it (<run>/episodes/NNNNNN-LEN.npz)."""
    source = run_folder(run.folder)
    paths = [os.path.join(source, "args.json")] + glob.glob(os.path.join(source, "**", "metrics.jsonl"), recursive=True)
    if run.keep_episodes_min_return is not None:
        import numpy as np  # only here: the sweep itself needs no numpy

        def kept(path):
            with np.load(path) as episode:
                return float(episode["return"]) >= run.keep_episodes_min_return

        paths += [p for p in sorted(glob.glob(os.path.join(source, "**", "[0-9]*.npz"), recursive=True)) if kept(p)]
    for path in paths:
        target = os.path.join(run.results, os.path.relpath(path, source))
        os.makedirs(os.path.dirname(target), exist_ok=True)
        shutil.copyfile(path, target)


def run_cell(run: Run, threads: int, *_deps) -> dict:
    """Run (or resume) one run to its end, copy its results, write DONE. _deps: Ray's finished dependencies."""
    os.makedirs(run.folder, exist_ok=True)
    cmd = command(run)
    start = time.time()
    die_with_parent = None  # the script is killed when this worker dies, so a retried run never has two writers
    if sys.platform == "linux":
        import ctypes

        prctl = ctypes.CDLL(None).prctl  # looked up here: between fork and exec only the call itself happens
        die_with_parent = lambda: prctl(1, signal.SIGKILL)  # noqa: E731  PR_SET_PDEATHSIG
    with open(os.path.join(run.folder, "log.txt"), "a") as log:
        log.write(f"$ {shlex.join(cmd)}\n")
        log.flush()
        rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, preexec_fn=die_with_parent,
                            env={**os.environ, "OMP_NUM_THREADS": str(threads)}).returncode
    if rc != 0:
        with open(os.path.join(run.folder, "log.txt")) as f:
            tail = f.read().strip().splitlines()[-1:] or [""]
        error = RunKilled if rc < 0 else RunFailed
        raise error(f"{run.name}: exit code {rc} ({tail[0][:200]}); log: {run.folder}/log.txt")
    save_results(run)
    open(os.path.join(run.folder, "DONE"), "w").close()
    return {"name": run.name, "minutes": (time.time() - start) / 60, "resumed": "--resume" in cmd,
            "returns": episode_returns(os.path.join(run.results, "metrics.jsonl"))}


def episode_returns(path: str) -> list:
    """Training-episode returns in a metrics.jsonl (none for a --task-sequence run, whose tasks have their own)."""
    if not os.path.exists(path):
        return []
    with open(path) as f:
        rows = [json.loads(line) for line in f if line.strip()]
    return [row["charts/episodic_return"] for row in rows if "charts/episodic_return" in row]


def progress_line(k: int, total: int, result: dict) -> str:
    returns = result["returns"]
    summary = f"mean training return {sum(returns) / len(returns):.1f} over {len(returns)} episodes" if returns else ""
    return (f"[{k}/{total}] {result['name']}: finished{' (resumed)' if result['resumed'] else ''} in "
            f"{result['minutes']:.1f} min | {summary}")


def threads_per_run(workers: int) -> int:
    """Each local run's OMP_NUM_THREADS: the caller's when set (e.g. 1 for two sweeps side by side on 2 cores, where
    cores / workers would oversubscribe them), else cores / workers."""
    given = os.environ.get("OMP_NUM_THREADS", "")
    return int(given) if given.isdigit() and int(given) > 0 else max(1, (os.cpu_count() or 1) // workers)


def run_local(runs: list, todo: list, workers: int) -> list:
    """Up to `workers` runs at a time in threads (each waits on its subprocess); returns the failure lines."""
    threads = threads_per_run(workers)
    state = {r.name: "done" for r in runs if r not in todo}
    waiting, running, failures, k = list(todo), {}, [], 0
    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
        while waiting or running:
            for run in list(waiting):
                if any(state.get(d) == "failed" for d in run.deps):
                    state[run.name] = "failed"
                    waiting.remove(run)
                    failures.append(f"{run.name}: not started, a prior run failed")
                elif all(state.get(d) == "done" for d in run.deps):
                    running[pool.submit(run_cell, run, threads)] = run
                    waiting.remove(run)
            finished, _ = concurrent.futures.wait(running, return_when=concurrent.futures.FIRST_COMPLETED)
            for future in finished:
                run = running.pop(future)
                try:
                    result = future.result()
                    state[run.name] = "done"
                    k += 1
                    print(progress_line(k, len(todo), result), flush=True)
                except RunFailed as e:
                    state[run.name] = "failed"
                    failures.append(str(e))
                    print(f"FAILED {e}", flush=True)
    return failures


def run_ray(todo: list, address: str, retries: int) -> list:
    """Each run a Ray task; a dependency is passed as the object reference of its task. Returns the failure lines."""
    import ray

    if address == "local":  # a new private instance on this machine (never an existing one), sized to its cores
        ray.init(address="local", include_dashboard=False, log_to_driver=False)
    else:
        ray.init(address=address, log_to_driver=False)
    print(f"ray: {ray.cluster_resources()}", flush=True)
    task = ray.remote(run_cell)
    refs = {}
    for run in todo:  # deps come first in `todo`; a dep that is done already is not in refs and is not waited for
        refs[run.name] = task.options(num_cpus=run.cpus, num_gpus=run.gpus, max_retries=retries,
                                      retry_exceptions=[RunKilled], name=run.name).remote(
            run, max(1, int(run.cpus)), *[refs[d] for d in run.deps if d in refs])
    names = {ref: name for name, ref in refs.items()}
    pending, failures, k = list(refs.values()), [], 0
    while pending:
        finished, pending = ray.wait(pending, num_returns=1)
        try:
            result = ray.get(finished[0])
        except ray.exceptions.RayError as e:  # the run failed, or one it depends on did (then that run's error)
            name = names[finished[0]]
            cause = e.cause if isinstance(e, ray.exceptions.RayTaskError) and e.cause else e
            message = str(cause).strip().splitlines()[-1][:300]  # a RunFailed message starts with its run's name
            failures.append(message if message.startswith(name + ":") else f"{name}: not started or lost ({message})")
            print(f"FAILED {failures[-1]}", flush=True)
            continue
        k += 1
        print(progress_line(k, len(todo), result), flush=True)
    ray.shutdown()
    return failures


class OneLineParser(argparse.ArgumentParser):
    """argparse's errors as one line, `error: --flag: ...`, exit code 2, as every other bad input here (and in the
    training scripts) is reported: argparse's own usage block would bury the line that matters. report.py's parser
    too. extra_positional and missing_positional word the errors of a parser's positional arguments."""
    extra_positional = None  # the line for an argument no positional takes (None: as an unknown flag)
    missing_positional = None  # the line for a missing positional argument (None: argparse's words)

    def error(self, message: str):
        named = re.match(r"argument (\S+?)(?:/\S+)?: (.*)", message, re.S)  # a bad value, a bad choice, no value
        if named:
            message = f"{named.group(1)}: {named.group(2)}"
        elif message.startswith("unrecognized arguments: "):
            first = message.split(": ", 1)[1].split()[0]
            flags = [o for a in self._actions for o in a.option_strings if o.startswith("--") and o != "--help"]
            message = f"{first}: {self.extra_positional}" if self.extra_positional and not first.startswith("-") \
                else f"{first}: unknown flag (known: {', '.join(flags)})"
        elif self.missing_positional and message.startswith("the following arguments are required: "):
            message = f"{message.split(': ', 1)[1]}: {self.missing_positional}"
        print(f"error: {message}", file=sys.stderr)
        sys.exit(2)


def main():
    parser = OneLineParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.extra_positional = "one spec only (give the others' runs as cells of one spec)"
    parser.missing_positional = "missing (a sweep spec, e.g. sweeps/cartpole_tables.toml)"
    parser.add_argument("spec", help="a sweep spec (TOML), e.g. sweeps/cartpole_tables.toml")
    parser.add_argument("--workers", type=int, default=1, help="local backend: runs at a time (each gets cores / N threads, or "
                        "OMP_NUM_THREADS when set)")
    parser.add_argument("--ray-address", default=None,
                        help="run on Ray: `auto` (a running cluster), `local` (start one here) or host:port")
    parser.add_argument("--ray-retries", type=int, default=3, help="Ray: retries of a run lost to a node failure or a kill")
    parser.add_argument("--runs-dir", default="runs", help="runs go to <runs-dir>/<experiment>/<run>/")
    parser.add_argument("--results-dir", default="results", help="results go to <results-dir>/<experiment>/<run>/")
    parser.add_argument("--dry-run", action="store_true", help="print each run's state and command, run nothing")
    parser.add_argument("--only", nargs="+", default=None, metavar="PATTERN",
                        help="run only the runs whose names match one of these patterns (fnmatch, e.g. '*__dreamer__*')"
                             ", and the priors they need")
    parser.add_argument("--max-runs", type=int, default=None, metavar="N",
                        help="run at most N of the runs still to do (lowest seed first), and the priors they need: "
                             "a grid in parts, each finished within a time-limited allocation (a device session)")
    parser.add_argument("--collect", action="store_true",
                        help="only copy the done runs' results again from their run folders to a results/ that lost "
                             "them (a device's working tree resynced between calls), and run nothing")
    args = parser.parse_args()
    for name, least in (("max_runs", 1), ("workers", 1), ("ray_retries", 0)):  # checked before anything is written
        value = getattr(args, name)
        if value is not None and value < least:
            parser.error(f"argument --{name.replace('_', '-')}: must be >= {least} (got {value})")
    if args.ray_address:  # Ray workers may start in another folder: give them absolute paths (shared filesystem)
        args.runs_dir, args.results_dir = os.path.abspath(args.runs_dir), os.path.abspath(args.results_dir)
    try:
        experiment, runs = load_spec(args.spec, args.runs_dir, args.results_dir)
    except SpecError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    if args.only:
        runs = select(runs, args.only)
        if not runs:
            print(f"error: --only {' '.join(args.only)}: no run of {args.spec} matches", file=sys.stderr)
            sys.exit(2)
    pending = to_run(runs)
    for run in runs:  # results/ deleted or not yet committed here: copy them again from the done runs
        if run not in pending and not os.path.exists(os.path.join(run.results, "args.json")) and not args.dry_run:
            save_results(run)
            print(f"{run.name}: results copied again to {run.results}")
    if args.collect:
        return
    todo = pending if args.max_runs is None else first_runs(runs, pending, args.max_runs)
    print(f"sweep {experiment}: {len(runs)} runs, {len(runs) - len(pending)} done already, {len(pending)} to run"
          + (f", {len(todo)} of them now (--max-runs {args.max_runs})" if len(todo) < len(pending) else "")
          + f" (folders under {os.path.join(args.runs_dir, experiment)})", flush=True)
    if args.dry_run:
        for run in runs:
            try:
                state = ("done" if run not in pending else "later" if run not in todo
                         else "resume" if run_folder(run.folder) else "new")
                print(f"{run.name} [{state}]" + ("" if state == "done" else f": {shlex.join(command(run, 'python'))}"))
            except RunFailed as e:  # a folder that holds two runs
                print(f"{run.name} [error]: {e}")
        return
    if not todo:
        return
    failures = run_ray(todo, args.ray_address, args.ray_retries) if args.ray_address else \
        run_local(runs, todo, args.workers)
    if failures:
        print(f"{len(failures)} of {len(todo)} runs failed:\n  " + "\n  ".join(failures), file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
