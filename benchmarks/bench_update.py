"""Seconds per update of rama_dreamer.py (or rama_metaworld.py), every method, and collection speed.

Times the training script's own functions, imported: a full update of Algorithm 2 (addressing + world model +
actor + value) per method, at the paper's size (n=50 chunks of L=50 steps) and a small size (n=16, L=50), on
synthetic episodes (no environment in the timing), on the CPU and on CUDA when present; then collection in env steps
per second with the agent acting, in 1 env and in --num-envs envs. The first line names the date, the machine, torch,
the thread count, the speed flags and what was found about native bf16 on each device timed.

Every flag of the script is accepted too (--precision, --channels-last, --device, --obs-type,
--image-size, --env-id, --num-envs, --address-imagine-starts, --vrama-select, network sizes, ...).

Run (from the repository root):
    python benchmarks/bench_update.py                                  # every method, both sizes, CPU (and CUDA)
    python benchmarks/bench_update.py --device cuda --sizes paper --updates 5 --precision fp32
    python benchmarks/bench_update.py --device cpu --sizes paper --updates 2 --no-collection
    python benchmarks/bench_update.py --device cuda --profile          # the operators of one paper-size update
    python benchmarks/bench_update.py --device cpu --count-ops --sizes small --obs-type state --mlp-units 200
    python benchmarks/bench_update.py --device cpu --ab-flag channels-last --methods dreamer --updates 6
    python benchmarks/bench_update.py --device cuda --ab-flag cuda-graph --sizes paper --updates 20 \
        --json results/benchmarks/DATE-h100-graphs.json                # CUDA graphs on/off, paired, as JSON too
    git show 33e394e:rama_dreamer.py > /tmp/old.py                     # this version against an older one:
    python benchmarks/bench_update.py --device cpu --compare-to /tmp/old.py --sizes paper --methods dreamer
    python benchmarks/bench_update.py --script rama_metaworld --env-id metaworld/push --num-envs 4
    python benchmarks/bench_update.py --device cuda --cuda-graph True --share 1 4 16 --sizes small --obs-type state \
        --mlp-units 200 --methods dreamer                              # 1, 4, 16 processes sharing the GPU
"""
import collections
import dataclasses
import importlib
import importlib.util
import json
import multiprocessing
import os
import platform
import queue
import sys
import time
from dataclasses import dataclass
from typing import Literal, Optional, Tuple

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)  # the training scripts sit in the repository root

import numpy as np  # noqa: E402
import torch  # noqa: E402
import tyro  # noqa: E402

SCRIPTS = ("rama_dreamer", "rama_metaworld")
# the synthetic episodes' state vector and action sizes: walker-walk's (24, 6) and Meta-World's (39, 4)
STATE_AND_ACTION = {"rama_dreamer": ((24,), 6), "rama_metaworld": ((39,), 4)}
SIZES = {"paper": (50, 50), "small": (16, 50)}  # (n chunks, L steps)
PARTS = ["world_model", "actor_critic", "addressing", "batch_sampling"]
ROWS = []  # the printed table's rows as dicts, for --json


