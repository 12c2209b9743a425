"""sweep.py: spec expansion, and a tiny grid run locally and on a local Ray instance.

Both runs of the grid resume a killed run, and a second call skips the done runs."""
import glob
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest

from helpers import ROOT, TINY, run_script
import sweep

# a tiny grid: Dreamer, then `uniform` with the Dreamer run of the same seed as its prior
TINY_SPEC = f"""
experiment = "tiny"
flags = {json.dumps(["--env-id", "dmc/cartpole-balance", "--obs-type", "state", *TINY])}
seeds = [1]

[cells.balance]
methods = ["dreamer", "uniform"]
prior = "balance/dreamer"
"""


def write_spec(tmp_path, text: str) -> str:
    path = tmp_path / "spec.toml"
    path.write_text(text)
    return str(path)


def sweep_cli(tmp_path, spec, *flags, timeout=300):
    return run_script("sweep.py", spec, "--runs-dir", str(tmp_path / "runs"), "--results-dir",
                      str(tmp_path / "results"), *flags, timeout=timeout)


def test_spec_expands_cells_methods_seeds_and_priors(tmp_path):
    spec = write_spec(tmp_path, """
experiment = "exp"
flags = "--obs-type state --total-steps 1000"
seeds = [1, 2]
[cells.stand]
flags = ["--env-id", "dmc/walker-stand"]
methods = ["dreamer"]
[cells.walk]
flags = "--env-id dmc/walker-walk --prior-min-return 600"
methods = ["dreamer", "rrama", "rrama_nosg"]
seeds = [2]
prior = "stand"
method_flags.rrama_nosg = "--method rrama --address-stop-grad-x False"
""")
    experiment, runs = sweep.load_spec(spec, "R", "S")
    by_name = {r.name: r for r in runs}
    assert experiment == "exp"
    assert list(by_name) == ["stand__dreamer__s1", "stand__dreamer__s2", "walk__dreamer__s2", "walk__rrama__s2",
                             "walk__rrama_nosg__s2"]
    nosg = by_name["walk__rrama_nosg__s2"]
    assert nosg.folder == os.path.join("R", "exp", "walk__rrama_nosg__s2")
    assert nosg.results == os.path.join("S", "exp", "walk__rrama_nosg__s2")
    assert nosg.deps == ["stand__dreamer__s2"]  # the prior run of the same seed only
    assert nosg.flags == ["--exp-name", "walk", "--obs-type", "state", "--total-steps", "1000", "--env-id",
                          "dmc/walker-walk", "--prior-min-return", "600", "--method", "rrama",
                          "--address-stop-grad-x", "False", "--seed", "2"]
    assert by_name["walk__dreamer__s2"].deps == []  # Dreamer takes no prior data, so it waits for nothing
    assert {r.script for r in runs} == {os.path.join(ROOT, "rama_dreamer.py")}  # the spec's default script
    # the command: --prior-dirs names the prior's folder; a started run is resumed, keeping --device and the budget
    assert sweep.command(nosg, "python")[-2:] == ["--prior-dirs", os.path.join("R", "exp", "stand__dreamer__s2")]
    run = by_name["stand__dreamer__s1"]
    run.folder = str(tmp_path / "started")
    run.flags += ["--device", "cpu"]
    os.makedirs(tmp_path / "started" / "dmc_walker-stand__x__dreamer__1__123")
    (tmp_path / "started" / "dmc_walker-stand__x__dreamer__1__123" / "args.json").write_text("{}")
    assert sweep.command(run, "python") == ["python", run.script, "--resume",
                                            str(tmp_path / "started" / "dmc_walker-stand__x__dreamer__1__123"),
                                            "--device", "cpu", "--total-steps", "1000"]


def test_a_cell_may_run_the_other_script(tmp_path):
    spec = write_spec(tmp_path, """
experiment = "families"
flags = "--obs-type state"
[cells.kitchen]
flags = "--env-id kitchen/bluebox"
[cells.drawer]
script = "rama_metaworld.py"
flags = "--env-id metaworld/drawer-close --task-set new"
""")
    _, runs = sweep.load_spec(spec, "R", "S")
    assert [(r.name, os.path.basename(r.script)) for r in runs] == [("kitchen__dreamer__s1", "rama_dreamer.py"),
                                                                    ("drawer__dreamer__s1", "rama_metaworld.py")]
    assert sweep.command(runs[1], "python")[:2] == ["python", os.path.join(ROOT, "rama_metaworld.py")]


