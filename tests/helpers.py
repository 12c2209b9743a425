"""Shared by the subprocess tests: tiny sizes and a runner for the experiment scripts."""
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# tiny sizes: 100-env-step episodes (50 agent steps at DMC's action repeat 2, 100 at Meta-World's 1), 3 episodes,
# one of them the random prefill, 2 updates each, small networks
TINY = ["--total-steps", "300", "--time-limit", "100", "--batch-size", "4", "--seq-len", "8",
        "--updates-per-episode", "2", "--prefill-episodes", "1", "--cnn-depth", "4", "--deter-size", "16",
        "--stoch-size", "4", "--hidden-size", "16", "--mlp-units", "16", "--horizon", "3", "--eval-every", "200",
        "--device", "cpu", "--address-units", "16", "--address-cnn-depth", "4", "--address-batch", "5",
        "--address-plot-every", "2", "--address-prob", "1.0"]


def run_script(script: str, *flags, check=True, timeout=300):
    """Run ROOT/script with flags in a subprocess; with check, fail the test on a non-zero exit."""
    proc = subprocess.run([sys.executable, os.path.join(ROOT, script), *flags], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)
    if check:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def synthetic_replay(obs_shape, action_size: int, episodes: int, length: int, rng, task: str = "synthetic"):
    """A rama_dreamer Replay of random episodes (the benchmark's generator): no environment needed."""
    import rama_dreamer
    from benchmarks.bench_update import synthetic_replay as add_random_episodes

    return add_random_episodes(rama_dreamer.Replay(), obs_shape, action_size, episodes, length, rng, task)