@dataclass
class Options:
    """What the benchmark times; the agent's flags that follow are the script's own."""
    script: Literal["rama_dreamer", "rama_metaworld"] = "rama_dreamer"
    """the script to time (the update is code the two share; collection runs the script's environment)"""
    updates: int = 3
    """timed updates per setting (after the warm-up updates)"""
    warmup: Optional[int] = None
    """untimed updates first; None = 1, or 5 with --cuda-graph (3 eager on the side stream, the capture, a replay)"""
    methods: Tuple[Literal["dreamer", "uniform", "rrama", "vrama", "rbrama"], ...] = (
        "dreamer", "uniform", "rrama", "vrama", "rbrama")
    """methods to time"""
    sizes: Tuple[Literal["paper", "small"], ...] = ("paper", "small")
    """sizes to time: paper (n=50, L=50), small (n=16, L=50)"""
    profile: bool = False
    """instead of the timings: profile one paper-size `dreamer` update and print the operators that take the time"""
    count_ops: bool = False
    """instead of the timings: count the operators one update of each method dispatches (views excluded), at the first
    of --sizes: on a GPU each is about one kernel, so a graphed update's time is about their number x a few µs"""
    collection: bool = True
    """also time collection (env steps per second, 1 env and --num-envs envs, on --env-id)"""
    ab_flag: Optional[str] = None
    """instead of the table: a boolean flag (e.g. channels-last) on against off, --updates pairs in one process"""
    compare_to: Optional[str] = None
    """instead of the table: this script against another version of it (a file, e.g. an older commit's), paired"""
    json: Optional[str] = None
    """also write the table's rows, and the first line's facts, to this JSON file"""
    share: Tuple[int, ...] = ()
    """instead of the table: for each N, N processes side by side on the one device, each running updates of the first
    of --methods at the first of --sizes for --share-seconds once all are warmed up: the updates per second of all
    together against one alone (do runs sharing a GPU add up?), and each process's GPU memory"""
    share_seconds: float = 15.0
    """how long each --share process runs updates after the common start"""


def script_flag(argv: list) -> str:
    """--script, read before parsing, because the flags that follow are that script's Args (tyro refuses a bad one)."""
    name = SCRIPTS[0]
    for i, arg in enumerate(argv):
        if arg == "--script" and i + 1 < len(argv):
            name = argv[i + 1]
        elif arg.startswith("--script="):
            name = arg.partition("=")[2]
    return name if name in SCRIPTS else SCRIPTS[0]


def parse(argv: list):
    """(script module, Options, the script's Args), from one command line: both sets of flags without prefixes."""
    script = importlib.import_module(script_flag(argv))
    Bench = dataclasses.make_dataclass("Bench", [
        ("benchmark", tyro.conf.OmitArgPrefixes[Options], dataclasses.field(default_factory=Options)),
        ("agent", tyro.conf.OmitArgPrefixes[script.Args], dataclasses.field(default_factory=script.Args))])
    bench = tyro.cli(Bench, args=argv, description=__doc__.split("\n\n")[0])
    return script, bench.benchmark, bench.agent


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor()


def synthetic_replay(replay, obs_shape, action_size: int, episodes: int, length: int, rng, task: str = "synthetic"):
    """Adds random episodes (images uint8 or state vectors, T+1 steps each) to a script's Replay: no environment
    needed. The tests use it too."""
    for _ in range(episodes):
        shape = (length + 1, *obs_shape)
        obs = rng.integers(0, 256, shape, dtype=np.uint8) if len(obs_shape) == 3 else rng.normal(size=shape)
        replay.add({"obs": obs, "action": rng.uniform(-1, 1, (length + 1, action_size)).astype(np.float32),
                    "reward": rng.uniform(0, 1, length + 1).astype(np.float32),
                    "terminal": np.zeros(length + 1, bool), "task": task})
    return replay


def time_collection(S, args, device: torch.device) -> None:
    """Env steps per second of collection with the agent's policy acting (rendering + one encoder and RSSM step per
    agent step), in one env and in --num-envs subprocesses, and per step of the envs what the policy took (its
    actions come back to the host, so the device has finished) against the rest (physics, rendering, bookkeeping):
    the share that graphing the policy's step could remove at most."""
    args = dataclasses.replace(args, time_limit=min(args.time_limit, 400), total_steps=10**9)
    policy, rng = None, np.random.default_rng(args.seed)
    acting = []  # seconds of each policy call in the round being timed (one call per step of the envs)

    def timed_act(obs):
        t0 = time.perf_counter()
        action = policy.act(obs, args.expl_noise, rng)
        acting.append(time.perf_counter() - t0)
        return action
    for num_envs in sorted({1, args.num_envs}):
        envs = S.make_envs(args, args.env_id, args.seed, num_envs)
        if policy is None:
            policy = S.Policy(S.Agent(envs.single_observation_space.shape, envs.single_action_space.shape[0],
                                      args).to(device), device)
        for _ in range(2):  # the first round warms up (subprocess start, renderer, kernels); the second is timed
            policy.reset(num_envs)
            acting.clear()
            t0 = time.perf_counter()
            episodes, _ = S.run_episodes(envs, timed_act, list(range(num_envs)), "bench")
            seconds = time.perf_counter() - t0
        steps = sum(len(ep["reward"]) - 1 for ep in episodes) * args.action_repeat
        print(f"{device.type:<6} collection {args.env_id} ({args.obs_type}), {num_envs} env(s): "
              f"{steps / seconds:.0f} env steps/s | per step of the envs: policy {1e3 * np.mean(acting):.2f} ms, "
              f"the rest {1e3 * (seconds - sum(acting)) / len(acting):.2f} ms", flush=True)
        envs.close()