def test_a_prior_made_once_serves_every_seed(tmp_path):
    spec = write_spec(tmp_path, """
seeds = [1, 2]
[cells.prior]
seeds = [0]
[cells.twice]
seeds = [0, 5]
[cells.task]
methods = ["uniform"]
prior = "prior"
[cells.task2]
methods = ["uniform"]
prior = "twice"
seeds = [1]
""")
    with pytest.raises(sweep.SpecError, match=r"prior 'twice' names no run with seed 1"):  # two runs: ambiguous
        sweep.load_spec(spec)
    write_spec(tmp_path, open(spec).read().split("[cells.task2]")[0])
    by_name = {r.name: r for r in sweep.load_spec(spec)[1]}
    assert by_name["task__uniform__s1"].deps == ["prior__dreamer__s0"]
    assert by_name["task__uniform__s2"].deps == ["prior__dreamer__s0"]


def test_only_selects_runs_with_their_priors_and_committed_results_count_as_done(tmp_path):
    spec = write_spec(tmp_path, """
[cells.prior]
[cells.task]
methods = ["dreamer", "uniform", "rrama"]
prior = "prior"
""")
    runs = sweep.load_spec(spec, str(tmp_path / "runs"), str(tmp_path / "results"))[1]
    names = lambda rs: [r.name for r in rs]  # noqa: E731
    assert names(sweep.select(runs, ["*__dreamer__*"])) == ["prior__dreamer__s1", "task__dreamer__s1"]
    assert names(sweep.select(runs, ["task__rrama__*"])) == ["prior__dreamer__s1", "task__rrama__s1"]
    assert names(sweep.to_run(runs)) == names(runs)
    for run in runs[:3]:  # prior, task dreamer and uniform finished on another machine: only their results are here
        os.makedirs(run.results)
        open(os.path.join(run.results, "args.json"), "w").close()
    # rrama still needs the prior's episodes, which are not here: the prior runs again; the others are done
    assert names(sweep.to_run(runs)) == ["prior__dreamer__s1", "task__rrama__s1"]
    os.makedirs(os.path.join(runs[0].folder, "dmc_run"))
    open(os.path.join(runs[0].folder, "dmc_run", "args.json"), "w").close()  # the prior's run folder is here
    assert names(sweep.to_run(runs)) == ["task__rrama__s1"]


def test_max_runs_takes_the_lowest_seeds_first_with_the_priors_they_need(tmp_path):
    spec = write_spec(tmp_path, """
seeds = [1, 2]
[cells.prior]
seeds = [3]
[cells.task]
methods = ["dreamer", "uniform"]
prior = "prior"
""")
    runs = sweep.load_spec(spec, str(tmp_path / "runs"), str(tmp_path / "results"))[1]
    names = lambda rs: [r.name for r in rs]  # noqa: E731
    todo = sweep.to_run(runs)
    # seed 1's two runs come first (returned in spec order); uniform's prior (seed 3, serving every seed) comes with
    # it, beyond the count
    assert names(sweep.first_runs(runs, todo, 2)) == ["prior__dreamer__s3", "task__dreamer__s1", "task__uniform__s1"]
    assert names(sweep.first_runs(runs, todo, 1)) == ["task__dreamer__s1"]
    assert names(sweep.first_runs(runs, todo, 9)) == names(todo)
    os.makedirs(runs[0].results)  # the prior done on another machine, its episodes not here: it still runs
    open(os.path.join(runs[0].results, "args.json"), "w").close()
    os.makedirs(os.path.join(runs[0].folder, "dmc_run"))  # ...unless its run folder is here
    open(os.path.join(runs[0].folder, "dmc_run", "args.json"), "w").close()
    todo = sweep.to_run(runs)
    assert names(sweep.first_runs(runs, todo, 3)) == ["task__dreamer__s1", "task__dreamer__s2", "task__uniform__s1"]
    out = sweep_cli(tmp_path, spec, "--dry-run", "--max-runs", "3").stdout
    assert "4 to run, 3 of them now (--max-runs 3)" in out
    assert "task__uniform__s2 [later]" in out and "task__dreamer__s2 [new]" in out
    assert "prior__dreamer__s3 [done]" in out
    refused = run_script("sweep.py", spec, "--dry-run", "--max-runs", "0", check=False)
    assert refused.returncode == 2 and refused.stderr == "error: --max-runs: must be >= 1 (got 0)\n"


