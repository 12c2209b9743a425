"""Reliability (issues 14, 126): bad input is one line on stderr with nothing written, non-finite losses stop the run
unsaved, one writer per run folder, SIGINT/SIGTERM stop with a folder that resumes to the same update count; a full
disk, memory that will not hold M and the replay, and checkpoints that hold pickled objects are each one line."""
import glob
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

import rama_dreamer as rd
from helpers import ROOT, TINY, run_script

pytestmark = pytest.mark.slow  # every test here runs the script in a subprocess (4-40 s each)

STATE = ["--env-id", "dmc/cartpole-balance", "--obs-type", "state", *TINY]  # 5-d observations, 1-d actions


def run(*flags, script="rama_dreamer.py", timeout=180):
    return run_script(script, *flags, check=False, timeout=timeout)


def snapshot(folder) -> dict:
    """Every file under folder (hidden ones too) with its size and modification time."""
    files = {}
    for dirpath, _, names in os.walk(folder):
        for name in names:
            stat = os.stat(os.path.join(dirpath, name))
            files[os.path.relpath(os.path.join(dirpath, name), folder)] = (stat.st_size, stat.st_mtime_ns)
    return files


def one_line_error(proc, *names) -> str:
    """Exit != 0 and exactly one line on stderr, naming each of names."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode != 0 and len(lines) == 1, (proc.returncode, proc.stderr[-3000:])
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


def read_metrics(run_path):
    with open(os.path.join(run_path, "metrics.jsonl")) as f:
        return [json.loads(line) for line in f]


def updates_logged(run_path):
    return [row["charts/updates"] for row in read_metrics(run_path) if "charts/updates" in row]


def saved_state(run_path):
    return torch.load(os.path.join(run_path, "checkpoint.pt"), weights_only=False)["state"]


def write_prior(folder, obs_shape, action_size, dtype=np.float32, episodes=2):
    os.makedirs(folder, exist_ok=True)
    for i in range(episodes):
        reward = np.ones(11, np.float32)
        rd.save_episode(str(folder), i, {"obs": np.zeros((11, *obs_shape), dtype), "reward": reward,
                                         "action": np.zeros((11, action_size), np.float32),
                                         "terminal": np.zeros(11, bool), "task": np.asarray("prior"),
                                         "return": np.asarray(reward.sum())})
    return str(folder)


def truncated_prior(folder):
    path = os.path.join(write_prior(folder, (5,), 1), "000000-10.npz")
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)
    return str(folder)


# (flags given the prior folder under tmp, what the line must name); cartpole: state (5,), action (1,), images 64x64
PRIOR_CASES = {
    "missing": (lambda tmp: ["--prior-dirs", str(tmp / "nope")], ["--prior-dirs", "nope"]),
    "empty": (lambda tmp: ["--prior-dirs", str(os.makedirs(tmp / "empty") or tmp / "empty")], ["--prior-dirs"]),
    "truncated npz": (lambda tmp: ["--prior-dirs", truncated_prior(tmp / "p")], ["000000-10.npz"]),
    "other image size": (lambda tmp: ["--prior-dirs", write_prior(tmp / "p", (32, 32, 3), 1, np.uint8),
                                      "--obs-type", "pixels"], ["000000-10.npz", "(32, 32, 3)"]),
    "other action size": (lambda tmp: ["--prior-dirs", write_prior(tmp / "p", (5,), 2)], ["000000-10.npz", "(2,)"]),
    "other obs type": (lambda tmp: ["--prior-dirs", write_prior(tmp / "p", (64, 64, 3), 1, np.uint8)],
                       ["000000-10.npz", "(64, 64, 3)"]),
}
CLI_CASES = {  # refused before any network or env is built
    "negative lr": (["--model-lr", "-1"], ["--model-lr"]),
    "nan lr": (["--actor-lr", "nan"], ["--actor-lr"]),
    "image too small": (["--image-size", "16", "--obs-type", "pixels"], ["--image-size"]),
    "horizon 1": (["--horizon", "1"], ["--horizon"]),
    "no camera 7": (["--camera", "7", "--obs-type", "pixels"], ["--camera"]),
    "empty sequence": (["--task-sequence", ","], ["--task-sequence"]),
}


@pytest.mark.parametrize("case", list(PRIOR_CASES) + list(CLI_CASES))
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, case):
    if case in PRIOR_CASES:
        make_flags, names = PRIOR_CASES[case]
        flags = ["--method", "uniform", *make_flags(tmp_path)]
    else:
        flags, names = CLI_CASES[case]
    runs = tmp_path / "runs"
    one_line_error(run(*STATE, "--run-dir", str(runs), *flags), *names)
    assert not runs.exists()  # not even an empty run folder


@pytest.mark.parametrize("prior", ["missing", "other action size"])
def test_bad_prior_dirs_write_nothing_in_metaworld(tmp_path, prior):
    folder = str(tmp_path / "nope") if prior == "missing" else write_prior(tmp_path / "p", (39,), 3)
    runs = tmp_path / "runs"
    proc = run("--env-id", "metaworld/push", "--obs-type", "state", *TINY, "--method", "uniform", "--prior-dirs", folder,
               "--run-dir", str(runs), script="rama_metaworld.py")
    one_line_error(proc, "--prior-dirs" if prior == "missing" else "000000-10.npz")
    assert not runs.exists()


PARSE_CASES = {  # (script, flags, the line on stderr): tyro's boxes were 4-9 lines
    "bad int": ("rama_dreamer.py", ["--batch-size", "abc"],
                "error: --batch-size: invalid literal for int() with base 10: 'abc'"),
    "bad float": ("rama_metaworld.py", ["--model-lr", "fast"], "error: --model-lr: could not convert"),
    "bad choice": ("rama_dreamer.py", ["--method", "foo"],
                   "error: --method: 'foo' is not one of dreamer, uniform, vrama, rrama, rbrama"),
    "bad choice, metaworld": ("rama_metaworld.py", ["--task-set", "foo"],
                              "error: --task-set: 'foo' is not one of train, new"),
    "bad optional bool": ("rama_dreamer.py", ["--cuda-graph", "maybe"], "error: --cuda-graph: 'maybe' is not one of"),
    "unknown flag": ("rama_dreamer.py", ["--no-such-flag"], "error: --no-such-flag: unknown flag"),
    "typo": ("rama_metaworld.py", ["--batchsize", "3"],
             "error: --batchsize: unknown flag (did you mean --batch-size?)"),
    "no value": ("rama_dreamer.py", ["--batch-size"], "error: --batch-size: needs a value"),
}


@pytest.mark.parametrize("case", list(PARSE_CASES))
def test_parse_errors_are_one_line(tmp_path, case):
    script, flags, line = PARSE_CASES[case]
    runs = tmp_path / "runs"
    proc = run("--run-dir", str(runs), *flags, script=script)
    assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1, proc.stderr
    assert proc.stderr.startswith(line), proc.stderr
    assert not runs.exists()


@pytest.mark.parametrize("script", ["rama_dreamer.py", "rama_metaworld.py"])
def test_help_still_prints(script):
    proc = run("--help", script=script)
    assert proc.returncode == 0 and "--batch-size" in proc.stdout and "--force" in proc.stdout, proc.stderr


@pytest.fixture(scope="module")
def done_run(tmp_path_factory):
    """A finished tiny run: 3 episodes of 100 env steps, 2 rounds of 2 updates, an evaluation at step 200."""
    root = tmp_path_factory.mktemp("done")
    run_script("rama_dreamer.py", *STATE, "--run-dir", str(root))
    (run_path,) = glob.glob(os.path.join(root, "*"))
    return run_path


@pytest.fixture
def copy_of(done_run, tmp_path):
    return shutil.copytree(done_run, tmp_path / "run")


def edit_args(**changes):
    def edit(run_path):
        with open(os.path.join(run_path, "args.json")) as f:
            saved = json.load(f)
        with open(os.path.join(run_path, "args.json"), "w") as f:
            json.dump({**saved, **changes}, f)
    return edit


def truncate(*names):
    def cut(run_path):
        for name in names:
            with open(os.path.join(run_path, name), "r+b") as f:
                f.truncate(100)
    return cut


def write_text(name, text):
    def write(run_path):
        with open(os.path.join(run_path, name), "w") as f:
            f.write(text)
    return write


def pickled_object(run_path):
    """A checkpoint.pt that runs code when unpickled: it would create a file in the run folder."""
    class Payload:
        def __reduce__(self):
            return open, (os.path.join(run_path, "code_ran"), "w")

    torch.save({"state": Payload()}, os.path.join(run_path, "checkpoint.pt"))


RESUME_CASES = {  # (what is done to the run folder, flags beside --resume, what the line must name)
    "other flags": (None, ["--env-id", "dmc/walker-walk", "--obs-type", "pixels", "--total-steps", "500"],
                    ["--env-id, --obs-type may not"]),
    "run dir": (None, ["--run-dir", "elsewhere"], ["--run-dir may not"]),
    "mlp_units": (edit_args(mlp_units=32), [], ["checkpoint.pt does not match args.json", "mlp_units 16"]),
    "obs_type": (edit_args(obs_type="pixels"), [], ["checkpoint.pt does not match args.json", "obs_type 'state'"]),
    "env_id": (edit_args(env_id="dmc/cartpole-swingup"), [], ["checkpoint.pt does not match", "env_id"]),
    "truncated checkpoints": (truncate("checkpoint.pt", "checkpoint.pt.prev"), [],
                              ["checkpoint.pt: not a readable checkpoint", "checkpoint.pt.prev"]),
    "broken args.json": (write_text("args.json", "{"), [], ["args.json"]),
    "unknown env in args.json": (edit_args(env_id="dmc/walker-fly"), [], ["args.json", "--env-id"]),
    "pickled object": (pickled_object, [], ["checkpoint.pt: holds a pickled", "could run code"]),  # not unpickled
}


@pytest.mark.parametrize("case", list(RESUME_CASES))
def test_bad_resume_is_one_line_and_changes_nothing(copy_of, case):
    damage, flags, names = RESUME_CASES[case]
    if damage:
        damage(copy_of)
    before = snapshot(copy_of)
    one_line_error(run("--resume", str(copy_of), *flags), *names)
    assert snapshot(copy_of) == before


def test_checkpoint_from_before_args_were_stored_names_the_mismatched_tensor(copy_of):
    path = os.path.join(copy_of, "checkpoint.pt")
    payload = torch.load(path, weights_only=False)
    del payload["args"]
    torch.save(payload, path)
    os.remove(path + ".prev")
    edit_args(mlp_units=32)(copy_of)
    line = one_line_error(run("--resume", str(copy_of), "--total-steps", "400"), "checkpoint.pt does not match")
    assert "size mismatch" in line and "torch.Size([16" in line


def test_resume_extends_a_run_with_total_steps(copy_of):
    proc = run("--resume", str(copy_of), "--total-steps", "400", "--eval-every", "1000")
    assert proc.returncode == 0, proc.stderr[-3000:]
    with open(os.path.join(copy_of, "args.json")) as f:
        saved = json.load(f)
    assert saved["total_steps"] == 400 and saved["eval_every"] == 1000 and saved["resume"] is None
    assert len(rd.list_episode_files(os.path.join(copy_of, "episodes"))) == 4
    assert updates_logged(copy_of) == [2, 4, 6] and saved_state(copy_of)["updates"] == 6


def test_damaged_newest_checkpoint_falls_back_to_the_one_before(copy_of):
    truncate("checkpoint.pt")(copy_of)
    proc = run("--resume", str(copy_of), "--total-steps", "400")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "checkpoint.pt: not a readable checkpoint" in proc.stdout and "falling back to" in proc.stdout
    assert len(rd.list_episode_files(os.path.join(copy_of, "episodes"))) == 4


def test_kill_after_a_round_does_not_redo_it(copy_of):
    # the state a kill leaves between the round at 2 episodes (checkpoint written) and the 3rd episode's file
    os.remove(rd.list_episode_files(os.path.join(copy_of, "episodes"))[-1])
    proc = run("--resume", str(copy_of))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert len(rd.list_episode_files(os.path.join(copy_of, "episodes"))) == 3
    assert saved_state(copy_of)["updates"] == 4  # as uninterrupted: 2 rounds of 2, the second not redone
    assert updates_logged(copy_of) == [2, 4]  # no duplicate row


@pytest.mark.parametrize("lr", ["1e9", "3"])
def test_non_finite_losses_stop_without_saving(tmp_path, lr):
    proc = run(*STATE, "--total-steps", "600", "--model-lr", lr, "--run-dir", str(tmp_path))
    line = one_line_error(proc, "non-finite")
    assert proc.returncode == 1
    update = int(re.search(r"non-finite (losses|addressing)/\w+ at update (\d+)", line).group(2))
    (run_path,) = glob.glob(os.path.join(tmp_path, "*"))
    rows = read_metrics(run_path)
    assert all(np.isfinite(v) for row in rows for v in row.values())  # nothing non-finite logged
    assert rows[-1]["errors/non_finite_update"] == update
    ckpt = os.path.join(run_path, "checkpoint.pt")
    assert os.path.exists(ckpt) == (update > 2)  # the first round (updates 1-2) saves the first checkpoint
    if os.path.exists(ckpt):  # the last good one: finite, from before the bad update
        payload = torch.load(ckpt, weights_only=False)
        assert payload["state"]["updates"] < update
        assert all(v.isfinite().all() for v in payload["agent"].values())
    assert lr != "3" or os.path.exists(ckpt)


def start(run_dir, *flags):
    proc = subprocess.Popen([sys.executable, os.path.join(ROOT, "rama_dreamer.py"), *STATE, "--run-dir", str(run_dir),
                             *flags], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    return proc


def wait_for(condition, proc, timeout=240):
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        if condition():
            return
        time.sleep(0.05)
    proc.kill()
    pytest.fail(f"timed out or exited: {proc.communicate()[1][-3000:]}")


def test_a_second_writer_is_refused(tmp_path):
    proc = start(tmp_path, "--total-steps", "100000")
    try:
        wait_for(lambda: glob.glob(os.path.join(tmp_path, "*", "checkpoint.pt")), proc)
        (run_path,) = glob.glob(os.path.join(tmp_path, "*"))
        one_line_error(run("--resume", run_path), "another process is writing this run folder")
    finally:
        proc.kill()
        proc.wait()
    # the lock goes with the process, even with kill -9
    assert run("--resume", run_path, "--total-steps", "100").returncode == 0


UPDATES = ["--updates-per-episode", "100"]  # rounds long enough to stop one in the middle


@pytest.fixture(scope="module")
def uninterrupted_updates(tmp_path_factory):
    root = tmp_path_factory.mktemp("uninterrupted")
    run_script("rama_dreamer.py", *STATE, *UPDATES, "--run-dir", str(root))
    (run_path,) = glob.glob(os.path.join(root, "*"))
    return saved_state(run_path)["updates"], updates_logged(run_path)[-1]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_mid_round_stops_cleanly_and_resumes_to_the_same_update_count(tmp_path, sig, uninterrupted_updates):
    proc = start(tmp_path, *UPDATES)
    episode_logged = lambda: any("charts/episodes" in row for row in read_metrics(glob.glob(  # noqa: E731
        os.path.join(tmp_path, "*"))[0])) if glob.glob(os.path.join(tmp_path, "*", "metrics.jsonl")) else False
    wait_for(episode_logged, proc)  # the first episode is stored: the first round of 100 updates starts
    time.sleep(0.3)
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=60)
    (run_path,) = glob.glob(os.path.join(tmp_path, "*"))
    lines = stderr.strip().splitlines()
    assert proc.returncode == 128 + sig and len(lines) == 1, stderr[-3000:]
    assert lines[0] == f"stopped by {sig.name}; continue with: python rama_dreamer.py --resume {run_path}"
    assert 0 < saved_state(run_path)["updates"] < 100  # stopped mid-round, the updates done so far saved
    assert rd.list_episode_files(os.path.join(run_path, "episodes"))  # complete episodes only
    proc = run("--resume", run_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    logged = updates_logged(run_path)
    assert (saved_state(run_path)["updates"], logged[-1]) == uninterrupted_updates == (200, 200)
    assert logged == sorted(set(logged))  # no row repeated


# ---------------------------------------------------------------------------------------------------------------
# Issue 126: a full disk, memory, out of memory at the first update, checkpoints that would run code on loading
# ---------------------------------------------------------------------------------------------------------------
def run_patched(patch: str, *flags, script="rama_dreamer.py"):
    """The script in a subprocess after `patch` (Python code) ran in it: a fault injected below the script."""
    code = (f"{patch}\nimport runpy, sys\nsys.argv = {[script, *flags]!r}\n"
            f"runpy.run_path({script!r}, run_name='__main__')")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)


def full_disk(pattern: str, nth: int) -> str:
    """The nth file opened for writing whose path matches pattern fills the disk: half its bytes land, then ENOSPC."""
    return f"""