def method_setup(S, args, method: str, n: int, length: int, obs_shape, action_size: int, device, **flags):
    """The args, agent, f_φ (for the addressed methods) and the update step (x, plan) -> output of one timed method
    at size (n, L), flags overridden: the script's `update`, or its GraphedUpdate with --cuda-graph."""
    run_args = dataclasses.replace(args, batch_size=n, seq_len=length, method=method, **flags)
    agent = S.Agent(obs_shape, action_size, run_args).to(device)
    addressing = S.Addressing(obs_shape, action_size, run_args, device) if method in S.ADDRESSED_METHODS else None
    if getattr(run_args, "cuda_graph", False):
        return run_args, agent, addressing, S.GraphedUpdate(agent, addressing, run_args)
    return run_args, agent, addressing, lambda x, plan: S.update(agent, addressing, x, plan, run_args)


def warmup_updates(options: Options, args) -> int:
    """--warmup, or its default: 1, or 5 when a timed version captures CUDA graphs."""
    if options.warmup is not None:
        return options.warmup
    graphs = getattr(args, "cuda_graph", False) or (options.ab_flag or "").replace("-", "_") == "cuda_graph"
    return 5 if graphs else 1


def one_update(S, setup, x, multitask, rng, device, i: int) -> dict:
    """Update i of Algorithm 2 as script S runs it: the host's plan, then the update (a script from before the
    fixed-shape update, --compare-to, plans inside its update)."""
    run_args, agent, addressing, step = setup
    if not hasattr(S, "plan_update"):
        return S.update(agent, x, multitask, addressing, run_args, rng, device, "current", i)
    return step(x, S.plan_update(run_args, multitask, addressing, rng, device, "current", i))


def timed_update(S, setup, batches, multitask, rng, device: torch.device, i: int):
    """Update i of a method_setup, the wait for its batch included, timed to the end of its GPU work: (seconds, the
    update's output with that wait in its batch_sampling timing)."""
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    x, waited = next(batches)
    out = one_update(S, setup, x, multitask, rng, device, i)
    out["timings"]["batch_sampling"] += waited
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t0, out


def sampled_batches(S, replay, n: int, length: int, rng, device, count: int):
    """The script's current-task batches, (x, seconds waited) `count` times: its sample_batches, or the ChunkSampler
    of a version from before 2026-12-07 (--compare-to), without its prefetch thread."""
    if hasattr(S, "sample_batches"):
        return S.sample_batches(replay, n, length, rng, device, count)
    return S.ChunkSampler(replay, n, length, rng, device, prefetch=False).batches(count)


def warmed_up(S, options: Options, args, setup, n: int, length: int, replay, multitask, rng, device, measured: int = 1):
    """Runs a method_setup's warm-up updates (--warmup) on chunks (n, L) and returns the batches, at the one of the
    update to measure next, and that update's index (--profile and --count-ops measure one update, --share as many
    as fit in its seconds: `measured` batches follow the warm-up's)."""
    warmup = warmup_updates(options, args)
    batches = sampled_batches(S, replay, n, length, rng, device, warmup + measured)
    for i in range(warmup):
        one_update(S, setup, next(batches)[0], multitask, rng, device, i)
    return batches, warmup