def test_kept_prior_episodes_stand_in_for_a_prior_run_folder_on_another_machine(tmp_path):
    import numpy as np

    import rama_dreamer as rd

    spec = write_spec(tmp_path, """
[cells.prior]
keep_episodes_min_return = 500
[cells.task]
methods = ["uniform"]
prior = "prior"
flags = "--prior-min-return 500"
""")
    prior, task = sweep.load_spec(spec, str(tmp_path / "runs"), str(tmp_path / "results"))[1]
    assert prior.keep_episodes_min_return == 500
    # the prior's run folder, with episodes of returns 499.9, 500 and 950 (the script's own episode format)
    episodes = os.path.join(prior.folder, "dmc_run", "episodes")
    os.makedirs(episodes)
    open(os.path.join(prior.folder, "dmc_run", "args.json"), "w").write("{}")
    for index, ret in enumerate([499.9, 500.0, 950.0]):
        rd.save_episode(episodes, index, {"obs": np.full((4, 5), index, np.float32), "action": np.zeros((4, 1)),
                                          "reward": np.zeros(4), "terminal": np.zeros(4, bool), "task": "t",
                                          "return": np.float32(ret)})
    sweep.save_results(prior)
    kept = sorted(os.listdir(os.path.join(prior.results, "episodes")))
    assert kept == ["000001-3.npz", "000002-3.npz"]  # 499.9 is below R: not kept
    assert sweep.command(task)[-1] == os.path.join(prior.folder, "dmc_run")  # here, the run folder is the prior

    shutil.rmtree(tmp_path / "runs")  # another machine: only results/ (with the kept episodes) is here
    assert [r.name for r in sweep.to_run([prior, task])] == ["task__uniform__s1"]  # the prior does not run again
    assert sweep.command(task)[-2:] == ["--prior-dirs", prior.results]
    # the script reads the same M from the kept episodes as from the run folder, filtered at R
    m = rd.load_prior_episodes([prior.results], 500, 1000, (5,), 1, np.random.default_rng(0))
    assert [float(e["obs"][0, 0]) for e in m] == [1.0, 2.0]

    # without kept episodes, a done prior whose run folder is gone runs again (its episodes are the prior data)
    shutil.rmtree(os.path.join(prior.results, "episodes"))
    assert [r.name for r in sweep.to_run([prior, task])] == ["prior__dreamer__s1", "task__uniform__s1"]
    # a user of kept episodes that filters below R would see a different M on another machine: refused
    write_spec(tmp_path, open(spec).read().replace("--prior-min-return 500", "--prior-min-return 400"))
    with pytest.raises(sweep.SpecError, match=r"task__uniform__s1 filters its prior prior__dreamer__s1 at "
                                              r"--prior-min-return 400, below that cell's keep_episodes_min_return"):
        sweep.load_spec(spec)


def test_a_raised_budget_resumes_done_runs_with_the_new_total_steps(tmp_path):
    """Raising --total-steps in the spec makes a done run not done: it resumes with the spec's budget (the script
    accepts --total-steps beside --resume); one with only committed results runs again. Lowering it changes nothing."""
    text = '[cells.task]\nflags = "--total-steps 300 --device cpu"\n'
    spec = write_spec(tmp_path, text)
    here, elsewhere = (sweep.load_spec(spec, str(tmp_path / "runs"), str(tmp_path / r))[1][0] for r in ("a", "b"))
    folder = os.path.join(here.folder, "dmc_run")
    os.makedirs(folder)
    with open(os.path.join(folder, "args.json"), "w") as f:
        json.dump({"total_steps": 300}, f)
    open(os.path.join(here.folder, "DONE"), "w").close()
    os.makedirs(elsewhere.results)
    with open(os.path.join(elsewhere.results, "args.json"), "w") as f:
        json.dump({"total_steps": 300}, f)
    elsewhere.folder = str(tmp_path / "not_here")
    assert sweep.is_done(here) and sweep.is_done(elsewhere)
    for steps, done in (("600", False), ("200", True)):
        write_spec(tmp_path, text.replace("300", steps))
        raised = sweep.load_spec(spec, str(tmp_path / "runs"), str(tmp_path / "a"))[1][0]
        elsewhere.flags = raised.flags
        assert sweep.is_done(raised) == done and sweep.is_done(elsewhere) == done
        assert sweep.command(raised, "python") == ["python", raised.script, "--resume", folder, "--device", "cpu",
                                                   "--total-steps", steps]