import builtins, errno, io, re
real_open, seen = builtins.open, [0]
class Full(io.FileIO):
    def write(self, b):
        super().write(bytes(b)[:len(b) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")
def fake_open(file, mode="r", *args, **kwargs):
    if mode[0] in "wa" and re.search({pattern!r}, str(file)):
        seen[0] += 1
        if seen[0] == {nth}:
            raw = io.BufferedWriter(Full(file, mode[0]))
            return raw if "b" in mode else io.TextIOWrapper(raw)
    return real_open(file, mode, *args, **kwargs)
builtins.open = fake_open
"""


FULL_DISK_CASES = {  # (the write that fails: its path's pattern, which one; extra flags; the file the line names)
    "episode": (r"\.npz\.tmp$", 3, [], "000002-50.npz"),  # the third episode
    "checkpoint": (r"checkpoint\.pt\.tmp$", 2, [], "checkpoint.pt"),  # the second round's checkpoint
    "address.pt": (r"address\.pt\.tmp$", 2, ["--method", "rrama"], "address.pt"),
    "metrics": (r"metrics\.jsonl$", 3, [], "metrics.jsonl"),  # the second episode's line
}


@pytest.mark.parametrize("case", list(FULL_DISK_CASES))
def test_a_full_disk_stops_in_one_line_leaving_complete_files_and_resumes(tmp_path, case):
    pattern, nth, flags, name = FULL_DISK_CASES[case]
    proc = run_patched(full_disk(pattern, nth), *STATE, *flags, "--run-dir", str(tmp_path))
    (run_path,) = glob.glob(os.path.join(tmp_path, "*"))
    line = one_line_error(proc, name, "no space left on the device", "MiB free", f"--resume {run_path}")
    assert proc.returncode == 1, line
    assert not [f for f in snapshot(run_path) if f.endswith(".tmp")]  # no temp file left
    episodes = rd.list_episode_files(os.path.join(run_path, "episodes"))
    assert 0 < len(episodes) < 3  # stopped at once, before the run's third and last episode
    for path in episodes:  # every episode complete
        rd.load_episode(path)
    for ckpt in glob.glob(os.path.join(run_path, "*.pt*")):  # every checkpoint loadable
        torch.load(ckpt, weights_only=True)
    assert read_metrics(run_path)  # every line whole
    proc = run("--resume", run_path)  # space freed
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert len(rd.list_episode_files(os.path.join(run_path, "episodes"))) == 3
    assert saved_state(run_path)["updates"] == 4  # as an uninterrupted run: 2 rounds of 2


def test_a_run_that_will_not_fit_in_memory_is_refused_in_one_line(tmp_path):
    runs = tmp_path / "runs"
    proc = run(*STATE, "--total-steps", str(10**15), "--run-dir", str(runs))  # petabytes of replay
    one_line_error(proc, "will not fit", "GiB of memory available", "--prior-max-episodes", "--obs-type state",
                   "--force")
    assert proc.returncode == 2 and not runs.exists()


def test_memory_estimate_counts_k_prior_episodes_and_force_starts_anyway(tmp_path):
    import gymnasium

    prior = write_prior(tmp_path / "prior", (64, 64, 3), 1, np.uint8, episodes=10)  # 10 x 11 frames of 12 KB
    space = gymnasium.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    step = 64 * 64 * 3 + 4 + 5  # bytes: a frame, an action, a reward, a terminal
    own = 2 * 51 * step  # --total-steps 200 at 100 env steps (50 agent steps) per episode: 2 episodes of 51 steps
    meminfo = tmp_path / "meminfo"
    meminfo.write_text(f"MemTotal: 100 kB\nMemAvailable: {(own + 5 * 11 * step) // 1024} kB\n")
    args = rd.Args(env_id="dmc/cartpole-balance", method="uniform", total_steps=200, time_limit=100,
                   prior_dirs=(prior,))
    with pytest.raises(rd.UsageError, match=r"M \(10 prior episodes.*--prior-max-episodes"):
        rd.check_memory(args, space, 1, 1, str(meminfo))
    rd.check_memory(rd.dataclasses.replace(args, prior_max_episodes=4), space, 1, 1, str(meminfo))  # K = 4 fits
    rd.check_memory(rd.dataclasses.replace(args, force=True), space, 1, 1, str(meminfo))
    with pytest.raises(rd.UsageError, match="--total-steps 2,000"):  # 20 episodes of its own do not fit
        rd.check_memory(rd.dataclasses.replace(args, prior_dirs=(), total_steps=2000), space, 1, 1, str(meminfo))


OUT_OF_MEMORY = """
import torch
def out_of_memory(*args, **kwargs):
    raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 20.00 GiB")
torch.Tensor.backward = out_of_memory
"""


def test_out_of_memory_at_the_first_update_names_sizes_that_fit(tmp_path):
    proc = run_patched(OUT_OF_MEMORY, *STATE, "--run-dir", str(tmp_path))
    one_line_error(proc, "out of memory on cpu at the first update", "--batch-size 4 --seq-len 8",
                   "--batch-size 2 or --seq-len 4", "halve its activations")
    assert proc.returncode == 1


def test_checkpoints_from_before_issue_126_load_and_new_ones_need_no_pickles(copy_of):
    for name in ("checkpoint.pt", "checkpoint.pt.prev"):  # numpy's RNG state as an ndarray, as runs saved it before
        path = os.path.join(copy_of, name)
        payload = torch.load(path, weights_only=False)
        payload["rng"]["numpy"] = np.random.get_state()
        torch.save(payload, path)
    proc = run("--resume", str(copy_of), "--total-steps", "400")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert saved_state(copy_of)["updates"] == 6
    for name in ("checkpoint.pt", "checkpoint.pt.prev"):  # written now: tensors and plain types only
        torch.load(os.path.join(copy_of, name), weights_only=True)