def profile_update(S, options: Options, args, obs_shape, action_size: int, replay, multitask, rng,
                   device: torch.device) -> None:
    """Where the time of one paper-size Dreamer update goes, operator by operator (after a warm-up update)."""
    from torch.profiler import ProfilerActivity, profile

    setup = method_setup(S, args, "dreamer", 50, 50, obs_shape, action_size, device)
    batches, i = warmed_up(S, options, args, setup, 50, 50, replay, multitask, rng, device)
    cuda = device.type == "cuda"
    with profile(activities=[ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])) as prof:
        one_update(S, setup, next(batches)[0], multitask, rng, device, i)
        if cuda:
            torch.cuda.synchronize()
    print(prof.key_averages().table(sort_by="self_cuda_time_total" if cuda else "self_cpu_time_total", row_limit=25,
                                    max_name_column_width=40), flush=True)


def count_update_ops(S, options: Options, args, obs_shape, action_size: int, replay, multitask, rng,
                     device: torch.device) -> None:
    """Operators dispatched by one update per method (after warm-up updates), views excluded, and the most frequent.
    A CPU count stands in for the kernels of a CUDA update, with known differences: Adam is set to its multi-tensor
    (foreach) step here, as on CUDA, but a GRU stays ~16 operators a step on a CPU, where CUDA fuses an nn.GRUCell step
    into 3 kernels and runs f_φ's nn.GRU over a whole chunk in cuDNN (so the RAMa methods' counts run high here)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.ops = collections.Counter()

        def __torch_dispatch__(self, func, types, func_args=(), kwargs=None):
            if not func.is_view:
                self.ops[func.__name__.split(".")[0]] += 1
            return func(*func_args, **(kwargs or {}))

    n, length = SIZES[options.sizes[0]]
    for method in options.methods:
        setup = method_setup(S, args, method, n, length, obs_shape, action_size, device)
        for opt in list(setup[1].optimizers().values()) + ([setup[2].opt] if setup[2] else []):
            for group in opt.param_groups:
                group["foreach"] = True
        batches, i = warmed_up(S, options, args, setup, n, length, replay, multitask, rng, device)
        with Count() as count:
            one_update(S, setup, next(batches)[0], multitask, rng, device, i)
        total = sum(count.ops.values())
        ROWS.append({"device": device.type, "size": options.sizes[0], "method": method, "operators": total,
                     "by_operator": dict(count.ops.most_common()), "flags": run_flags(args)})
        print(f"{device.type:<6} {options.sizes[0]:<6} {method:<8} {total:>6} operators | most frequent: "
              + ", ".join(f"{k} {v}" for k, v in count.ops.most_common(8)), flush=True)


def time_updates(S, options: Options, args, device: torch.device, obs_shape, action_size: int, replay, multitask,
                 rng) -> None:
    """One table row per size and method: mean seconds per update over options.updates updates after a warm-up."""
    for size in options.sizes:
        n, length = SIZES[size]
        reference = None
        for method in options.methods:
            setup = method_setup(S, args, method, n, length, obs_shape, action_size, device)
            totals = dict.fromkeys(PARTS + ["total"], 0.0)
            warmup = warmup_updates(options, args)
            batches = sampled_batches(S, replay, n, length, rng, device, options.updates + warmup)
            for i in range(options.updates + warmup):  # the warm-up (update 0 refreshes D, once per C)
                seconds, out = timed_update(S, setup, batches, multitask, rng, device, i)
                if i >= warmup:
                    totals["total"] += seconds / options.updates
                    for k in PARTS:
                        totals[k] += out["timings"].get(k, 0.0) / options.updates
            reference = reference or totals["total"]
            ROWS.append({"device": str(device), "size": size, "n": n, "L": length, "method": method,
                         "seconds": totals["total"], "vs_dreamer": totals["total"] / reference,
                         **{p: totals[p] for p in PARTS}, "flags": run_flags(args)})
            print(f"{str(device):<6} {size:<6} {n:>3} {length:>3} {method:<8} {totals['total']:>9.3f} "
                  f"{totals['total'] / reference:>9.2f}x " + " ".join(f"{totals[p]:>14.3f}" for p in PARTS),
                  flush=True)


def variants(S, options: Options, args) -> dict:
    """The two versions a paired timing compares, {label: (script module, its args)}: --ab-flag's flag on and off,
    or this script against --compare-to's copy of it (another commit's file, its Args filled from these flags)."""
    if options.ab_flag:
        name = options.ab_flag.replace("-", "_")  # main checked that it is a boolean flag
        return {"on": (S, dataclasses.replace(args, **{name: True})),
                "off": (S, dataclasses.replace(args, **{name: False}))}
    spec = importlib.util.spec_from_file_location("compared_script", options.compare_to)
    other = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(other)
    other_args = other.Args(**{f.name: getattr(args, f.name) for f in dataclasses.fields(other.Args)
                               if hasattr(args, f.name)})
    return {"this": (S, args), os.path.basename(options.compare_to): (other, other_args)}


def paired_timing(S, options: Options, args, device: torch.device, obs_shape, action_size: int, replay, multitask,
                  rng) -> None:
    """Paired timing of two versions (variants()) at the first of --sizes: two agents in one process, their updates
    alternating (which goes first alternates too), so the drift of a noisy machine falls on both. Separate commands
    differed by ±10% on the H100 from one command to the next, more than the effects measured. Prints each one's
    median seconds per update and per part, and the paired median ratio of the second to the first."""
    n, length = SIZES[options.sizes[0]]
    versions, warmup = variants(S, options, args), warmup_updates(options, args)
    (first, _), (second, _) = versions.items()
    print(f"{'device':<6} {'size':<6} {'method':<8} {'version':<24} {'median s':>9} "
          + " ".join(f"{p:>14}" for p in PARTS) + f"  {second}/{first} (paired median), pairs {first} faster",
          flush=True)
    for method in options.methods:
        setups, batches = {}, {}
        seconds, parts = {v: [] for v in versions}, {v: {p: [] for p in PARTS} for v in versions}
        for label, (module, version_args) in versions.items():
            torch.manual_seed(args.seed)  # the same initial weights for both
            setups[label] = method_setup(module, version_args, method, n, length, obs_shape, action_size, device)
            batches[label] = sampled_batches(module, replay, n, length, np.random.default_rng(args.seed), device,
                                             options.updates + warmup)
        for i in range(options.updates + warmup):  # the warm-up rounds (round 0 refreshes D)
            for label in (list(versions) if i % 2 else list(versions)[::-1]):
                took, out = timed_update(versions[label][0], setups[label], batches[label], multitask, rng, device, i)
                if i >= warmup:
                    seconds[label].append(took)
                    for p in PARTS:
                        parts[label][p].append(out["timings"].get(p, 0.0))
        a, b = np.array(seconds[first]), np.array(seconds[second])  # (updates,) each
        for label in versions:
            ROWS.append({"device": device.type, "size": options.sizes[0], "method": method, "version": label,
                         "median_seconds": float(np.median(seconds[label])), "seconds": seconds[label],
                         **{p: float(np.median(parts[label][p])) for p in PARTS},
                         "flags": run_flags(versions[label][1]),
                         f"paired_{second}_over_{first}": float(np.median(b / a)), "pairs": len(a),
                         f"pairs_{first}_faster": int(np.sum(b > a))})
            print(f"{device.type:<6} {options.sizes[0]:<6} {method:<8} {label:<24} {np.median(seconds[label]):>9.3f} "
                  + " ".join(f"{np.median(parts[label][p]):>14.3f}" for p in PARTS), flush=True)
        print(f"{'':<6} {'':<6} {method:<8} {'paired':<24} {f'{np.median(b / a):.3f}x':>9}  {np.sum(b > a)}/{len(a)} "
              f"pairs {first} faster", flush=True)


def share_worker(script: str, options: Options, args, rank: int, barrier, results) -> None:
    """One --share process: its own agent and synthetic episodes, warmed up (and captured), then updates in rounds of
    10 (a sync after each, as a real run syncs once per round) from the moment every process is ready until
    --share-seconds later. Puts (rank, updates done, seconds, bytes of device memory the allocator held at most)."""
    S, device = importlib.import_module(script), torch.device(args.device)
    n, length = SIZES[options.sizes[0]]
    obs_shape, action_size = observation_shape(script, args), STATE_AND_ACTION[script][1]
    rng = np.random.default_rng(args.seed + rank)
    replay, multitask = synthetic_data(S, obs_shape, action_size, rng)
    torch.manual_seed(args.seed + rank)
    setup = method_setup(S, args, options.methods[0], n, length, obs_shape, action_size, device)
    batches, warmup = warmed_up(S, options, args, setup, n, length, replay, multitask, rng, device, measured=10**9)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    barrier.wait()
    t0, done = time.perf_counter(), 0
    while time.perf_counter() - t0 < options.share_seconds:
        for _ in range(10):
            one_update(S, setup, next(batches)[0], multitask, rng, device, warmup + done)
            done += 1
        sync()
    memory = torch.cuda.max_memory_reserved() if device.type == "cuda" else 0
    results.put((rank, done, time.perf_counter() - t0, memory))


def shared_timing(options: Options, args) -> None:
    """--share: for each N, N processes (spawned, each with its own CUDA context) run updates side by side; one row
    per N: updates/s in all, per process, and against N = 1 (or the first N), and GPU memory per process."""
    context = multiprocessing.get_context("spawn")
    print(f"{'device':<6} {'size':<6} {'method':<8} {'procs':>5} {'updates/s':>10} {'per proc':>9} {'ms/update':>10} "
          f"{'vs first':>9} {'GiB/proc':>9}", flush=True)
    first = None
    for count in options.share:
        barrier, results = context.Barrier(count), context.Queue()
        procs = [context.Process(target=share_worker, args=(options.script, options, args, rank, barrier, results))
                 for rank in range(count)]
        for proc in procs:
            proc.start()
        rows = []  # (rank, updates, seconds, bytes), one per process
        while len(rows) < count:
            try:
                rows.append(results.get(timeout=5))
            except queue.Empty:  # a process that died (its traceback is above) would leave the others at the barrier
                if any(proc.exitcode not in (None, 0) for proc in procs):
                    for proc in procs:
                        proc.kill()
                    raise SystemExit(f"--share {count}: a process failed (exit codes "
                                     f"{[proc.exitcode for proc in procs]})")
        for proc in procs:
            proc.join()
        rate = sum(done / seconds for _, done, seconds, _ in rows)  # updates per second, all processes together
        first = first or rate
        memory = max(r[3] for r in rows) / 2**30
        ROWS.append({"device": args.device, "size": options.sizes[0], "method": options.methods[0],
                     "processes": count, "updates_per_second": rate, "vs_first": rate / first,
                     "ms_per_update": [1000 * seconds / done for _, done, seconds, _ in sorted(rows)],
                     "gib_per_process": memory, "seconds": options.share_seconds, "flags": run_flags(args),
                     "mps": bool(os.environ.get("CUDA_MPS_PIPE_DIRECTORY"))})
        print(f"{args.device:<6} {options.sizes[0]:<6} {options.methods[0]:<8} {count:>5} {rate:>10.1f} "
              f"{rate / count:>9.1f} {1000 * count / rate:>10.1f} {rate / first:>8.2f}x {memory:>9.2f}", flush=True)


def observation_shape(script: str, args) -> tuple:
    return (args.image_size, args.image_size, 3) if args.obs_type == "pixels" else STATE_AND_ACTION[script][0]


def synthetic_data(S, obs_shape, action_size: int, rng) -> tuple:
    """The timed task's replay (4 synthetic episodes of 500 steps) and M (4 of a prior task, then the replay's)."""
    replay = synthetic_replay(S.Replay(), obs_shape, action_size, episodes=4, length=500, rng=rng, task="current")
    multitask = synthetic_replay(S.Replay(), obs_shape, action_size, episodes=4, length=500, rng=rng, task="prior")
    for episode in replay.episodes:
        multitask.add(episode)
    return replay, multitask


def main(S, options: Options, args) -> None:
    """Seconds per full update per method and size, on CPU and on CUDA when present (--device auto), or on --device."""
    args = S.resolve_defaults(args)
    if getattr(args, "cuda_graph", False) is None:  # the scripts' default (graphs on CUDA); the benchmark times eager
        args = dataclasses.replace(args, cuda_graph=False)  # updates unless --cuda-graph True or --ab-flag cuda-graph
    S.check_args(args)
    if options.updates < 1:
        raise S.UsageError(f"--updates must be > 0 (got {options.updates})")
    bools = [f.name for f in dataclasses.fields(args) if isinstance(getattr(args, f.name), bool)]
    if options.ab_flag and options.ab_flag.replace("-", "_") not in bools:
        raise S.UsageError(f"--ab-flag {options.ab_flag}: not a boolean flag of {options.script} "
                           f"(one of {', '.join(S.flag(n)[2:] for n in bools)})")
    if any(count < 1 for count in options.share) or options.share_seconds <= 0:
        raise S.UsageError(f"--share {options.share} --share-seconds {options.share_seconds}: counts of processes "
                           "must be > 0, and the seconds too")
    if options.share and args.device == "auto":
        raise S.UsageError("--share: name the device (--device cuda or --device cpu)")
    if options.compare_to and not os.path.isfile(options.compare_to):
        raise S.UsageError(f"--compare-to {options.compare_to}: no such file")
    if (options.ab_flag or "").replace("-", "_") == "cuda_graph":
        S.check_args(dataclasses.replace(args, cuda_graph=True))  # --cuda-graph needs CUDA: one line if not
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else []) if args.device == "auto" else [args.device]
    facts = (f"{time.strftime('%Y-%m-%d')} | machine: {platform.machine()} {cpu_name()} | {os.cpu_count()} CPUs | "
             f"torch {torch.__version__} | threads {torch.get_num_threads()}"
             + (f" | {torch.cuda.get_device_name()}" if torch.cuda.is_available() else "")
             + f" | precision {args.precision} | channels-last {args.channels_last}"
             + "".join(f" | {d} bf16: {S.native_bf16(torch.device(d))[1]}" for d in devices))
    print(facts, flush=True)
    try:
        run(S, options, args, devices)
    finally:  # what was measured before a failure is kept too
        if options.json:
            with open(options.json, "w") as f:
                json.dump({"facts": facts, "argv": sys.argv[1:], "rows": ROWS}, f, indent=1)


def run_flags(args) -> str:
    """The speed flags of a row (which precision, layout, graphs), as the command line spells them."""
    return f"--precision {args.precision} --channels-last {args.channels_last} --cuda-graph " \
           f"{getattr(args, 'cuda_graph', False)}"


def run(S, options: Options, args, devices: list) -> None:
    for device_name in devices:  # check_args checked --device; `auto` times the CPU as well
        S.check_precision(args.precision, torch.device(device_name))
    if options.share:
        return shared_timing(options, args)
    obs_shape, action_size = observation_shape(options.script, args), STATE_AND_ACTION[options.script][1]
    rng = np.random.default_rng(args.seed)
    replay, multitask = synthetic_data(S, obs_shape, action_size, rng)
    if options.ab_flag or options.compare_to:
        return paired_timing(S, options, args, torch.device(devices[-1]), obs_shape, action_size, replay, multitask,
                             rng)
    if options.count_ops:
        return count_update_ops(S, options, args, obs_shape, action_size, replay, multitask, rng,
                                torch.device(devices[-1]))
    if options.profile:
        return profile_update(S, options, args, obs_shape, action_size, replay, multitask, rng,
                              torch.device(devices[-1]))
    print(f"{'device':<6} {'size':<6} {'n':>3} {'L':>3} {'method':<8} {'s/update':>9} {'vs dreamer':>10} "
          + " ".join(f"{p:>14}" for p in PARTS), flush=True)
    for device_name in devices:
        device = torch.device(device_name)
        time_updates(S, options, args, device, obs_shape, action_size, replay, multitask, rng)
        if options.collection:
            time_collection(S, args, device)


if __name__ == "__main__":
    script, options, args = parse(sys.argv[1:])
    try:
        main(script, options, args)
    except script.UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(e.code)