@pytest.mark.parametrize("text, message", [
    ('bad_key = 1\n[cells.a]\n', r"unknown keys \['bad_key'\]"),
    ('[cells.a]\nmethods = ["rrama"]\nprior = "b"\n[cells.b]\n', r"prior 'b' names no run with seed 1"),
    ('[cells.a]\nmethods = ["rrama"]\nprior = "a/rrama"\n', r"prior 'a/rrama' names no run"),  # itself: a cycle
    ('[cells.a]\nflags = "--seed 3"\n', r"--seed is set by the sweep"),
    ('[cells.a]\nmethods = ["dreamer", "rrama"]\nprior = "a"\n', r"is the cell itself"),
    ('[cells.a]\nmethods = ["mine"]\n', r"method 'mine' is not one of"),
    ('[cells.a__b]\n', r"'__' separates"),
    ('[cells.a]\nscript = "nope.py"\n', r"cell 'a': script 'nope.py' is not a file"),
])
def test_spec_errors_name_the_problem(tmp_path, text, message):
    with pytest.raises(sweep.SpecError, match=message):
        sweep.load_spec(write_spec(tmp_path, text))


@pytest.mark.parametrize("flags, line", [
    (["--workers", "abc"], "error: --workers: invalid int value: 'abc'"),
    (["--wrkers", "2"], "error: --wrkers: unknown flag (known: --workers, --ray-address, --ray-retries, --runs-dir, "
                        "--results-dir, --dry-run, --only, --max-runs, --collect)"),
    (["--workers"], "error: --workers: expected one argument"),
    (["--only"], "error: --only: expected at least one argument"),
    (["--max-runs", "0"], "error: --max-runs: must be >= 1 (got 0)"),
    (["--workers", "0"], "error: --workers: must be >= 1 (got 0)"),
    (["--ray-retries", "-1"], "error: --ray-retries: must be >= 0 (got -1)"),
    (["other.toml"], "error: other.toml: one spec only (give the others' runs as cells of one spec)"),
])
def test_bad_command_line_is_one_line_and_writes_nothing(tmp_path, flags, line):
    """Every bad input to sweep.py is one `error: --flag: ...` line on stderr, exit code 2 (argparse's own error
    prints a usage block above it), before anything is written: the spec would run otherwise."""
    proc = run_script("sweep.py", write_spec(tmp_path, TINY_SPEC), "--runs-dir", str(tmp_path / "runs"),
                      "--results-dir", str(tmp_path / "results"), *flags, check=False)
    assert (proc.returncode, proc.stderr.splitlines(), proc.stdout) == (2, [line], "")
    assert not (tmp_path / "runs").exists() and not (tmp_path / "results").exists()
    proc = run_script("sweep.py", check=False)
    assert (proc.returncode, proc.stderr.splitlines()) == (2, ["error: spec: missing (a sweep spec, e.g. "
                                                               "sweeps/cartpole_tables.toml)"])


def test_a_bad_choice_names_the_allowed_values(capsys):
    """sweep.py has no flag with choices today; its parser names them for any that gets some."""
    parser = sweep.OneLineParser()
    parser.add_argument("--backend", choices=["local", "ray"])
    with pytest.raises(SystemExit) as exit_code:
        parser.parse_args(["--backend", "slurm"])
    assert exit_code.value.code == 2
    assert capsys.readouterr().err.splitlines() == [
        "error: --backend: invalid choice: 'slurm' (choose from 'local', 'ray')"]


@pytest.mark.slow
def test_local_sweep_resumes_a_killed_run_then_skips_done_runs(tmp_path):
    spec = write_spec(tmp_path, TINY_SPEC)
    _, runs = sweep.load_spec(spec, str(tmp_path / "runs"), str(tmp_path / "results"))
    prior = runs[0]
    # a killed run: the Dreamer run started by hand with the sweep's own command, SIGKILLed after its first episode
    proc = subprocess.Popen(sweep.command(prior), cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 240
        while not glob.glob(os.path.join(prior.folder, "*", "episodes", "*.npz")):
            assert time.time() < deadline and proc.poll() is None, "the run wrote no episode in time"
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    killed_at = len(glob.glob(os.path.join(prior.folder, "*", "episodes", "*.npz")))
    assert killed_at < 3  # 3 episodes make a TINY run

    out = sweep_cli(tmp_path, spec, "--workers", "2").stdout
    assert "2 runs, 0 done already, 2 to run" in out
    assert "[1/2] balance__dreamer__s1: finished (resumed)" in out  # the uniform run waited for its prior
    assert "[2/2] balance__uniform__s1: finished in" in out
    inner = glob.glob(os.path.join(prior.folder, "*", "args.json"))
    assert len(inner) == 1  # resumed in place, not started again beside the killed run
    dreamer_run = os.path.dirname(inner[0])
    assert len(glob.glob(os.path.join(dreamer_run, "episodes", "*.npz"))) == 3
    assert "--resume" in open(os.path.join(prior.folder, "log.txt")).read()
    # results: args.json and metrics.jsonl of each run; the uniform run's prior is the Dreamer run of its seed
    for run in runs:
        assert sorted(os.listdir(run.results)) == ["args.json", "metrics.jsonl"]
        assert os.path.exists(os.path.join(run.folder, "DONE"))
    with open(os.path.join(runs[1].results, "args.json")) as f:
        assert json.load(f)["prior_dirs"] == [dreamer_run]

    logs = [open(os.path.join(r.folder, "log.txt")).read() for r in runs]
    again = sweep_cli(tmp_path, spec, "--workers", "2").stdout
    assert "2 runs, 2 done already, 0 to run" in again
    assert [open(os.path.join(r.folder, "log.txt")).read() for r in runs] == logs  # nothing ran again
    shutil.rmtree(tmp_path / "results")  # results of done runs are copied again, still without running anything
    assert "results copied again" in sweep_cli(tmp_path, spec).stdout
    assert sorted(os.listdir(runs[0].results)) == ["args.json", "metrics.jsonl"]


@pytest.mark.slow
def test_gpu_session_sweep_stages_run_a_spec(tmp_path):
    """benchmarks/gpu_session.sh's sweep-start, sweep-poll and sweep-pack (issue 41's GPU calls) on a CPU: the tiny
    grid runs detached in two parts (MAX_RUNS), the poll returns when it has ended (not at the call's deadline), and
    the archive holds every done run's results, the sweep's log and each run's log tail, even when results/ was
    deleted between the calls (the device copies the working tree afresh on every call)."""
    import tarfile

    for name in ("sweep.py", "rama_dreamer.py", "kitchen_env.py", "report.py", "benchmarks/gpu_session.sh"):
        os.makedirs(tmp_path / os.path.dirname(name), exist_ok=True)
        shutil.copy(os.path.join(ROOT, name), tmp_path / name)
    (tmp_path / "sweeps").mkdir()
    (tmp_path / "sweeps" / "tiny.toml").write_text(TINY_SPEC)
    env = dict(os.environ, PATH=os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"],
               OUT=str(tmp_path / "out"), SWEEP_TMP=str(tmp_path / "st"), SPEC="sweeps/tiny.toml", WORKERS="1",
               BUDGET="400", OMP_NUM_THREADS="1")
    stages = ["bash", "benchmarks/gpu_session.sh", "sweep-start", "sweep-poll", "sweep-pack"]
    # the grid in two parts, as in device sessions too short for all of it: MAX_RUNS=1 runs Dreamer alone
    proc = subprocess.run(stages, cwd=tmp_path, env=dict(env, MAX_RUNS="1"), capture_output=True, text=True,
                          timeout=420)
    assert "2 to run, 1 of them now (--max-runs 1)" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "[1/1] balance__dreamer__s1: finished in" in proc.stdout and "uniform" not in proc.stdout.split("now")[1]
    start = time.time()
    proc = subprocess.run(stages[:-1], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=420)
    assert time.time() - start < 300, proc.stdout[-2000:]  # the poll ended with the sweep, not at BUDGET - 45 s
    assert "1 done already, 1 to run" in proc.stdout, proc.stdout[-2000:]
    assert "[1/1] balance__uniform__s1: finished in" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-2000:]
    shutil.rmtree(tmp_path / "results")  # the next call's fresh copy of the working tree has no untracked results/
    proc = subprocess.run(stages[:2] + ["sweep-pack"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120)
    assert "balance__uniform__s1: results copied again" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-2000:]
    with tarfile.open(tmp_path / "out" / "tiny.tgz") as archive:
        names = set(archive.getnames())
    for run in ("balance__dreamer__s1", "balance__uniform__s1"):
        assert {f"results/tiny/{run}/args.json", f"results/tiny/{run}/metrics.jsonl", f"logs/tiny/{run}.txt"} <= names
    assert "logs/tiny/sweep.txt" in names


def test_dry_run_prints_commands_and_states(tmp_path):
    spec = write_spec(tmp_path, TINY_SPEC)
    out = sweep_cli(tmp_path, spec, "--dry-run").stdout
    assert "balance__dreamer__s1 [new]: python " in out and "--method dreamer --seed 1 --run-dir" in out
    assert out.rstrip().endswith(f"--prior-dirs {tmp_path / 'runs' / 'tiny' / 'balance__dreamer__s1'}")
    assert not (tmp_path / "runs").exists()


def script_pid(folder: str):
    """The pid of the training script that runs in a sweep folder (our own child's child, found by its --run-dir)."""
    for path in glob.glob("/proc/[0-9]*/cmdline"):
        try:
            args = open(path, "rb").read().decode(errors="replace").split("\0")
        except OSError:
            continue
        if any(a.endswith("rama_dreamer.py") for a in args) and folder in args:
            return int(path.split("/")[2])
    return None


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the script's pid in /proc")
def test_ray_sweep_retries_a_killed_run_on_a_local_instance(tmp_path):
    # 6 episodes instead of 3, so the run is still going when it is killed
    spec = write_spec(tmp_path, TINY_SPEC.replace(
        '"--eval-every"', '"--total-steps", "600", "--eval-every"'))
    _, runs = sweep.load_spec(spec, str(tmp_path / "runs"), str(tmp_path / "results"))
    prior = runs[0]
    proc = subprocess.Popen([sys.executable, os.path.join(ROOT, "sweep.py"), spec, "--runs-dir", str(tmp_path / "runs"),
                             "--results-dir", str(tmp_path / "results"), "--ray-address", "local"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # the time limits guard against a hang only: on 2 cores shared with other jobs, Ray took 2 minutes to start each
    # task, and the whole sweep overran a 300 s limit by the second run's start (CI, 2026-11-23)
    try:  # SIGKILL the Dreamer script (not its Ray worker) after its first episode: Ray retries, and it resumes
        deadline = time.time() + 600
        while not glob.glob(os.path.join(prior.folder, "*", "episodes", "*.npz")):
            assert time.time() < deadline and proc.poll() is None, "the run wrote no episode in time"
            time.sleep(0.05)
        pid = script_pid(prior.folder)
        assert pid, "the script ended before it could be killed"
        os.kill(pid, signal.SIGKILL)
        killed_at = len(glob.glob(os.path.join(prior.folder, "*", "episodes", "*.npz")))
        out, err = proc.communicate(timeout=1200)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err[-3000:]
    assert killed_at < 6
    assert "'CPU':" in out  # the cluster's resources line: Ray ran it
    assert "[1/2] balance__dreamer__s1: finished (resumed)" in out
    assert "[2/2] balance__uniform__s1: finished in" in out
    assert "--resume" in open(os.path.join(prior.folder, "log.txt")).read()
    inner = glob.glob(os.path.join(prior.folder, "*", "episodes"))
    assert len(inner) == 1 and len(os.listdir(inner[0])) == 6
    for name in ("balance__dreamer__s1", "balance__uniform__s1"):
        assert sorted(os.listdir(tmp_path / "results" / "tiny" / name)) == ["args.json", "metrics.jsonl"]
    with open(tmp_path / "results" / "tiny" / "balance__uniform__s1" / "args.json") as f:
        assert json.load(f)["prior_dirs"] == [os.path.dirname(inner[0])]
    # a second call finds both done and starts no Ray instance
    assert "2 done already, 0 to run" in sweep_cli(tmp_path, spec, "--ray-address", "local").stdout


@pytest.mark.parametrize("spec", sorted(glob.glob(os.path.join(ROOT, "sweeps", "*.toml"))), ids=os.path.basename)
def test_every_committed_spec_expands(spec):
    """Each spec under sweeps/ parses and passes sweep.py's checks (priors, filters, scripts): its dry run lists runs."""
    proc = run_script("sweep.py", spec, "--dry-run")
    runs = [line for line in proc.stdout.splitlines() if re.match(r"\S+__s\d+ \[(new|done|resume)", line)]
    assert runs and all("rama_" in line for line in runs if "[new]" in line)  # done runs print no command


def test_threads_per_run_keep_a_given_omp_num_threads(monkeypatch):
    """cores / workers by default; an OMP_NUM_THREADS the caller set wins (two sweeps of one worker each on 2 cores
    would otherwise run 2 threads each: 4 on 2 cores); an unusable value falls back to cores / workers."""
    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert [sweep.threads_per_run(w) for w in (1, 2, 3, 16)] == [8, 4, 2, 1]
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert sweep.threads_per_run(1) == 1
    for bad in ("0", "two", ""):
        monkeypatch.setenv("OMP_NUM_THREADS", bad)
        assert sweep.threads_per_run(2) == 4
