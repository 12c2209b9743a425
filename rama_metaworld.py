"""RAMa with Dreamer on Meta-World with parametric task variability, from pixels: one file, read top to bottom.

Paper: Zholus & Panov, "Multitask Adaptation by Retrospective Exploration with Learned World Models" (Table 2).
A Dreamer (v1) agent (RSSM world model, actor and value trained in latent imagination) learns a Meta-World task
whose object and goal positions vary: 50 task vectors are drawn at start-up and one is made active at every reset,
never shown to the agent. Prior experience is collected on a "train" set of vectors; the adaptation run uses a
disjoint "new" set, and the addressing model f_φ picks chunks of the prior episodes to mix into the agent's batches
(RAMa: Retrospective Addressing for Multitask Adaptation; Algorithms 1-2, Eqs. 1-3). This file is a sibling of
rama_dreamer.py: `diff rama_dreamer.py rama_metaworld.py` shows only the environment and task logic.

Contents (each section sits under a `# ----` banner):
    1. imports              2. Args (every knob a flag)       3. environment (Meta-World v3, scripted experts)
    4. episode storage, replay and the multitask buffer       5. networks (encoder, decoder, RSSM, heads, f_φ)
    6. losses: λ-returns, KL with free nats, imagination, the Dreamer update
    7. Algorithm 2: the addressing step (f_φ on Eqs. 1-3), then the batch mix (q̂, masks)
    8. acting, logging, checkpoints                           9. the training loop (Algorithm 1)

Run:
    python rama_metaworld.py --env-id metaworld/push --task-set train --exp-name prior     # prior experience
    python rama_metaworld.py --env-id metaworld/push --collect-expert 200 --exp-name prior # or: scripted expert
    python rama_metaworld.py --env-id metaworld/push --task-set new --method rrama --prior-dirs runs/<prior run>
    python rama_metaworld.py --env-id metaworld/push --total-steps 400 --time-limit 100 --batch-size 4 \
        --seq-len 8 --updates-per-episode 2 --cnn-depth 4 --deter-size 16 --stoch-size 4 --hidden-size 16 \
        --mlp-units 16 --horizon 3                                         # tiny smoke run (seconds)
    python rama_metaworld.py --resume runs/<run>                          # continue a killed run
    python benchmarks/bench_update.py --script rama_metaworld             # seconds per update, collection
"""

# ----------------------------------------------------------------------------------------------------------
# 1. Imports
# ----------------------------------------------------------------------------------------------------------
import os

os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen rendering; must be set before mujoco is imported

import contextlib
import copy
import dataclasses
import errno
import fcntl
import functools
import glob
import importlib.util
import io
import json
import multiprocessing
import pickle
import random
import re
import shutil
import signal
import sys
import time
import types
from dataclasses import dataclass
from typing import Any, Literal, Optional, Tuple

import gymnasium
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from torch import distributions as td

td.Distribution.set_default_validate_args(False)  # argument checks cost Python time in the hot loops


# ----------------------------------------------------------------------------------------------------------
# 2. Args, in the paper's order
# ----------------------------------------------------------------------------------------------------------
@dataclass
class Args:
    # The run: method, environment, seed and budget
    method: Literal["dreamer", "uniform", "vrama", "rrama", "rbrama"] = "dreamer"
    """dreamer (no prior data), uniform (the paper's "No addressing"), vrama (Eq. 1), rrama (Eq. 2), rbrama (Eq. 3)"""
    env_id: str = "metaworld/push"
    """the environment: `metaworld/<task>` (push, peg-insert-side, sweep-into, dial-turn, drawer-close, any v3 name)"""
    task_sequence: Optional[str] = None
    """Algorithm 1: tasks trained in order in one run, e.g. `walker-stand,walker-walk`; overrides --env-id"""
    seed: int = 1
    """seed of python, numpy, torch, the environment and every sampler"""
    total_steps: int = 1_000_000
    """environment steps to train for (counting repeated actions, as the paper does)"""
    obs_type: Literal["pixels", "state"] = "pixels"
    """`pixels` (64x64 RGB, the paper) or `state` (the suite's proprioceptive vector, MLP encoder; cheap)"""
    action_repeat: int = 1
    """each action is repeated this many environment steps (Meta-World: the authors' 1, not Dreamer's 2;
    docs/deviations.md#metaworld-protocol)"""
    time_limit: Optional[int] = None
    """env steps per episode; None = 500 (Meta-World's own limit, also its maximum)"""
    image_size: int = 64
    """rendered image height and width"""
    camera: str = "corner2_moved"
    """camera: `corner2_moved` (corner2 at [0.75, 0.075, 0.7], the MWM / TD-MPC2 recipe) or a named camera"""
    task_set: Literal["train", "new"] = "train"
    """which 50 task vectors: `train` (collect prior experience) or the disjoint `new` set (adaptation)"""
    num_tasks: int = 50
    """task vectors drawn at start-up; one is active per episode and never shown to the agent"""
    render_quality: Literal["fast", "shadows", "default"] = "fast"
    """`fast` (no shadows or reflections, ~10 ms/frame on CPU), `shadows` (~40 ms), `default` (~130 ms)"""
    collect_expert: int = 0
    """write this many scripted-expert episodes to the run folder and exit (a fast prior buffer)"""

    # Algorithm 2 (Appendix B): n, L, C, S, p, β, m, K, and the addressing model f_φ
    batch_size: int = 50
    """n: chunks per batch"""
    seq_len: int = 50
    """L: steps per chunk"""
    updates_per_episode: int = 50
    """C: updates between two collected episodes (Meta-World: the authors' 100 per 1,000 env steps; the paper: 100)"""
    prefill_episodes: int = 10
    """S: random-action episodes before training (Meta-World: the authors' 5,000 env steps; the paper: 1)"""
    address_prob: float = 0.5
    """p: probability that a world-model batch mixes in multitask chunks"""
    current_fraction: float = 0.5
    """β: fraction of a mixed batch that stays current-task chunks"""
    address_batch: int = 50
    """m: multitask chunks scored against the current chunks per addressing update"""
    prior_max_episodes: int = 1000
    """K: prior episodes kept, subsampled at random"""
    prior_dirs: Tuple[str, ...] = ()
    """episode folders of earlier runs (or their run folders): the multitask buffer M"""
    prior_min_return: Optional[float] = None
    """least return of a kept prior episode (the paper: 600 for walker walk)"""
    address_refresh: int = 100
    """recompute the candidates' embeddings D every this many updates (C in Algorithm 2)"""
    address_candidates: int = 10_000
    """most candidate chunks of M in D (a random subset of M's chunks at each refresh)"""
    address_units: int = 200
    """GRU size of the addressing model = size of a trajectory embedding"""
    address_cnn_depth: int = 16
    """channel multiplier of the addressing model's own conv encoder"""
    address_lr: float = 1e-3
    """Adam learning rate of the addressing model"""
    address_grad_clip: float = 100.0
    """gradient norm clipping of the addressing model"""
    wm_on_addressed: bool = True
    """train the world model on addressed chunks too (off: they only start imagination)"""

    # Dreamer (v1): the world model
    deter_size: int = 200
    """RSSM deterministic (GRU) state size"""
    stoch_size: int = 30
    """RSSM stochastic (Gaussian) state size"""
    hidden_size: int = 200
    """RSSM hidden layer size"""
    cnn_depth: int = 32
    """channel multiplier of the conv encoder and decoder"""
    mlp_units: int = 400
    """units of the reward, value and actor MLPs (and of the state encoder/decoder)"""
    free_nats: Optional[float] = None
    """KL free nats; None = 3 for pixels (the paper), 0 for state (docs/deviations.md#state-observations)"""
    obs_std: Optional[float] = None
    """std of p(o|s); None = 1 for pixels (the paper), 0.1 for state (docs/deviations.md#state-observations)"""
    kl_scale: float = 1.0
    """weight of the KL term"""
    model_lr: float = 6e-4
    """Adam learning rate of the world model"""
    grad_clip: float = 100.0
    """gradient norm clipping of every optimiser"""
    adam_eps: float = 1e-4
    """epsilon of every Adam optimiser (Dreamer v1's 1e-4; torch's default is 1e-8)"""

    # Dreamer (v1): actor and value
    actor_lr: float = 8e-5
    """Adam learning rate of the actor"""
    value_lr: float = 8e-5
    """Adam learning rate of the value"""
    horizon: Optional[int] = None
    """imagination horizon; None = 15 (the paper's setting)"""
    gamma: float = 0.99
    """discount"""
    return_lambda: float = 0.95
    """λ of the λ-returns"""
    expl_noise: float = 0.3
    """std of the Gaussian noise added to actions while collecting"""
    actor_init_std: float = 5.0
    """the actor's std before training (tanh-normal)"""
    actor_min_std: float = 1e-4
    """the actor's minimal std"""
    actor_mean_scale: float = 5.0
    """the actor's pre-tanh mean is squashed to [-scale, scale]"""

    # Departures from the paper, and switches between its readings: each names its docs/deviations.md entry
    preset: Optional[Literal["authors-code"]] = None
    """`authors-code`: the authors' code's values of the flags in PRESETS; given flags win
    (docs/deviations.md#authors-preset)"""
    address_stop_grad_x: Optional[bool] = None
    """no gradient through f(x); None = on for rrama, rbrama; off for vrama (docs/deviations.md#stop-grad-x)"""
    address_standardize: bool = True
    """standardise the REINFORCE advantages over the batch (as the authors' code does)
    (docs/deviations.md#standardized-advantages)"""
    vrama_reduction: Literal["mean", "sum"] = "mean"
    """VRAMa: "mean" = γ^t-weighted mean of V_λ (Dreamer's actor loss); "sum" = Eq. 1's Σ_t
    (docs/deviations.md#vrama-reduction)"""
    vrama_select: Literal["embeddings", "frames"] = "embeddings"
    """VRAMa: what the straight-through one-hots multiply: the chunks' encodings or their frames
    (docs/deviations.md#vrama-select)"""
    address_imagine_starts: int = 0
    """VRAMa: imagine from this many random posteriors of the picks; 0 = all (the paper)
    (docs/deviations.md#imagine-starts)"""
    address_x_net: Literal["shared", "frozen"] = "shared"
    """f(x) by f_φ itself (the paper) or by a frozen copy of its initial weights (not in the paper;
    docs/deviations.md#frozen-x-net)"""
    address_layer_norm: bool = False
    """layer-normalise f_φ's per-step input layer (not in the paper; docs/deviations.md#address-net-size)"""
    address_reward_input: bool = False
    """feed f_φ the stored reward of each step too (not in the paper; docs/deviations.md#address-net-size)"""
    address_adam_eps: Optional[float] = None
    """epsilon of the addressing model's Adam; None = --adam-eps (docs/deviations.md#address-optimiser)"""
    address_weight_decay: float = 0.0
    """decoupled weight decay of f_φ: each step θ ← (1 − wd)·θ before Adam's (the authors' code: 1e-6)
    (docs/deviations.md#address-optimiser)"""
    own_episodes_in_m: bool = True
    """store the run's own episodes in M too (Algorithm 2); off: M holds prior data (and earlier tasks') only
    (docs/deviations.md#own-episodes-in-m)"""
    address_candidates_mode: Literal["memory", "fresh"] = "memory"
    """what q̂ picks from: `memory` (D over M's chunks, Algorithm 2) or `fresh` (m new chunks of M per mixed batch)
    (docs/deviations.md#fresh-candidates)"""
    address_logit_scale: float = 1.0
    """q̂'s logits are multiplied by this before the softmax (the authors' `temp`, read in their memory mode only)
    (docs/deviations.md#logit-scale)"""
    address_oversample_ends: bool = False
    """draw M's chunks with start min(U{0..T}, T+1−L), as the authors' replay does: the last chunk ~L/T of the time
    (docs/deviations.md#oversample-ends)"""
    reward_mask_borrowed: Literal["other-tasks", "all"] = "other-tasks"
    """which borrowed chunks lose their reward loss: other tasks' (the paper) or all of them (the authors' code)
    (docs/deviations.md#reward-mask-borrowed)"""
    vrama_objective: Literal["imagine", "posterior"] = "imagine"
    """VRAMa: −V_λ imagined from the picks (Eq. 1), or −λ-returns along the picks' own posteriors (the authors')
    (docs/deviations.md#vrama-posterior)"""
    addressed_wm_rule: Literal["rows", "batch"] = "rows"
    """with --no-wm-on-addressed: mask the borrowed rows, or skip the model step of a mixed batch (the authors')
    (docs/deviations.md#addressed-wm-rule)"""
    imagine_after_model_step: bool = False
    """step the world model before imagining (off: Dreamer v1 computes all three losses with the same parameters)
    (docs/deviations.md#update-order)"""
    init: Literal["keras", "torch"] = "keras"
    """weight initialisation: Dreamer v1's (Keras': Glorot-uniform, zero biases, orthogonal GRU) or torch's defaults
    (docs/deviations.md#init-eval-action)"""
    eval_action: Literal["sample-mode", "mean"] = "sample-mode"
    """evaluation's action: Dreamer v1's (the most likely of 100 samples) or the tanh of the Gaussian mean
    (docs/deviations.md#init-eval-action)"""
    actor_dist: Literal["tanh_normal", "trunc_normal"] = "tanh_normal"
    """the actor's distribution: Dreamer v1's tanh of a Gaussian, or the authors' DreamerV2 actor (a Gaussian with
    mean tanh(x) and std 2 sigmoid(x / 2) + --actor-min-std, truncated to [-1, 1]; they use --actor-min-std 0.1)
    (docs/deviations.md#actor-dist)"""
    slow_target: bool = False
    """bootstrap the λ-returns from a copy of the value refreshed every --slow-target-every updates (DreamerV2)
    (docs/deviations.md#slow-target)"""
    slow_target_every: int = 100
    """updates between two copies of the value into its slow target (the authors' `slow_target_update: 100`)
    (docs/deviations.md#slow-target)"""
    reward_scale: float = 1.0
    """the world model learns rewards times this, so values scale with it; logged returns and success stay raw
    (docs/deviations.md#metaworld-reward-scale)"""

    # Logging and run folders
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """this experiment's name (part of the run folder's name)"""
    run_dir: str = "runs"
    """the folder that holds run folders"""
    resume: Optional[str] = None
    """a run folder to continue with its args.json (only RESUME_FLAGS beside it)"""
    eval_every: int = 10_000
    """run evaluation episodes (no exploration noise) every this many environment steps, and at the last step"""
    eval_episodes: int = 1
    """evaluation episodes per evaluation"""
    capture_video: bool = False
    """save GIFs of eval episodes and (pixels) of open-loop world-model predictions under `videos/`"""
    plain_log: bool = False
    """print plain lines instead of progress bars (always so without a terminal on stderr)"""
    log_interval_seconds: float = 60.0
    """plain-log mode: a progress line at least this often inside a round of updates (0: after every update)"""
    address_plot_every: int = 10
    """draw the addressing-probabilities picture every this many episodes"""
    track: bool = False
    """log to Weights & Biases as well (needs `pip install wandb`)"""
    wandb_project: str = "rama"
    """the W&B project"""
    force: bool = False
    """start even when M and the replay will not fit in the memory available (this process only; --resume checks)"""

    # Speed (none changes what is learned, up to floating-point rounding)
    device: str = "auto"
    """`auto` (CUDA when present, else CPU), `cpu`, `cuda`, `cuda:1`, ..."""
    precision: Literal["fp32", "bf16"] = "fp32"
    """`bf16`: conv stacks and MLP hidden layers in bfloat16 autocast (RSSM, output layers, losses stay fp32)"""
    channels_last: bool = True
    """conv weights and activations in channels-last layout (10% faster updates on CPU; no change on an H100)"""
    num_envs: int = 1
    """environments collecting in parallel (subprocesses via gymnasium's AsyncVectorEnv when > 1)"""
    cuda_graph: Optional[bool] = None
    """capture each update as CUDA graphs and replay them (GraphedUpdate; eager if a capture fails). None: on when
    the device is CUDA (2.6-6x faster updates on an H100, the same math), off elsewhere; True on a CPU is refused"""


def resolve_defaults(args: Args) -> Args:
    """Fill the defaults that depend on the environment (right after parsing; saved resolved in args.json)."""
    free_nats = args.free_nats if args.free_nats is not None else (3.0 if args.obs_type == "pixels" else 0.0)
    obs_std = args.obs_std if args.obs_std is not None else (1.0 if args.obs_type == "pixels" else 0.1)
    return dataclasses.replace(args, horizon=args.horizon or 15, time_limit=args.time_limit or 500,
                               free_nats=free_nats, obs_std=obs_std)


def apply_preset(args: Args, given: set) -> Args:
    """--preset's values for the flags not given on the command line, and one line saying what it set."""
    if args.preset is None:
        return args
    values = {k: v for k, v in PRESETS[args.preset].items() if k not in given}
    print(f"preset {args.preset}: " + " ".join(f"{flag(k)} {v}" for k, v in values.items()) +
          (f" (given flags kept: {' '.join(flag(k) for k in sorted(given & set(PRESETS[args.preset])))})"
           if given & set(PRESETS[args.preset]) else ""), flush=True)
    return dataclasses.replace(args, **values)


# --preset authors-code: the authors' code (artemZholus/generalization_with_world_models at 6bd4a23, the paper's
# era) where it departs from the paper's text; docs/deviations.md#authors-preset names the file and line of each value
PRESETS = {"authors-code": dict(
    own_episodes_in_m=False, address_lr=1e-4, address_adam_eps=1e-5, address_weight_decay=1e-6,
    address_candidates_mode="fresh", address_batch=102, address_oversample_ends=True, reward_mask_borrowed="all",
    vrama_objective="posterior", address_stop_grad_x=True, addressed_wm_rule="batch", address_cnn_depth=32)}


def episode_agent_steps(args: Args) -> int:
    """Agent steps of a full episode: ceil(--time-limit / --action-repeat), ActionRepeat's rule."""
    return -(-args.time_limit // args.action_repeat)


def task_list(args: Args) -> list:
    """The env ids to train in order: --task-sequence (short names get --env-id's suite) or just --env-id."""
    if not args.task_sequence:
        return [args.env_id]
    suite_name = args.env_id.split("/")[0]
    return [t if "/" in t else f"{suite_name}/{t}" for t in args.task_sequence.split(",") if t.strip()]


ADDRESSED_METHODS = ("vrama", "rrama", "rbrama")


# ----------------------------------------------------------------------------------------------------------
# 3. Environment: Meta-World v3 from pixels, with parametric task variability
# ----------------------------------------------------------------------------------------------------------
MOVED_CAMERA_POS = (0.75, 0.075, 0.7)  # MWM / TD-MPC2 recipe: corner2 moved closer (3.1.1 ships it as corner4)
RENDER_QUALITIES = ("fast", "shadows", "default")


def make_env_spec(env_id: str) -> dict:
    """Parse `metaworld/<name>` (with or without `-v3`) into its parts; refuse unknown ids."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    suite_name, _, name = env_id.partition("/")
    name = name.removesuffix("-v3")
    if suite_name != "metaworld" or f"{name}-v3" not in ALL_V3_ENVIRONMENTS:
        known = ", ".join(f"metaworld/{n.removesuffix('-v3')}" for n in ("push-v3", "dial-turn-v3", "drawer-close-v3"))
        raise UsageError(f"--env-id: {env_id!r} is not a known environment (e.g. {known}, any Meta-World v3 name)")
    return {"suite": suite_name, "task": f"{name}-v3", "name": name}


@functools.lru_cache(maxsize=8)
def _sample_rand_vecs(task: str, seed: int, count: int) -> np.ndarray:
    """`count` distinct task vectors (float64), drawn as Meta-World draws its benchmark tasks: a reset with an
    unfrozen vector runs the task's own sampler, rejection loops included (pick-place redraws goals too close to the
    object), so every vector is valid. With the env's private generator (`seeded_rand_vec`), not Meta-World's global
    np.random seeding, nor the public `metaworld.ML1(name, seed)`: it draws test_tasks with seed + 1, so run s's new
    set is run s + 1's train set (checked on 3.1.1), and it fixes 50 vectors per set (no --num-tasks)."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    env = ALL_V3_ENVIRONMENTS[task]()
    env._freeze_rand_vec, env.seeded_rand_vec, env._set_task_called = False, True, True
    env.np_random = np.random.default_rng(seed)
    vecs = []
    for _ in range(20 * count):
        if len(vecs) == count:
            break
        env.reset()
        if not any(np.array_equal(env._last_rand_vec, v) for v in vecs):  # keep only distinct vectors
            vecs.append(env._last_rand_vec.copy())
    env.close()
    if len(vecs) < count:
        raise UsageError(f"--num-tasks: {task} has fewer than {count} distinct task vectors")
    return np.stack(vecs)


def task_vectors(env_name: str, task_set: str, seed: int, num_tasks: int = 50) -> np.ndarray:
    """The (num_tasks, D) float32 task vectors of a set: "train" (prior experience) or "new" (adaptation), the first
    and second half of one stream of 2 * num_tasks distinct draws: disjoint by construction, fixed by (env, seed)."""
    return _task_vectors64(env_name, task_set, seed, num_tasks).astype(np.float32)


def _task_vectors64(env_name, task_set, seed, num_tasks):
    if task_set not in ("train", "new"):
        raise UsageError(f"--task-set: {task_set!r} is not one of train, new")
    vecs = _sample_rand_vecs(make_env_spec(f"metaworld/{env_name}")["task"], int(seed), 2 * num_tasks)
    return vecs[:num_tasks] if task_set == "train" else vecs[num_tasks:]


class MetaWorldEnv(gymnasium.Env):
    """A Meta-World v3 task with a time limit and 64x64 RGB (or 39-d state) observations (ActionRepeat repeats).

    Parametric variability (paper, Sec. 5): `num_tasks` task vectors (object/goal positions) of `task_set` are
    drawn at start-up from `task_seed` (default: `seed`; the eval env gets the run's seed too: the same set). Each
    reset makes one active, chosen by the episode's seed (or the env's own generator when reset() gets none). Given
    its vector an episode is deterministic: Meta-World ignores reset(seed=) and env.seed(); the frozen vector alone
    places object and goal. The agent never sees the vector (the state's goal slot is zeroed, as in ML1;
    `task_vector` holds it for analysis); the goal marker (a green site) is drawn in the image, as in the visual
    Meta-World literature. `last_success`: True once info["success"] held at any env step of the episode."""

    def __init__(self, env_id, seed, obs_type="pixels", image_size=64, time_limit=500,
                 camera="corner2_moved", task_set="train", num_tasks=50, render_quality="fast", task_seed=None):
        import mujoco
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS
        from metaworld.types import Task

        spec = make_env_spec(env_id)
        if render_quality not in RENDER_QUALITIES:
            raise UsageError(f"--render-quality: {render_quality!r} is not one of {', '.join(RENDER_QUALITIES)}")
        self.task_name = spec["name"]
        self._env = ALL_V3_ENVIRONMENTS[spec["task"]]()
        self._env.max_path_length = time_limit  # Meta-World truncates there and raises one step later
        cls, task = type(self._env), spec["task"]
        self._vectors = _task_vectors64(spec["name"], task_set, seed if task_seed is None else task_seed, num_tasks)
        self._tasks = [Task(env_name=task, data=pickle.dumps(dict(rand_vec=v, env_cls=cls, partially_observable=True)))
                       for v in self._vectors]
        self._env.set_task(self._tasks[0])  # builds the goal space etc.; reset() picks the episode's task
        self._rng = np.random.default_rng(seed)
        self._obs_type = obs_type
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32)
        self.observation_space = gymnasium.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8) \
            if obs_type == "pixels" else gymnasium.spaces.Box(-np.inf, np.inf, (39,), np.float32)
        self.task_index, self.task_vector, self.last_success = 0, self._vectors[0].astype(np.float32), False
        self._state, self._policy = None, None

        model = self._env.model  # each env compiles its own MjModel: camera and quality edits stay local
        if camera == "corner2_moved":
            model.cam_pos[model.camera("corner2").id] = MOVED_CAMERA_POS
        cameras = ["corner2_moved"] + [model.camera(i).name for i in range(model.ncam)]
        if camera not in cameras:
            raise UsageError(f"--camera: {camera!r} is not one of {', '.join(cameras)}")
        self._camera = model.camera("corner2" if camera == "corner2_moved" else camera).id
        self._flip = camera.startswith("corner")  # corner cameras' xml poses were made for mujoco-py's
        # bottom-up buffers: flipping rows gives the upright (mirrored) view MWM/TD-MPC2 agents saw
        if render_quality != "default":  # read when the GL context is made: set before the Renderer
            model.vis.quality.offsamples = 0  # no multisampling
            model.vis.quality.shadowsize = 1024
        self._renderer = mujoco.Renderer(model, image_size, image_size)
        flags = self._renderer.scene.flags  # mjv_updateScene leaves these alone: set once
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = render_quality == "default"
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = render_quality != "fast"

    def observe(self):
        if self._obs_type == "pixels":
            return self.render()
        return self._state.astype(np.float32)  # 39-d, goal slot zeroed (partially observable)

    def render(self):
        self._renderer.update_scene(self._env.data, camera=self._camera)
        image = self._renderer.render()
        return np.ascontiguousarray(image[::-1] if self._flip else image)  # (H, W, 3) uint8

    def reset(self, *, seed=None, options=None):
        """The info holds the active task vector (EPISODE_EXTRAS: stored with the episode for analysis)."""
        rng = self._rng if seed is None else np.random.default_rng(seed)
        self.task_index = int(rng.integers(len(self._tasks)))
        self.task_vector = self._vectors[self.task_index].astype(np.float32)
        self._env.set_task(self._tasks[self.task_index])
        self._state, _ = self._env.reset()
        self.last_success = False
        return self.observe(), {"task_vector": self.task_vector, "task_index": self.task_index}

    def step(self, action):
        reward, terminated, truncated, info = self.step_physics(action)
        return self.observe(), reward, terminated, truncated, info

    def step_physics(self, action):
        """One env step without the observation: (reward, terminated, truncated, info). Meta-World never terminates
        (not even on success); it truncates at the time limit, and a further step would raise."""
        action = np.clip(np.asarray(action, np.float64), -1.0, 1.0)  # Meta-World leaves the gripper unclipped
        self._state, reward, _, truncated, info = self._env.step(action)
        self.last_success |= bool(info["success"])
        return float(reward), False, bool(truncated), {"success": bool(info["success"])}

    def close(self):
        """Free the GL context now: one left to the interpreter's exit prints EGL errors. Safe to call twice."""
        if self._renderer is not None:
            self._renderer.close()
            self._env.close()
            self._renderer = None


def expert_action(env: MetaWorldEnv) -> np.ndarray:
    """The scripted Meta-World policy's action for the env's current state (any obs_type). The policies read the
    goal from the last 3 state entries, which partial observability zeroes: a copy of the state gets it back."""
    if env._policy is None:
        import warnings

        from metaworld.policies import ENV_POLICY_MAP

        warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high")  # their gains clip; harmless
        env._policy = ENV_POLICY_MAP[f"{env.task_name}-v3"]()
    state = env._state.copy()
    state[-3:] = env._env._get_pos_goal()
    return np.clip(env._policy.get_action(state), -1.0, 1.0).astype(np.float32)


EPISODE_EXTRAS = ("task_vector", "task_index")  # the keys of reset's info an episode file stores as well


def check_prior_episodes(args: Args, multitask) -> None:
    """Table 2's protocol, checked before the run starts: the prior's episodes (M, a Replay) of this run's env ran on
    other task vectors than this run's (the prior with --task-set train, the run with --task-set new, the same --seed
    and --num-tasks: the new set is the draws after the first --num-tasks, so the same --task-set, or a run's smaller
    --num-tasks than the prior's, would share vectors)."""
    for env_id in task_list(args):
        name = make_env_spec(env_id)["name"]
        ours = {v.tobytes() for v in task_vectors(name, args.task_set, args.seed, args.num_tasks)}  # float32 bytes
        shared = sum(ep["task"] == name and "task_vector" in ep and
                     np.asarray(ep["task_vector"], np.float32).tobytes() in ours for ep in multitask.episodes)
        if shared:
            raise UsageError(f"--prior-dirs: {shared} of the prior's episodes of {name} ran on this run's own task "
                             f"vectors (--task-set {args.task_set}, --seed {args.seed}, --num-tasks {args.num_tasks}); "
                             f"collect the prior with --task-set train and adapt with --task-set new, the same --seed "
                             f"and --num-tasks")


class ActionRepeat(gymnasium.Wrapper):
    """Each action repeated `repeat` env steps within `time_limit` env steps per episode, for every family
    (docs/deviations.md#action-repeat): the rewards add up, success at any step counts, and an episode is truncated
    once it has taken time_limit env steps (or by the env itself), so it lasts ceil(time_limit / repeat) agent
    steps, the last action repeated only as far as the limit. The env steps with `step_physics(action)` -> (reward,
    terminated, truncated, info) and renders or reads its observation once per agent step, with `observe()`."""

    def __init__(self, env: gymnasium.Env, repeat: int, time_limit: int):
        super().__init__(env)
        self.repeat, self.time_limit, self.env_steps = repeat, time_limit, 0

    def reset(self, **kwargs):
        self.env_steps = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        reward, success = 0.0, None  # success stays None for envs that do not report it
        for _ in range(self.repeat):
            r, terminated, truncated, info = self.env.unwrapped.step_physics(action)
            reward, self.env_steps = reward + r, self.env_steps + 1
            if "success" in info:
                success = bool(success) or bool(info["success"])
            if terminated or truncated or self.env_steps >= self.time_limit:
                break
        info = info if success is None else {**info, "success": success}
        return self.env.unwrapped.observe(), reward, terminated, truncated or self.env_steps >= self.time_limit, info


def check_env_args(args: Args) -> None:
    """The flags of this script's environments, checked by check_args (section 10) with the rest."""
    if not args.num_tasks > 0:
        raise UsageError(f"--num-tasks must be > 0 (got {args.num_tasks})")
    if args.time_limit > 500:
        raise UsageError(f"--time-limit {args.time_limit}: Meta-World episodes last at most 500 steps")


def make_env(args: Args, env_id: str, seed: int) -> gymnasium.Env:
    # every env of a run (train and eval) draws its task vectors from the run's seed: the same set
    env = MetaWorldEnv(env_id, seed, args.obs_type, args.image_size, args.time_limit, args.camera, args.task_set,
                       args.num_tasks, args.render_quality, task_seed=args.seed)
    return ActionRepeat(env, args.action_repeat, args.time_limit)


def collect_expert_episodes(args: Args, run_path: str):
    """A fast prior buffer: episodes of Meta-World's scripted expert on the run's task set, then exit."""
    from tqdm import tqdm

    envs = make_envs(args, args.env_id, args.seed, 1)
    env = envs.envs[0].unwrapped
    episode_dir = os.path.join(run_path, "episodes")
    os.makedirs(episode_dir, exist_ok=True)
    try:
        for index in tqdm(range(len(list_episode_files(episode_dir)), args.collect_expert), desc="expert episodes"):
            episode = run_episodes(envs, lambda o: expert_action(env)[None], [args.seed * 1_000_003 + index],
                                   env.task_name)[0][0]
            episode["policy"] = np.asarray("expert")  # M's make-up (report.py: where the picks came from)
            save_episode(episode_dir, index, episode)
    finally:
        envs.close()
    print(f"wrote {args.collect_expert} expert episodes to {episode_dir}", flush=True)


# ----------------------------------------------------------------------------------------------------------
# 4. Episode storage and replay
# ----------------------------------------------------------------------------------------------------------
# An episode is a dict of arrays over T+1 steps: obs[t] is seen after action[t] (action[0] = 0) and brings
# reward[t] (reward[0] = 0); terminal[t] marks a true end (not a time limit). One `.npz` file per episode,
# named `{index:06d}-{agent_steps}.npz`, so the step count of a run is recoverable from the file names alone.
def save_episode(directory: str, index: int, episode: dict) -> str:
    """Write atomically (disk_write: a temp file in the same folder, then a rename), so a kill or a full disk never
    leaves half a file."""
    path = os.path.join(directory, f"{index:06d}-{len(episode['reward']) - 1}.npz")
    with disk_write(path) as f:
        np.savez_compressed(f, **episode)
    return path


def read_npz(path: str, keys=None) -> dict:
    try:
        with np.load(path) as data:
            return {k: data[k] for k in (data.files if keys is None else keys)}
    except Exception as e:  # a truncated or foreign file: name it, don't crash deep inside
        raise UsageError(f"{path}: not a readable episode file ({type(e).__name__}: {e})") from None


def load_episode(path: str) -> dict:
    episode = read_npz(path)
    missing = {"obs", "action", "reward", "terminal", "task"} - set(episode)
    if missing:
        raise UsageError(f"{path}: not an episode file (missing {sorted(missing)})")
    episode["task"] = str(episode["task"])
    return episode


def list_episode_files(directory: str) -> list:
    return sorted(glob.glob(os.path.join(directory, "[0-9]*.npz")))


class Replay:
    """Episodes in memory (images as uint8) and uniform sampling of fixed-length chunks, each addressed by (episode
    id, start): `gather` copies only the chunks, never whole episodes."""

    def __init__(self):
        self.episodes, self.tasks, self.returns, self.policies = [], [], [], []
        self._lengths = np.zeros(0, np.int64)  # (E,) steps per episode (T+1)

    def add(self, episode: dict):
        self.episodes.append(episode)
        self.tasks.append(str(episode["task"]))
        self.policies.append(str(episode.get("policy", "agent")))  # what collected it: a learning agent, or a script
        self.returns.append(float(episode["reward"].sum()))
        self._lengths = np.append(self._lengths, len(episode["reward"]))

    def memory_bytes(self) -> int:
        return sum(v.nbytes for ep in self.episodes for v in ep.values() if isinstance(v, np.ndarray))

    def __len__(self):
        return len(self.episodes)

    def _starts_per_episode(self, seq_len: int):
        return np.maximum(self._lengths - seq_len + 1, 0)  # (E,) chunk starts each episode offers

    def num_chunks(self, seq_len: int) -> int:
        return int(self._starts_per_episode(seq_len).sum())

    def sample_ids(self, n: int, seq_len: int, rng: np.random.Generator, oversample_ends: bool = False):
        """n (episode, start) pairs, uniform over all chunks of length seq_len; oversample_ends: a start uniform
        over the episode's T+1 steps, clipped to the last chunk's (the authors' replay): that chunk gets ~L/T."""
        starts_per_episode = self._starts_per_episode(seq_len)
        total = starts_per_episode.sum()
        if total == 0:
            raise ValueError(f"no episode has {seq_len} steps")
        episode_ids = rng.choice(len(self.episodes), size=n, p=starts_per_episode / total)  # (n,)
        if oversample_ends:
            return episode_ids, np.minimum(rng.integers(0, self._lengths[episode_ids]),
                                           starts_per_episode[episode_ids] - 1)
        starts = rng.integers(0, starts_per_episode[episode_ids])  # (n,)
        return episode_ids, starts

    def gather(self, episode_ids, starts, seq_len: int) -> dict:
        keys = ("obs", "action", "reward", "terminal")
        return {k: np.stack([self.episodes[e][k][s:s + seq_len] for e, s in zip(episode_ids, starts)]) for k in keys}

    def sample(self, n: int, seq_len: int, rng: np.random.Generator, oversample_ends: bool = False) -> dict:
        return self.gather(*self.sample_ids(n, seq_len, rng, oversample_ends), seq_len)

    def chunk_rewards(self, episode_ids, starts, seq_len: int) -> np.ndarray:
        """(n,) stored reward sums of the chunks: what RRAMa's bandit reward estimates on the current task."""
        return np.array([self.episodes[e]["reward"][s:s + seq_len].sum() for e, s in zip(episode_ids, starts)])

    def grid_ids(self, seq_len: int, cap: int, rng: np.random.Generator):
        """Non-overlapping chunks of every episode (a random phase each), at most `cap` of them at random."""
        episode_ids, starts = [], []
        for e, length in enumerate(self._lengths):
            if length >= seq_len:
                first = rng.integers(0, length - seq_len + 1) % seq_len
                grid = np.arange(first, length - seq_len + 1, seq_len)
                episode_ids.append(np.full(len(grid), e))
                starts.append(grid)
        episode_ids, starts = np.concatenate(episode_ids), np.concatenate(starts)
        if len(starts) > cap:
            keep = rng.choice(len(starts), cap, replace=False)
            episode_ids, starts = episode_ids[keep], starts[keep]
        return episode_ids, starts


def episode_folders(directory: str) -> list:
    """Where a run keeps episodes: DIR itself, DIR/episodes, or DIR/*/episodes (a --task-sequence run)."""
    for pattern in ("", "episodes", os.path.join("*", "episodes")):
        folders = [d for d in sorted(glob.glob(os.path.join(directory, pattern))) if list_episode_files(d)]
        if folders:
            return folders
    return []


def load_prior_episodes(dirs, min_return, max_episodes: int, obs_shape, action_size: int, rng) -> list:
    """The multitask buffer M: episodes of earlier runs, filtered by return, K of them at random."""
    paths = []
    for directory in dirs:
        if not os.path.isdir(directory):
            raise UsageError(f"--prior-dirs {directory}: no such folder")
        folders = episode_folders(directory)
        if not folders:
            raise UsageError(f"--prior-dirs {directory}: holds no episode files (NNNNNN-LEN.npz)")
        paths += [p for folder in folders for p in list_episode_files(folder)]
    if min_return is not None:  # reading one member of an .npz is cheap: filter before loading images
        paths = [p for p in paths if float(read_npz(p, ["return"])["return"]) >= min_return]
        if not paths:
            raise UsageError(f"--prior-min-return {min_return}: no prior episode has that return")
    if len(paths) > max_episodes:
        paths = [paths[i] for i in sorted(rng.choice(len(paths), max_episodes, replace=False))]
    episodes = []
    for path in paths:
        episode = load_episode(path)
        if episode["obs"].shape[1:] != tuple(obs_shape) or episode["action"].shape[1:] != (action_size,):
            raise UsageError(f"{path}: observations {episode['obs'].shape[1:]} / actions {episode['action'].shape[1:]}"
                             f" do not match the environment's {tuple(obs_shape)} / ({action_size},)")
        episodes.append(episode)
    return episodes


def to_device(batch: dict, device) -> dict:
    """numpy (or pinned torch) chunks (B, T, ...) -> torch tensors on device as stored (images uint8: 4x less to
    copy than floats)."""
    return {k: torch.as_tensor(v).to(device, non_blocking=True) for k, v in batch.items()}


def preprocess(batch: dict) -> dict:
    """Chunks on the device as stored -> what the networks read: images uint8 (B, T, H, W, 3) -> float (B, T, 3, H, W)
    in [-0.5, 0.5]; state obs, actions and rewards float; terminal stays bool."""
    obs = batch["obs"]
    obs = obs.permute(0, 1, 4, 2, 3).float().div_(255.0).sub_(0.5) if obs.dtype == torch.uint8 else obs.float()
    return {k: obs if k == "obs" else v if k == "terminal" else v.float() for k, v in batch.items()}


def to_torch(batch: dict, device) -> dict:
    """numpy (or pinned torch) chunks (B, T, ...) -> float torch tensors on device (terminal stays bool)."""
    return preprocess(to_device(batch, device))


def sample_batches(replay: Replay, n: int, seq_len: int, rng: np.random.Generator, device, count: int):
    """x_i ~ M_τ for `count` updates: yields (n chunks on the device, the seconds their sampling took), from the
    task's own random stream. The replay must not change meanwhile (episodes are added between rounds)."""
    device = torch.device(device)
    for _ in range(count):
        t0 = time.perf_counter()
        batch = {k: torch.from_numpy(v) for k, v in replay.sample(n, seq_len, rng).items()}
        if device.type == "cuda":  # page-locked memory: the copy to the GPU runs asynchronously
            batch = {k: v.pin_memory() for k, v in batch.items()}
        yield to_torch(batch, device), time.perf_counter() - t0


# ----------------------------------------------------------------------------------------------------------
# 5. Networks
# ----------------------------------------------------------------------------------------------------------
class MLP(nn.Module):
    """ELU hidden layers then a linear output: (..., in) -> (..., out). With --precision bf16 the hidden layers run
    in bfloat16 autocast; the output layer stays fp32 (a value of ~100 in bf16 would be off by up to 0.5)."""

    bf16 = False

    def __init__(self, in_size: int, units: int, layers: int, out_size: int):
        super().__init__()
        hidden = []
        for _ in range(layers):
            hidden += [nn.Linear(in_size, units), nn.ELU()]
            in_size = units
        self.hidden, self.out = nn.Sequential(*hidden), nn.Linear(in_size, out_size)

    def forward(self, x):
        with torch.autocast(x.device.type, torch.bfloat16, enabled=self.bf16, cache_enabled=False):
            x = self.hidden(x)
        return self.out(x.float())


def conv_sizes(size: int, layers: int = 4) -> list:
    """Spatial sizes through `layers` convs with kernel 4, stride 2, no padding: 64 -> 31 -> 14 -> 6 -> 2."""
    sizes = [size]
    for _ in range(layers):
        sizes.append((sizes[-1] - 4) // 2 + 1)
    return sizes


class ConvEncoder(nn.Module):
    """Four convs (kernel 4, stride 2, depths 1,2,4,8 x depth): (N, 3, H, W) -> (N, embed_size)."""

    bf16, channels_last = False, False  # set by set_speed_options (--precision, --channels-last)

    def __init__(self, obs_shape, depth: int):
        super().__init__()
        height, width, channels = obs_shape
        layers, in_ch = [], channels
        for i in range(4):
            layers += [nn.Conv2d(in_ch, depth * 2**i, 4, 2), nn.ReLU()]
            in_ch = depth * 2**i
        self.net = nn.Sequential(*layers, nn.Flatten())
        self.embed_size = in_ch * conv_sizes(height)[-1] * conv_sizes(width)[-1]

    def forward(self, obs):  # (B, T, 3, H, W) -> (B, T, E)
        x = obs.flatten(0, 1)  # (B*T, 3, H, W)
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        with torch.autocast(x.device.type, torch.bfloat16, enabled=self.bf16, cache_enabled=False):
            x = self.net(x)
        return x.float().unflatten(0, obs.shape[:2])


def decoder_last_layer(size: int) -> tuple:
    """(kernel, stride) of the decoder's last transposed conv along an image side of `size` pixels. Dreamer v1's
    layers grow 1 -> 5 -> 13 -> 30 -> 64 (kernels 5, 5, 6, 6, stride 2); the last maps 30 to 29·stride + kernel, so
    stride = (size - 1) // 30 and kernel = size - 29·stride: v1's (6, 2) at 64, (9, 3) for the kitchen's 96."""
    stride = (size - 1) // 30
    if stride < 1:
        raise UsageError(f"--image-size {size}: Dreamer v1's decoder needs at least 31 pixels a side")
    return size - 29 * stride, stride


class ConvDecoder(nn.Module):
    """Dreamer v1's decoder: features -> dense 32·depth at 1x1 -> transposed convs (kernels 5, 5, 6, 6, stride 2,
    depths 4d, 2d, d, 3) -> mean image (B, T, 3, H, W). A side other than 64 changes the last layer alone (above)."""

    bf16, channels_last = False, False  # set by set_speed_options (--precision, --channels-last)

    def __init__(self, feat_size: int, obs_shape, depth: int):
        super().__init__()
        height, width, channels = obs_shape
        (kh, sh), (kw, sw) = decoder_last_layer(height), decoder_last_layer(width)
        self.linear = nn.Linear(feat_size, 32 * depth)
        self.net = nn.Sequential(
            nn.ConvTranspose2d(32 * depth, 4 * depth, 5, 2), nn.ReLU(),  # (4d, 5, 5)
            nn.ConvTranspose2d(4 * depth, 2 * depth, 5, 2), nn.ReLU(),  # (2d, 13, 13)
            nn.ConvTranspose2d(2 * depth, depth, 6, 2), nn.ReLU(),  # (d, 30, 30)
            nn.ConvTranspose2d(depth, channels, (kh, kw), (sh, sw)))  # (3, H, W)

    def forward(self, feat):  # (B, T, F) -> (B, T, 3, H, W)
        with torch.autocast(feat.device.type, torch.bfloat16, enabled=self.bf16, cache_enabled=False):
            x = self.linear(feat.flatten(0, 1))  # (B*T, 32*depth)
            # the first transposed conv reads a 1x1 input: it is a matrix product with its weight (in, out*5*5), the
            # same numbers 6x faster on CPU than oneDNN's transposed-conv kernel (tested against it)
            first = self.net[0]
            x = (x @ first.weight.to(x.dtype).flatten(1)).unflatten(1, first.weight.shape[1:])  # (B*T, 4d, 5, 5)
            x = x + first.bias.to(x.dtype)[:, None, None]
            if self.channels_last:
                x = x.contiguous(memory_format=torch.channels_last)
            x = self.net[1:](x)
        return x.float().unflatten(0, feat.shape[:2])


def mlp_encoder(obs_size: int, units: int) -> nn.Module:
    """State observations: (B, T, D) -> (B, T, units); the decoder is a plain MLP back to D."""
    encoder = nn.Sequential(MLP(obs_size, units, 2, units), nn.ELU())
    encoder.embed_size = units
    return encoder


def init_weights(module: nn.Module, scheme: str) -> nn.Module:
    """--init keras: Dreamer v1's initialisation (and the authors' code's: both Keras' defaults): Glorot-uniform
    weights, zero biases, orthogonal recurrent GRU weights. The RSSM's posterior layer, split in two here, gets the
    bound of v1's one layer over [h, e]. --init torch leaves torch's defaults (runs before 2026-11-24)."""
    if scheme == "torch":
        return module
    for m in module.modules():
        if isinstance(m, (nn.Linear, nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.xavier_uniform_(m.weight)  # uniform, bound sqrt(6 / (fan_in + fan_out))
        for name, param in m.named_parameters(recurse=False):
            if name.startswith("bias"):
                nn.init.zeros_(param)
            elif isinstance(m, (nn.GRU, nn.GRUCell)):  # (3H, in) input weights, (3H, H) recurrent ones
                (nn.init.orthogonal_ if name.startswith("weight_hh") else nn.init.xavier_uniform_)(param)
    for m in module.modules():  # after the loop above, which visits the RSSM before its layers
        if isinstance(m, RSSM):
            fan_in = m.obs_deter.in_features + m.obs_embed.in_features
            bound = np.sqrt(6.0 / (fan_in + m.obs_deter.out_features))
            for layer in (m.obs_deter, m.obs_embed):
                nn.init.uniform_(layer.weight, -bound, bound)
    return module


class RSSM(nn.Module):
    """Recurrent state-space model: prior p(z_t | h_t), h_t = GRU(h_{t-1}, z_{t-1}, a_t); posterior
    q(z_t | h_t, e_t), e_t the obs embedding. A state is a dict: mean, std, stoch (B, S) and deter (B, D)."""

    def __init__(self, action_size, embed_size, stoch_size=30, deter_size=200, hidden_size=200):
        super().__init__()
        self.stoch_size, self.deter_size, self.feat_size = stoch_size, deter_size, stoch_size + deter_size
        self.img_in = nn.Linear(stoch_size + action_size, hidden_size)
        self.gru = nn.GRUCell(hidden_size, deter_size)
        self.img_out = nn.Sequential(nn.Linear(deter_size, hidden_size), nn.ELU(), nn.Linear(hidden_size, 2 * stoch_size))
        # the posterior's first layer reads [h, e]; split in two so the embedding half runs once for all t
        self.obs_deter = nn.Linear(deter_size, hidden_size)
        self.obs_embed = nn.Linear(embed_size, hidden_size, bias=False)
        self.obs_out = nn.Linear(hidden_size, 2 * stoch_size)

    def initial(self, batch: int, device) -> dict:
        zeros = lambda n: torch.zeros(batch, n, device=device)  # noqa: E731
        return {"mean": zeros(self.stoch_size), "std": zeros(self.stoch_size),
                "stoch": zeros(self.stoch_size), "deter": zeros(self.deter_size)}

    @staticmethod
    def feat(state: dict):
        return torch.cat([state["stoch"], state["deter"]], -1)

    @staticmethod
    def _gaussian(x):
        """A layer's output (..., 2S) -> mean and std (..., S) of a diagonal Gaussian, std > 0.1."""
        mean, std = x.chunk(2, -1)
        return mean, F.softplus(std) + 0.1

    def _dist_params(self, x):
        mean, std = self._gaussian(x)
        return mean, std, mean + std * torch.randn_like(std)

    def deter_step(self, state: dict, action):
        """h_t = GRU(h_{t-1}, [z_{t-1}, a_t]): (B, D)."""
        return self.gru(F.elu(self.img_in(torch.cat([state["stoch"], action], -1))), state["deter"])

    def img_step(self, state: dict, action) -> dict:
        """The prior p(z_t | h_t) and a sample of it: one imagined step."""
        deter = self.deter_step(state, action)
        mean, std, stoch = self._dist_params(self.img_out(deter))
        return {"mean": mean, "std": std, "stoch": stoch, "deter": deter}

    def obs_step(self, deter, embed_proj) -> dict:
        """Posterior q(z_t | h_t, e_t) from h_t and the projected embedding (obs_embed(e_t), precomputed)."""
        x = F.elu(self.obs_deter(deter) + embed_proj)
        mean, std, stoch = self._dist_params(self.obs_out(x))
        return {"mean": mean, "std": std, "stoch": stoch, "deter": deter}

    def observe(self, embed, action, state: Optional[dict] = None):
        """Filter a chunk: embed (B, T, E), action (B, T, A) -> posteriors (mean, std, stoch, deter) and priors (mean,
        std, deter), dicts of (B, T, ...)."""
        if state is None:
            state = self.initial(embed.shape[0], embed.device)
        embed_proj = self.obs_embed(embed)  # (B, T, hidden), one matmul for the whole chunk
        posts = []
        # unbind, not [:, t]: the backward pass stacks the T gradients once, not T zero-filled copies of the chunk
        for action_t, embed_proj_t in zip(action.unbind(1), embed_proj.unbind(1)):
            state = self.obs_step(self.deter_step(state, action_t), embed_proj_t)
            posts.append(state)
        post = {k: torch.stack([s[k] for s in posts], 1) for k in posts[0]}
        # the filter never reads a prior's sample, only its mean and std (the KL): the prior head runs once for all
        # t, after the loop, instead of at every step (the same values; 15% fewer operators in an update, counted by
        # bench_update.py --count-ops: on a GPU, fewer kernels)
        mean, std = self._gaussian(self.img_out(post["deter"]))  # (B, T, S) each
        return post, {"mean": mean, "std": std, "deter": post["deter"]}

    def imagine_actions(self, state: dict, actions):
        """Open-loop rollout with given actions (B, T, A) -> prior states (B, T, ...)."""
        priors = []
        for t in range(actions.shape[1]):
            state = self.img_step(state, actions[:, t])
            priors.append(state)
        return {k: torch.stack([s[k] for s in priors], 1) for k in priors[0]}


class WorldModel(nn.Module):
    def __init__(self, obs_shape, action_size, args: Args):
        super().__init__()
        pixels = len(obs_shape) == 3
        self.encoder = ConvEncoder(obs_shape, args.cnn_depth) if pixels else mlp_encoder(obs_shape[0], args.mlp_units)
        self.rssm = RSSM(action_size, self.encoder.embed_size, args.stoch_size, args.deter_size, args.hidden_size)
        feat = self.rssm.feat_size
        self.decoder = (ConvDecoder(feat, obs_shape, args.cnn_depth) if pixels
                        else MLP(feat, args.mlp_units, 2, obs_shape[0]))
        self.reward = MLP(feat, args.mlp_units, 2, 1)


class Actor(nn.Module):
    """Tanh-normal (or truncated-normal) policy over features: (..., F) -> a distribution over actions in [-1, 1]^A."""

    def __init__(self, feat_size, action_size, units, init_std=5.0, min_std=1e-4, mean_scale=5.0,
                 dist: str = "tanh_normal"):
        super().__init__()
        self.net = MLP(feat_size, units, 4, 2 * action_size)
        self.action_size = action_size
        self.init_std, self.min_std, self.mean_scale, self.dist = init_std, min_std, mean_scale, dist

    def forward(self, feat):
        if self.dist == "trunc_normal":  # docs/deviations.md#actor-dist
            mean, std = self.net(feat).float().chunk(2, -1)  # (..., A) each
            return td.Independent(TruncatedNormal(torch.tanh(mean), 2 * torch.sigmoid(std / 2) + self.min_std), 1)
        return tanh_normal(self.net(feat), self.init_std, self.min_std, self.mean_scale)

    def std(self, feat):
        """(N, F) -> (N, A): the Gaussian's std, before the tanh or the truncation."""
        dist = self(feat).base_dist
        return dist.scale if self.dist == "trunc_normal" else dist.base_dist.scale

    def mode(self, feat, rule: str = "sample-mode", samples: int = 100):
        """The action used in evaluation, feat (N, F) -> (N, A): Dreamer v1's mode estimate, the most likely of 100
        samples (--eval-action sample-mode: with the initial std of 5 that is a nearly saturated action), or the tanh
        of the Gaussian mean (--eval-action mean)."""
        if self.dist == "trunc_normal":  # its mode is its mean before the truncation (the authors' actor.mode())
            return self(feat).base_dist.loc
        if rule == "mean":
            mean = self.net(feat).chunk(2, -1)[0]
            return torch.tanh(self.mean_scale * torch.tanh(mean / self.mean_scale))
        dist = self(feat)
        sample = dist.sample((samples,))  # (S, N, A)
        best = dist.log_prob(sample).argmax(0)  # (N,)
        return sample[best, torch.arange(len(best), device=best.device)]


def tanh_normal(out, init_std, min_std, mean_scale):
    """Dreamer's squashed Gaussian: mean in [-scale, scale], std = softplus(x + softplus^-1(init)) + min."""
    mean, std = out.chunk(2, -1)
    mean = mean_scale * torch.tanh(mean / mean_scale)
    std = F.softplus(std + np.log(np.expm1(init_std))) + min_std
    dist = td.TransformedDistribution(td.Normal(mean, std), [td.TanhTransform(cache_size=1)])
    return td.Independent(dist, 1)


class TruncatedNormal(td.Distribution):
    """N(loc, scale) restricted to [-1, 1], elementwise (the authors' `TruncNormalDist`, common/dists.py). Samples
    invert the CDF, so gradients reach loc and scale; they are clipped 1e-6 inside the bounds with a straight-through
    gradient, as theirs. loc in (-1, 1) keeps 0.5 inside [cdf(-1), cdf(1)], so the inversion never degenerates."""
    arg_constraints, has_rsample, clip = {}, True, 1e-6

    def __init__(self, loc, scale):
        self.loc, self.scale = loc, scale
        self.cdf_low = torch.special.ndtr((-1 - loc) / scale)
        self.cdf_high = torch.special.ndtr((1 - loc) / scale)
        super().__init__(loc.shape, validate_args=False)

    def rsample(self, sample_shape=torch.Size()):
        uniform = torch.rand(self._extended_shape(sample_shape), device=self.loc.device)
        u = (self.cdf_low + uniform * (self.cdf_high - self.cdf_low)).clamp(1e-6, 1 - 1e-6)
        x = self.loc + self.scale * torch.special.ndtri(u)
        return x + (x.clamp(-1 + self.clip, 1 - self.clip) - x).detach()

    def log_prob(self, x):
        z = (x - self.loc) / self.scale
        return -0.5 * z ** 2 - 0.5 * np.log(2 * np.pi) - self.scale.log() - (self.cdf_high - self.cdf_low).log()


# ALGO LOGIC: addressing
class AddressNet(nn.Module):
    """f_φ: a chunk -> an embedding (B, units), the last output of a GRU over [frame features, action] (Section 4.2).
    Its own encoder: what makes a good addressing is not what makes a good reconstruction. layer_norm and
    reward_input are not in the paper (--address-layer-norm keeps unnormalised states from saturating the GRU)."""

    def __init__(self, obs_shape, action_size: int, units: int, cnn_depth: int, layer_norm: bool = False,
                 reward_input: bool = False):
        super().__init__()
        self.encoder = ConvEncoder(obs_shape, cnn_depth) if len(obs_shape) == 3 else mlp_encoder(obs_shape[0], units)
        self.reward_input = reward_input
        self.inp = nn.Sequential(nn.Linear(self.encoder.embed_size + action_size + int(reward_input), units),
                                 nn.LayerNorm(units) if layer_norm else nn.Identity(), nn.ELU())
        self.gru = nn.GRU(units, units, batch_first=True)

    def forward(self, obs, action, reward=None):  # (B, T, ...) -> (B, units)
        parts = [self.encoder(obs), action] + ([reward[..., None]] if self.reward_input else [])
        x = self.inp(torch.cat(parts, -1))  # (B, T, units)
        return self.gru(x)[0][:, -1]


# ----------------------------------------------------------------------------------------------------------
# 6. Dreamer: losses, imagination and the update
# ----------------------------------------------------------------------------------------------------------
def masked_mean(x, mask=None):
    """Mean of x (B, T) over the chunks whose mask (B,) is 1 (all chunks when mask is None)."""
    if mask is None:
        return x.mean()
    return (x * mask[:, None]).sum() / (mask.sum() * x.shape[1]).clamp(min=1.0)


def kl_with_free_nats(post: dict, prior: dict, free_nats: float, mask=None):
    """KL(post || prior) summed over the state, averaged over (B, T), then clipped below at free_nats (v1)."""
    kl = td.kl_divergence(td.Normal(post["mean"], post["std"]), td.Normal(prior["mean"], prior["std"])).sum(-1)
    kl = masked_mean(kl, mask)
    return torch.clamp(kl, min=free_nats), kl


def gaussian_loglik(mean, target, event_dims: int, std: float = 1.0):
    """log N(target; mean, std²) summed over the last event_dims dims: (B, T, ...) -> (B, T)."""
    loglik = -0.5 * ((target - mean) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)
    return loglik.flatten(2).sum(-1) if event_dims else loglik


def world_model_loss(wm: WorldModel, batch: dict, free_nats: float, kl_scale: float, reward_mask=None,
                     model_mask=None, obs_std: float = 1.0):
    """ELBO of a batch of chunks: (KL with free nats) - log p(o|s) - log p(r|s). Returns loss, posts, metrics.
    reward_mask (B,) drops the reward term of other tasks' chunks; model_mask (B,) drops chunks from the whole loss."""
    embed = wm.encoder(batch["obs"])  # (B, T, E)
    post, prior = wm.rssm.observe(embed, batch["action"])
    feat = wm.rssm.feat(post)  # (B, T, F)
    obs_dims = 3 if batch["obs"].dim() == 5 else 1
    obs_loglik = masked_mean(gaussian_loglik(wm.decoder(feat), batch["obs"], obs_dims, obs_std), model_mask)
    if model_mask is not None:
        reward_mask = model_mask if reward_mask is None else reward_mask * model_mask
    reward_loglik = masked_mean(gaussian_loglik(wm.reward(feat).squeeze(-1), batch["reward"], 0), reward_mask)
    kl_loss, kl_value = kl_with_free_nats(post, prior, free_nats, model_mask)
    loss = kl_scale * kl_loss - obs_loglik - reward_loglik
    metrics = {"losses/world_model": loss, "losses/kl": kl_value, "losses/obs_loglik": obs_loglik,
               "losses/reward_loglik": reward_loglik}
    return loss, post, metrics


def lambda_return(reward, value, pcont, bootstrap, lam: float):
    """λ-returns over time: R_t = r_t + γ_t [(1-λ) v_{t+1} + λ R_{t+1}], R_T = bootstrap: (H, N), (N,) -> (H, N)."""
    next_values = torch.cat([value[1:], bootstrap[None]], 0)
    inputs = reward + pcont * next_values * (1 - lam)
    returns, last = [], bootstrap
    # unbind, not [t]: the backward pass stacks the H gradients once, not H zero-filled copies
    for inputs_t, discount_t in zip(reversed(inputs.unbind(0)), reversed((pcont * lam).unbind(0))):
        last = inputs_t + discount_t * last
        returns.append(last)
    return torch.stack(returns[::-1], 0)


def imagine(wm: WorldModel, actor: Actor, start: dict, horizon: int):
    """Roll the prior forward from start states (N, ...) with actions from the actor: features (H, N, F) and the
    actions taken (H, N, A)."""
    state, feat, feats, actions = start, wm.rssm.feat(start), [], []
    for _ in range(horizon):
        actions.append(actor(feat.detach()).rsample())  # (N, A)
        state = wm.rssm.img_step(state, actions[-1])
        feat = wm.rssm.feat(state)  # (N, F): the step's feature, and the actor's input at the next step
        feats.append(feat)
    return torch.stack(feats, 0), torch.stack(actions, 0)


def imagined_returns(wm: WorldModel, value_net: nn.Module, feats, gamma: float, lam: float,
                     detach_reward: bool = False):
    """Rewards and values along features (H, N, F) -> λ-returns (H-1, N), their weights, values and rewards (H, N);
    detach_reward: the gradient reaches the features through the values only."""
    reward = wm.reward(feats).squeeze(-1)  # (H, N)
    reward = reward.detach() if detach_reward else reward
    value = value_net(feats).squeeze(-1)  # (H, N)
    pcont = torch.full_like(reward, gamma)
    returns = lambda_return(reward[:-1], value[:-1], pcont[:-1], value[-1], lam)  # (H-1, N)
    # weight of step t = γ^t: later imagined steps matter less
    weights = torch.cumprod(torch.cat([torch.ones_like(pcont[:1]), pcont[:-2]], 0), 0).detach()  # (H-1, N)
    return returns, weights, value, reward


class Freeze:
    """Turn off gradients of some modules inside a block: actor and value losses must not train the model."""

    def __init__(self, *modules):
        self._params = [p for m in modules for p in m.parameters() if p.requires_grad]  # a slow target stays off

    def __enter__(self):
        for p in self._params:
            p.requires_grad_(False)

    def __exit__(self, *exc):
        for p in self._params:
            p.requires_grad_(True)


def backward(optimizer, loss, params, retain_graph: bool = False):
    """Gradients of loss for `params` only (nothing else the loss depends on gets one), the old ones cleared."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward(inputs=list(params), retain_graph=retain_graph)


def clip_and_step(optimizer, params, clip: float):
    """Clip the gradients' global norm to `clip`, then step; returns the norm before clipping."""
    norm = nn.utils.clip_grad_norm_(list(params), clip)
    optimizer.step()
    return norm


def optimizer_step(optimizer, loss, params, clip: float, retain_graph: bool = False):
    params = list(params)
    backward(optimizer, loss, params, retain_graph)
    return clip_and_step(optimizer, params, clip)


class Agent(nn.Module):
    """The Dreamer agent: world model, actor, value and their optimisers."""

    def __init__(self, obs_shape, action_size, args: Args):
        super().__init__()
        self.wm = WorldModel(obs_shape, action_size, args)
        feat = self.wm.rssm.feat_size
        self.actor = Actor(feat, action_size, args.mlp_units, args.actor_init_std, args.actor_min_std,
                           args.actor_mean_scale, args.actor_dist)
        self.value = MLP(feat, args.mlp_units, 3, 1)
        set_speed_options(init_weights(self, args.init), args.precision, args.channels_last)
        # --slow-target: the λ-returns bootstrap from a copy that only sync_slow_target moves (DreamerV2; not in v1)
        self.value_target = copy.deepcopy(self.value).requires_grad_(False) if args.slow_target else None
        # capturable (--cuda-graph): Adam keeps its step counts on the device, so that a CUDA graph can hold its step
        adam = functools.partial(torch.optim.Adam, eps=args.adam_eps, capturable=args.cuda_graph)
        self.model_opt = adam(self.wm.parameters(), lr=args.model_lr)
        self.actor_opt = adam(self.actor.parameters(), lr=args.actor_lr)
        self.value_opt = adam(self.value.parameters(), lr=args.value_lr)

    def optimizers(self):
        return {"model": self.model_opt, "actor": self.actor_opt, "value": self.value_opt}


def imagine_behaviour(agent: Agent, post: dict, args: Args):
    """Imagine --horizon steps with the actor from every posterior of the batch: the λ-returns (H-1, N), their γ^t
    weights, the value (H, N) to fit, and the start states, actions and rewards the diagnostics read."""
    with Freeze(agent.wm):  # actor gradients flow through the model, but do not train it
        start = {k: v.detach().flatten(0, 1) for k, v in post.items()}  # (B*T, ...): every posterior
        feats, actions = imagine(agent.wm, agent.actor, start, args.horizon)  # (H, B*T, F), (H, B*T, A)
    # without a slow target one value pass serves both losses: the actor's backward reaches the actor only, the
    # value's the value only; with one, the λ-returns bootstrap from the target and the value is fitted to them
    bootstrap_net = agent.value if agent.value_target is None else agent.value_target
    returns, weights, value, reward = imagined_returns(agent.wm, bootstrap_net, feats, args.gamma, args.return_lambda)
    if agent.value_target is not None:
        value = agent.value(feats.detach()).squeeze(-1)  # (H, B*T)
    return returns, weights, value, (start, actions, reward)


def actor_loss(returns, weights):
    """Dreamer v1's actor loss: the γ^t-weighted λ-returns, maximised through the model's imagined dynamics."""
    return -(weights * returns).mean()


def value_loss(value, returns, weights):
    """Dreamer v1's value loss: −log N(R_t; v(s_t), 1) of the λ-returns, stopped, γ^t-weighted."""
    return -(weights * gaussian_loglik(value[:-1], returns.detach(), 0)).mean()  # (H-1, B*T) terms


def train_step(agent: Agent, batch: dict, args: Args, reward_mask=None, model_mask=None, step_model=True) -> dict:
    """One Dreamer update, in v1's shape: the world-model loss on the batch, then the actor and value losses in
    imagination from its posteriors, then the steps. As in v1, all three losses use the parameters before this
    update (imagination rolls the model as it was); --imagine-after-model-step steps the model first.
    step_model False leaves the model as it is (the actor and value still learn from the batch's posteriors)."""
    timings = {}
    with timed(timings, "world_model"):
        if args.reward_scale != 1.0:  # docs/deviations.md#metaworld-reward-scale: what the model, value and actor see
            batch = {**batch, "reward": batch["reward"] * args.reward_scale}
        model_loss, post, metrics = world_model_loss(agent.wm, batch, args.free_nats, args.kl_scale, reward_mask,
                                                     model_mask, args.obs_std)
        if step_model:  # the model's gradients now: its graph's activations are freed before imagination needs memory
            backward(agent.model_opt, model_loss, agent.wm.parameters())
        if step_model and args.imagine_after_model_step:  # docs/deviations.md#update-order
            metrics["losses/model_grad_norm"] = clip_and_step(agent.model_opt, agent.wm.parameters(), args.grad_clip)
    with timed(timings, "actor_critic"):
        returns, weights, value, (start, actions, reward) = imagine_behaviour(agent, post, args)
        metrics["losses/actor"], metrics["losses/value"] = actor_loss(returns, weights), value_loss(value, returns,
                                                                                                       weights)
        backward(agent.actor_opt, metrics["losses/actor"], agent.actor.parameters(), retain_graph=True)
        metrics["losses/actor_grad_norm"] = clip_and_step(agent.actor_opt, agent.actor.parameters(), args.grad_clip)
        backward(agent.value_opt, metrics["losses/value"], agent.value.parameters())
        metrics["losses/value_grad_norm"] = clip_and_step(agent.value_opt, agent.value.parameters(), args.grad_clip)
        metrics["charts/imagined_return"] = returns.mean()
        metrics.update(imagination_diagnostics(agent.actor, start, actions, reward, value))  # the stepped actor's std
    with timed(timings, "world_model"):
        if step_model and not args.imagine_after_model_step:  # last: imagination rolled the model as it was
            metrics["losses/model_grad_norm"] = clip_and_step(agent.model_opt, agent.wm.parameters(), args.grad_clip)
    return {"metrics": metrics, "timings": timings}


def imagination_diagnostics(actor: Actor, start: dict, actions, reward, value) -> dict:
    """What tells an overshooting critic from a reward head that extrapolates: the imagined rewards (H, N), the
    value (H, N) at the first and last imagined steps, the actor's std at the start states and how many of the
    imagined actions (H, N, A) sit at the tanh's edges. A round's log averages them over its updates."""
    with torch.no_grad():
        std = actor.std(RSSM.feat(start))  # (N, A): the Gaussian's before the tanh or the truncation
        return {"imagine/reward_mean": reward.mean(), "imagine/reward_max": reward.max(),
                "imagine/value_first": value[0].mean(), "imagine/value_last": value[-1].mean(),
                "imagine/actor_std": std.mean(), "imagine/saturated_actions": (actions.abs() > 0.99).float().mean()}


def sync_slow_target(agent: Agent, updates: int, every: int):
    """--slow-target: copy the value into its target every `every` updates (in place: a CUDA graph reads it)."""
    if agent.value_target is not None and updates % every == 0:
        agent.value_target.load_state_dict(agent.value.state_dict())


# ----------------------------------------------------------------------------------------------------------
# 7. Algorithm 2: the addressing step (Eqs. 1-3), then the batch mix
# ----------------------------------------------------------------------------------------------------------
# ALGO LOGIC: addressing — q(j | x, M) = softmax_j(f(x)ᵀ f(M_j)) and the three objectives
def address_logits(emb_x, emb_m, stop_grad_x: bool):
    """(n, U) current-task embeddings, (m, U) multitask embeddings -> (n, m) logits, a plain dot product."""
    return (emb_x.detach() if stop_grad_x else emb_x) @ emb_m.T


def gumbel_max(logits, generator: Optional[torch.Generator] = None):
    """j ~ softmax(logits) per row, as argmax(logits + Gumbel noise): (n, m) -> (n,), drawn on the device with no
    host sync (torch.multinomial also breaks CUDA-graph capture, pytorch#134442)."""
    uniform = torch.rand(logits.shape, generator=generator, device=logits.device)  # (n, m) in [0, 1)
    return (logits.detach().float() - torch.log(-torch.log(uniform))).argmax(-1)


def straight_through_sample(logits, generator: Optional[torch.Generator] = None):
    """One-hot samples j ~ softmax(logits) (n, m) whose gradient is that of the probabilities."""
    probs = logits.softmax(-1)
    index = gumbel_max(logits, generator)  # (n,)
    one_hot = F.one_hot(index, probs.shape[-1]).to(probs.dtype)
    return one_hot + (probs - probs.detach()), index  # forward: exactly one-hot (+ 0); backward: d/d probs


def select_chunks(one_hot, chunks):
    """Differentiable selection by index: (n, m) one-hots times a batch (m, T, ...) -> (n, T, ...)."""
    return torch.einsum("nm,m...->n...", one_hot, chunks)


@torch.no_grad()
def predicted_reward_sum(wm: WorldModel, batch: dict):
    """Σ_t of the reward head's mean on the posterior states of each chunk: (B,), the bandit's reward (Eqs. 2-3,
    whose r_t ~ p(r_t | s_t) is replaced by its mean, as in the authors' code: docs/deviations.md#reward-head-mean)."""
    post, _ = wm.rssm.observe(wm.encoder(batch["obs"]), batch["action"])
    return wm.reward(wm.rssm.feat(post)).squeeze(-1).sum(1)


def reinforce_loss(logits, index, advantage, standardize: bool):
    """Eqs. 2-3: −A · log q(j | x). Minimising it raises the probability of picks with A > 0."""
    advantage = advantage.detach()
    if standardize and advantage.numel() > 1:
        advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
    log_q = logits.log_softmax(-1).gather(-1, index[:, None]).squeeze(-1)  # (n,)
    return -(advantage * log_q).mean()


def vrama_loss(agent: Agent, one_hot, m_batch: dict, horizon: int, gamma: float, lam: float, starts: int = 0,
               select: str = "embeddings", reduction: str = "mean", objective: str = "imagine"):
    """Eq. 1: imagine from the posteriors of the selected chunks M_j; the loss is −V_λ along the imagined steps.

    The agent is frozen: the gradient reaches φ through the one-hots. reduction "mean" (Dreamer's actor loss: the
    γ^t-weighted mean) or "sum" (Eq. 1's Σ_t); select "embeddings" or "frames" (the same forward pass, another
    straight-through gradient); starts > 0 imagines from that many random posteriors (an unbiased estimate).
    objective "posterior" (the authors' code) imagines nothing: λ-returns along the picks' own L posterior states,
    their rewards detached, so the gradient reaches φ through the values."""
    action = select_chunks(one_hot, m_batch["action"])  # (n, L, A)
    with Freeze(agent):
        if select == "frames":
            embed = agent.wm.encoder(select_chunks(one_hot, m_batch["obs"]))  # (n, L, E)
        else:  # the encoder's backward pass into 2,500 frames is most of what "frames" costs more
            with torch.no_grad():
                embed_m = agent.wm.encoder(m_batch["obs"])  # (m, L, E)
            embed = select_chunks(one_hot, embed_m.float())  # (n, L, E)
        post, _ = agent.wm.rssm.observe(embed, action)
        if objective == "posterior":
            feats = agent.wm.rssm.feat(post).transpose(0, 1)  # (L, n, F): the chunks' own steps as the horizon
        else:
            start = {k: v.flatten(0, 1) for k, v in post.items()}  # (n*L, ...), not detached: φ learns through it
            if 0 < starts < len(start["deter"]):
                keep = torch.randperm(len(start["deter"]), device=one_hot.device)[:starts]  # (starts,)
                start = {k: v[keep] for k, v in start.items()}
            feats, _ = imagine(agent.wm, agent.actor, start, horizon)  # (H, N, F)
        returns, weights, _, _ = imagined_returns(agent.wm, agent.value, feats, gamma, lam,
                                               detach_reward=objective == "posterior")  # (H-1, N) each
        if reduction == "sum":
            return -returns.sum(0).mean()
        return -(weights * returns).mean()


class Addressing:
    """The addressing model f_φ, its optimiser, and D: the embeddings of the candidate chunks of M (Algorithm 2)."""

    def __init__(self, obs_shape, action_size: int, args: Args, device):
        self.net = AddressNet(obs_shape, action_size, args.address_units, args.address_cnn_depth,
                              args.address_layer_norm, args.address_reward_input)
        self.net = set_speed_options(init_weights(self.net, args.init), args.precision, args.channels_last).to(device)
        # decoupled weight decay: torch scales it by lr, so wd / lr gives the authors' θ ← (1 − wd)·θ per step
        self.opt = torch.optim.Adam(self.net.parameters(), lr=args.address_lr,
                                    eps=args.address_adam_eps or args.adam_eps, decoupled_weight_decay=True,
                                    weight_decay=args.address_weight_decay / args.address_lr,
                                    capturable=args.cuda_graph)
        # f(x)'s network: f_φ itself, or a frozen copy of its initial weights. Under the stop-gradient a step of φ
        # is meant to move f(M_j) only (Section 4.3), yet the shared weights move f(x) with it
        # (docs/deviations.md#frozen-x-net).
        # .to() packs the copy's GRU weights into the one buffer cuDNN wants (a deepcopy leaves them apart)
        self.x_net = self.net if args.address_x_net == "shared" else \
            copy.deepcopy(self.net).requires_grad_(False).to(device)
        self.method, self.device, self.logit_scale = args.method, device, args.address_logit_scale
        self.stop_grad_x = args.method in ("rrama", "rbrama") if args.address_stop_grad_x is None \
            else args.address_stop_grad_x
        self.generator = torch.Generator(device).manual_seed(args.seed)  # the picks' Gumbel noise
        self.candidates = None  # (episode ids, starts) of the chunks embedded in D (or of the last fresh pool)
        self.candidate_rewards = None  # (N_c,) their stored reward sums, for the logs and the picture
        self.candidate_embeddings = None  # D: (N_c, U), D_j = f_φ(M_j)
        self.pool = None  # a Pool of the candidates' chunks on the device, for the updates to pick from

    def embed(self, batch: dict):
        """f_φ(M_j): (B, U)."""
        return self.net(batch["obs"], batch["action"], batch["reward"])

    def embed_x(self, batch: dict):
        """f(x_i), by x_net: (B, U)."""
        return self.x_net(batch["obs"], batch["action"], batch["reward"])

    def train(self, agent: Agent, x: dict, m_batch: dict, args: Args) -> dict:
        """(a) of Algorithm 2: score m multitask chunks against each x_i, sample j, step φ on Eq. 1, 2 or 3."""
        logits = address_logits(self.embed_x(x), self.embed(m_batch), self.stop_grad_x)  # (n, m)
        metrics = {}
        if self.method == "vrama":
            one_hot, index = straight_through_sample(logits, self.generator)
            loss = vrama_loss(agent, one_hot, m_batch, args.horizon, args.gamma, args.return_lambda,
                              args.address_imagine_starts, args.vrama_select, args.vrama_reduction,
                              args.vrama_objective)
        else:
            index = gumbel_max(logits, self.generator)  # (n,)
            # RbRAMa filters x in the same pass as M_j (one loop of RSSM steps, not two): the sums of m + n chunks
            scored = m_batch if self.method == "rrama" else \
                {k: torch.cat([m_batch[k], x[k]]) for k in ("obs", "action")}
            reward_sums = predicted_reward_sum(agent.wm, scored)  # (m,) or (m + n,)
            bandit_reward = reward_sums[:len(m_batch["action"])]  # (m,)
            # what the objective gains: the expected bandit reward of a pick under q against a uniform pick
            metrics["addressing/bandit_reward_q"] = (logits.detach().softmax(-1) @ bandit_reward).mean()
            metrics["addressing/bandit_reward_uniform"] = bandit_reward.mean()
            advantage = bandit_reward[index]  # Eq. 2 (RRAMa)
            if self.method == "rbrama":  # Eq. 3 (RbRAMa): the predicted reward sum of x_i as the baseline
                advantage = advantage - reward_sums[len(bandit_reward):]
            loss = reinforce_loss(logits, index, advantage, args.address_standardize)
        grad_norm = optimizer_step(self.opt, loss, self.net.parameters(), args.address_grad_clip)
        log_q = logits.detach().log_softmax(-1)
        entropy = -(log_q.exp() * log_q).sum(-1).mean()
        return {"addressing/loss": loss.detach(), "addressing/entropy": entropy,
                "addressing/entropy_uniform": torch.full_like(entropy, np.log(logits.shape[-1])),
                "addressing/grad_norm": grad_norm, **metrics}

    def refresh_if_due(self, args: Args, multitask: Replay, rng, updates_done: int, task_name: str):
        """Algorithm 2's "if c = 1": D recomputed at a task's first update and then every --address-refresh updates,
        and the pool of its chunks rebuilt (padded for --cuda-graph). Returns the seconds it took, or None."""
        if self.candidate_embeddings is not None and updates_done % args.address_refresh:
            return None
        t0 = time.perf_counter()
        chunks = self.refresh(multitask, args.seq_len, args.address_candidates, rng)
        # the candidates' mask values change only here (a task's first update refreshes: 0 updates done, or no D)
        reward_mask = borrowed_reward_mask(args, multitask, self.candidates[0], task_name, self.device)
        self.pool = Pool(self.candidates, chunks, reward_mask, self.candidate_embeddings)
        if args.cuda_graph:
            self.pool = padded_pool(self.pool, args.address_candidates)
        return time.perf_counter() - t0

    @torch.no_grad()
    def refresh(self, multitask: Replay, seq_len: int, cap: int, rng, chunk_batch: int = 64):
        """Recompute D_j = f_φ(M_j) for a fresh set of candidate chunks; returns their chunks on the device (as
        stored: images uint8), for the updates to gather their picks from without the host."""
        self.candidates = multitask.grid_ids(seq_len, cap, rng)
        self.candidate_rewards = multitask.chunk_rewards(*self.candidates, seq_len)
        parts, embeddings = [], []
        for i in range(0, len(self.candidates[0]), chunk_batch):
            ids = (self.candidates[0][i:i + chunk_batch], self.candidates[1][i:i + chunk_batch])
            parts.append(to_device(multitask.gather(*ids, seq_len), self.device))
            embeddings.append(self.embed(preprocess(parts[-1])))
        self.candidate_embeddings = torch.cat(embeddings, 0)  # (N_c, U)
        return {k: torch.cat([part[k] for part in parts], 0) for k in parts[0]}  # (N_c, L, ...)

    @torch.no_grad()
    def logits(self, x: dict, embeddings=None):
        """s · f(x_i)ᵀ D_j, the logits of q̂ (s: --address-logit-scale), over D or other embeddings: (n, N_c)."""
        return self.embed_x(x) @ (self.candidate_embeddings if embeddings is None else embeddings).T * self.logit_scale

    def probs(self, x: dict):
        """q̂(j | x_i) ∝ exp(s · f(x_i)ᵀ D_j) over the candidates: (n, N_c)."""
        return self.logits(x).softmax(-1)

    @torch.no_grad()
    def pick(self, x: dict, pool: "Pool"):
        """j ~ q̂(j | x_i) over a pool's chunks (embedded here when the pool holds no embeddings), drawn on the device
        by Gumbel-max: (n,). Rows of the pool that are padding (pool.valid False) are never picked."""
        embeddings = self.embed(preprocess(pool.chunks)) if pool.embeddings is None else pool.embeddings
        logits = self.logits(x, embeddings)  # (n, P)
        if pool.valid is not None:
            logits = logits.masked_fill(~pool.valid, float("-inf"))
        return gumbel_max(logits, self.generator)


@dataclass
class Pool:
    """Chunks of M kept on the device for the borrowed rows of a mixed batch to be picked from."""
    ids: tuple  # (episode ids, starts) of the chunks in M, each (P,)
    chunks: dict  # as stored (images uint8): obs (P, L, ...), action (P, L, A), reward and terminal (P, L)
    reward_mask: torch.Tensor  # (P,) 1 where a borrowed chunk keeps its reward loss
    embeddings: Optional[torch.Tensor] = None  # (P, U): D over the candidates (memory mode); None: embedded at the pick
    valid: Optional[torch.Tensor] = None  # (P,) False on the rows --cuda-graph pads the pool with


@dataclass
class UpdatePlan:
    """What the host decides before one update of Algorithm 2, handed to `update` as tensors on the device, so that
    the update runs without waiting for the host. Empty: the plain Dreamer update (no M, or no M yet)."""
    mixed: bool = False  # α ~ Bernoulli(p): the batch's last (1 − β)·n rows are replaced by chunks of M
    m_batch: Optional[dict] = None  # the m chunks M_j ~ M that train f_φ (the addressed methods)
    pool: Optional[Pool] = None  # what the borrowed rows are picked from (None: a batch without borrowed rows)
    refresh_seconds: Optional[float] = None  # set when this update recomputed D


def plan_update(args: Args, multitask: Replay, addressing: Optional[Addressing], rng, device, task_name: str,
                updates_done: int) -> UpdatePlan:
    """The host's part of one update (Algorithm 2): α, D's refresh when due, the m chunks of M that train f_φ, and
    the pool the borrowed rows come from, with a reward-mask value per pool chunk."""
    seq_len, ends, borrow = args.seq_len, args.address_oversample_ends, args.batch_size - keep_rows(args)
    if args.method == "dreamer" or multitask.num_chunks(seq_len) == 0:
        return UpdatePlan()
    plan = UpdatePlan(mixed=borrow > 0 and bool(rng.random() < args.address_prob))
    memory_mode = addressing is not None and args.address_candidates_mode == "memory"
    if addressing is not None:
        if memory_mode:
            plan.refresh_seconds = addressing.refresh_if_due(args, multitask, rng, updates_done, task_name)
        plan.m_batch = to_torch(multitask.sample(args.address_batch, seq_len, rng, ends), device)  # M_j ~ M
    if borrow == 0:
        return plan
    if memory_mode:
        plan.pool = addressing.pool
    else:  # `uniform`: the borrowed chunks themselves; `fresh` (the authors' code): m new chunks for q̂ to pick from
        ids = multitask.sample_ids(borrow if addressing is None else args.address_batch, seq_len, rng, ends)
        plan.pool = Pool(ids, to_device(multitask.gather(*ids, seq_len), device),
                         borrowed_reward_mask(args, multitask, ids[0], task_name, device))
        if addressing is not None:
            addressing.candidates, addressing.candidate_rewards = ids, multitask.chunk_rewards(*ids, seq_len)
    return plan


def borrowed_reward_mask(args: Args, multitask: Replay, episode_ids, task_name: str, device):
    """(P,) per chunk of a pool: 1 if it keeps its reward loss when borrowed, i.e. it is of this task (the paper
    masks other tasks' chunks; --reward-mask-borrowed all: none keeps it)."""
    same_task = [args.reward_mask_borrowed == "other-tasks" and multitask.tasks[e] == task_name for e in episode_ids]
    return torch.tensor(same_task, dtype=torch.float32).to(device, non_blocking=True)


def mixed_skips_model_step(args: Args) -> bool:
    """The authors' `agent_only` (--no-wm-on-addressed --addressed-wm-rule batch): a mixed batch leaves the model as
    it is, so a mixed and an unmixed update differ in more than their rows."""
    return not args.wm_on_addressed and args.addressed_wm_rule == "batch"


def keep_rows(args: Args) -> int:
    """β·n: the rows of a mixed batch that stay current-task chunks."""
    return int(round(args.current_fraction * args.batch_size))


def mix_batch(x: dict, pool: Pool, picks, keep: int, mixed: bool, mask_borrowed_model_rows: bool):
    """Algorithm 2's "if α = 1: B ← {x_i}_{i=1}^{βn} ∪ {M_j_i}_{i=1}^{(1−β)n}": x's first β·n rows stay and
    its other rows are replaced by the pool's chunks `picks`. Returns the batch, the reward mask (n,) (1: the row
    keeps its reward loss) and, with mask_borrowed_model_rows, the model mask (n,) (0: the row is left out of the
    model's loss). Unmixed (α = 0): x itself, every row kept, with masks of the same shapes."""
    ones = torch.ones(len(x["reward"]), device=x["reward"].device)  # (n,)
    if not mixed:
        return x, ones, ones if mask_borrowed_model_rows else None
    borrowed = preprocess({k: v[picks] for k, v in pool.chunks.items()})  # ((1 − β)·n, L, ...)
    batch = {k: torch.cat([x[k][:keep], borrowed[k]], 0) for k in x}
    reward_mask = torch.cat([ones[:keep], pool.reward_mask[picks]])
    model_mask = torch.cat([ones[:keep], torch.zeros_like(ones[keep:])]) if mask_borrowed_model_rows else None
    return batch, reward_mask, model_mask


def update(agent: Agent, addressing: Optional[Addressing], x: dict, plan: UpdatePlan, args: Args) -> dict:
    """One update of Algorithm 2, given n current-task chunks x_i ~ M_τ and the host's plan: (a) the addressing
    step; (b) the agent's step on the batch mix_batch makes of x and the pool's chunks picked by q̂ (by the host for
    `uniform`). Picks are drawn mixed or not (the random stream does not depend on α); no host sync inside."""
    timings, metrics, picks = {"batch_sampling": 0.0}, {}, None
    if plan.m_batch is not None:  # (a) train f_φ with the agent fixed
        with timed(timings, "addressing"):
            metrics.update(addressing.train(agent, x, plan.m_batch, args))
        if plan.refresh_seconds is not None:
            metrics["addressing/refresh_seconds"] = torch.tensor(plan.refresh_seconds)
            timings["addressing"] += plan.refresh_seconds
    batch, reward_mask, model_mask = x, None, None
    if plan.pool is not None:  # (b) mix M into the agent's batch
        with timed(timings, "batch_sampling"):
            keep = keep_rows(args)
            borrow = len(x["reward"]) - keep
            if addressing is None:  # `uniform`: the host drew the pool's chunks uniformly from M
                picks = torch.arange(borrow, device=x["reward"].device)
            else:  # j ~ q̂(j | x_i) for the first rows of x
                picks = addressing.pick({k: v[:borrow] for k, v in x.items()}, plan.pool)
            batch, reward_mask, model_mask = mix_batch(x, plan.pool, picks, keep, plan.mixed, not args.wm_on_addressed
                                                       and args.addressed_wm_rule == "rows")
    step_model = not (mixed_skips_model_step(args) and plan.mixed)
    out = train_step(agent, batch, args, reward_mask, model_mask, step_model)
    out["metrics"].update(metrics)
    out["timings"].update(timings)
    out["picks"] = (plan.pool.ids, picks) if plan.mixed else None  # the pool's ids and the picks' indices into it
    return out


def picks_metrics(picks: list, multitask: Replay, addressing: Optional[Addressing], updates: int,
                  seq_len: int) -> dict:
    """What the mixed batches borrowed: per-task fractions (and per collecting policy, where M mixes a scripted
    expert's, random or a learning agent's episodes) and stored returns of picks vs candidates."""
    picked = [e for p in picks for e in p[0]]
    metrics = {"addressing/mixed_batches": len(picks) / updates}
    if not picked:
        return metrics
    tasks = [multitask.tasks[e] for e in picked]
    for task in sorted(set(multitask.tasks)):
        metrics[f"addressing/pick_fraction/{task}"] = tasks.count(task) / len(tasks)
    policies = [multitask.policies[e] for e in picked]
    for policy in sorted(set(multitask.policies)) if len(set(multitask.policies)) > 1 else []:  # a scripted M
        metrics[f"addressing/pick_source/{policy}"] = policies.count(policy) / len(policies)
    metrics["addressing/picked_return"] = float(np.mean([multitask.returns[e] for e in picked]))
    pool = addressing.candidates[0] if addressing is not None and addressing.candidates is not None \
        else np.arange(len(multitask))
    metrics["addressing/candidate_return"] = float(np.mean([multitask.returns[e] for e in pool]))
    # the same at the level of chunks: the stored reward sum of each picked chunk against the candidates'
    metrics["addressing/picked_chunk_reward"] = float(np.mean([multitask.chunk_rewards(*p, seq_len).mean()
                                                               for p in picks if len(p[0])]))
    if addressing is not None and addressing.candidates is not None:
        metrics["addressing/candidate_chunk_reward"] = float(addressing.candidate_rewards.mean())
    return metrics


# ----------------------------------------------------------------------------------------------------------
# 8. Acting and logging
# ----------------------------------------------------------------------------------------------------------
class Policy:
    """Acts online in N envs at once: keeps the RSSM posteriors of the current episodes and picks actions from them."""

    def __init__(self, agent: Agent, device, eval_action: str = "sample-mode"):
        self.agent, self.device, self.eval_action = agent, device, eval_action

    def reset(self, num_envs: int = 1):
        self.state, self.action = None, torch.zeros(num_envs, self.agent.actor.action_size, device=self.device)

    @torch.no_grad()
    def act(self, obs: np.ndarray, explore_noise: Optional[float], rng: np.random.Generator) -> np.ndarray:
        """obs (N, ...) -> actions (N, A). explore_noise None = evaluation (the mode); else a sample plus Gaussian
        noise of that std."""
        wm = self.agent.wm
        embed = wm.encoder(preprocess(to_device({"obs": obs[:, None]}, self.device))["obs"])[:, 0]  # (N, E)
        state = self.state if self.state is not None else wm.rssm.initial(len(obs), self.device)
        self.state = wm.rssm.obs_step(wm.rssm.deter_step(state, self.action), wm.rssm.obs_embed(embed))
        feat = wm.rssm.feat(self.state)
        action = self.agent.actor.mode(feat, self.eval_action) if explore_noise is None else \
            self.agent.actor(feat).sample()
        action = action.cpu().numpy()  # (N, A)
        if explore_noise:
            action = np.clip(action + rng.normal(0.0, explore_noise, action.shape), -1.0, 1.0)
        self.action = torch.as_tensor(action, dtype=torch.float32, device=self.device)
        return action.astype(np.float32)


def worker_env(args: Args, env_id: str, seed: int) -> gymnasium.Env:
    """make_env, in a collecting subprocess too, where Ctrl-C and SIGTERM are the main process's to handle."""
    if multiprocessing.parent_process() is not None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
    return make_env(args, env_id, seed)


def make_envs(args: Args, env_id: str, seed: int, num_envs: int) -> gymnasium.vector.VectorEnv:
    """num_envs envs (seeds seed, seed + 1, ...) as one gymnasium vector env: in this process for one, in spawned
    subprocesses (no fork of a process using torch) for more. An env whose episode ended before the others' is
    reset on its next step (gymnasium's next-step autoreset); run_episodes ignores it until all have ended."""
    makers = [functools.partial(worker_env, args, env_id, seed + i) for i in range(num_envs)]
    if num_envs == 1:
        return gymnasium.vector.SyncVectorEnv(makers)
    return gymnasium.vector.AsyncVectorEnv(makers, context="spawn")


def run_episodes(envs, act, seeds: list, task: str, record: bool = False):
    """One episode in each env of a vector env; act(obs (N, ...)) -> actions (N, A). Returns the episode dicts
    and, with record, the rendered frames of the first env's episode."""
    obs, reset_info = envs.reset(seed=list(seeds))
    n = len(seeds)
    steps = [{"obs": [obs[i]], "action": [np.zeros(envs.single_action_space.shape, np.float32)], "reward": [0.0],
              "terminal": [False]} for i in range(n)]
    frames = [envs.call("render")[0]] if record else []
    done, success = np.zeros(n, bool), [None] * n  # success stays None for envs that do not report it
    while not done.all():
        action = act(obs)  # (N, A)
        obs, reward, terminated, truncated, info = envs.step(action)
        for i in np.flatnonzero(~done):
            for key, value in zip(("obs", "action", "reward", "terminal"), (obs, action, reward, terminated)):
                steps[i][key].append(value[i])
            if "success" in info and info["_success"][i]:
                success[i] = bool(success[i]) or bool(info["success"][i])
        if record:
            frames.append(envs.call("render")[0])
        done |= terminated | truncated
        check_stop()  # a stopped run drops the episodes in flight
    episodes = []  # the dicts that are stored (section 4)
    for i in range(n):
        episode = {k: np.asarray(v, dtype=np.float32 if k in ("action", "reward") else None)
                   for k, v in steps[i].items()}
        episode.update({k: np.asarray(reset_info[k][i]) for k in EPISODE_EXTRAS})
        episode["task"] = np.asarray(task)
        episode["return"] = np.asarray(episode["reward"].sum(), np.float32)
        if success[i] is not None:  # envs that report success: success at any step counts
            episode["success"] = np.asarray(success[i])
        episodes.append(episode)
    return episodes, frames


def episode_metrics(prefix: str, episodes: list) -> dict:
    """Mean return (and success rate, where the env reports success) of finished episodes."""
    metrics = {f"{prefix}/episodic_return": float(np.mean([float(ep["return"]) for ep in episodes]))}
    if "success" in episodes[0]:
        metrics[f"{prefix}/success_rate"] = float(np.mean([bool(ep["success"]) for ep in episodes]))
    return metrics


class Logger:
    """TensorBoard + metrics.jsonl (+ W&B): one JSON line per log call, keys grouped charts/, losses/, eval/."""

    def __init__(self, run_path: str, args: Args):
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(run_path)
        self.jsonl = os.path.join(run_path, "metrics.jsonl")
        self.wandb = None
        if args.track:  # check_args made sure wandb imports
            import wandb

            self.wandb = wandb.init(project=args.wandb_project, config=vars(args), name=os.path.basename(run_path),
                                    dir=run_path, resume="allow")

    def log(self, step: int, metrics: dict):
        metrics = {k: float(v) for k, v in metrics.items()}
        for key, value in metrics.items():
            self.writer.add_scalar(key, value, step)
        with disk_write(self.jsonl, "a") as f:  # a line whole or not at all
            f.write(json.dumps({"step": step, **metrics}) + "\n")
        if self.wandb:
            self.wandb.log(metrics, step=step)

    def close(self):
        self.writer.close()
        if self.wandb:
            self.wandb.finish()


def write_gif(path: str, frames, fps: int = 25):
    import imageio.v2 as imageio

    imageio.mimsave(path, [np.asarray(f, np.uint8) for f in frames], duration=1000 / fps, loop=0)


@torch.no_grad()
def open_loop_frames(wm: WorldModel, batch: dict, context: int = 5):
    """Truth | model | error rows for up to 4 chunks: observe `context` frames, then imagine with true actions."""
    batch = {k: v[:4] for k, v in batch.items()}
    post, _ = wm.rssm.observe(wm.encoder(batch["obs"][:, :context]), batch["action"][:, :context])
    start = {k: v[:, -1] for k, v in post.items()}
    prior = wm.rssm.imagine_actions(start, batch["action"][:, context:])
    model = torch.cat([wm.decoder(wm.rssm.feat(post)), wm.decoder(wm.rssm.feat(prior))], 1)  # (4, T, 3, H, W)
    truth = batch["obs"]
    grid = torch.cat([truth, model, (model - truth + 1) / 2 - 0.5], 3)  # rows stacked along height
    grid = torch.cat(list(grid), 3)  # chunks side by side along width -> (T, 3, 3H, 4W)
    return ((grid + 0.5).clamp(0, 1) * 255).to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()


def round_line(env_steps: int, total_steps: int, done: int, todo: int, seconds: float) -> str:
    """The plain-log line inside a round of updates: how far the round is, its speed and the time it has left."""
    from tqdm import tqdm

    rate = done / max(seconds, 1e-9)  # done >= 1 here
    return (f"step {env_steps}/{total_steps} | update {done}/{todo} of this round | {rate:.3g} updates/s | "
            f"round ETA {tqdm.format_interval((todo - done) / rate)}")


# ----------------------------------------------------------------------------------------------------------
# 9. The training loop (Algorithms 1 and 2)
# ----------------------------------------------------------------------------------------------------------
@dataclass
class Task:
    """One task of Algorithm 1 as the steps of Algorithm 2 share it: what train_task gives it, what open_task builds,
    and the counters its checkpoint saves."""
    args: Args
    env_id: str
    name: str  # the task's short name, stored with its episodes
    seed: int
    path: str  # its folder: the run folder, or <run>/<k>_<task> in a --task-sequence
    device: torch.device
    replay: Replay  # M_τ
    multitask: Replay  # M
    addressing: Optional[Addressing]  # f_φ (None for dreamer and uniform)
    rng: np.random.Generator
    address_path: str  # address.pt, the run's f_φ
    env_steps: int
    envs: Any = None  # the collecting envs and the evaluation env (open_task)
    eval_env: Any = None
    agent: Optional[Agent] = None
    policy: Optional[Policy] = None
    step: Any = None  # `update`, or its CUDA graphs (GraphedUpdate): (x, plan) -> the update's output
    batch_rng: Any = None  # the random stream of the x_i ~ M_τ (sample_batches)
    logger: Any = None
    progress: Any = None  # the bar over env steps (disabled: plain lines)
    # updates done, the next evaluation's step, the round in progress: saved in the checkpoint
    counters: dict = dataclasses.field(default_factory=dict)
    start: tuple = ()  # (time, env steps) when this process began the task: the speed counts from there
    last_line: float = 0.0  # when the last plain line was printed
    noticed: bool = False  # the first update's CPU notice is done


def train_task(args: Args, env_id: str, seed: int, task_path: str, device, multitask: Replay,
               addressing: Optional[Addressing], rng, address_path: str, checkpoint: Optional[dict]):
    """Algorithm 2 on one task: a fresh agent, the shared M and f_φ; resumes from task_path when it has data (and
    from `checkpoint`, read by main). Each collected episode: (a) a round of C updates, (b) evaluation when due,
    (c) collection."""
    os.makedirs(os.path.join(task_path, "episodes"), exist_ok=True)
    replay = Replay()  # M_τ: the episodes already on disk count (a resumed run recovers its step count here)
    for path in list_episode_files(os.path.join(task_path, "episodes")):
        add_episode(args, replay, multitask, load_episode(path))
    env_steps = sum(len(ep["reward"]) - 1 for ep in replay.episodes) * args.action_repeat
    last_eval_due = args.eval_episodes and checkpoint is not None and checkpoint["state"]["next_eval"] <= env_steps
    if env_steps >= args.total_steps and not last_eval_due:  # (a run killed before its last evaluation does it)
        print(f"task {env_id}: done ({len(replay)} episodes, {env_steps} steps)", flush=True)
    else:
        task = open_task(Task(args=args, env_id=env_id, name=make_env_spec(env_id)["name"], seed=seed,
                              path=task_path, device=device, replay=replay, multitask=multitask,
                              addressing=addressing, rng=rng, address_path=address_path, env_steps=env_steps),
                         checkpoint)
        try:
            while task.env_steps < args.total_steps:
                if len(replay) >= args.prefill_episodes and replay.num_chunks(args.seq_len) > 0:
                    end_round(task, *train_round(task))  # (a) C updates on chunks of M_τ, mixed with M
                evaluate_if_due(task)  # (b) without exploration noise, every --eval-every env steps
                collect(task)  # (c) an episode per env, each stored atomically
            evaluate_if_due(task)  # the last step's evaluation
        finally:
            for resource in (task.progress, task.logger, task.envs, task.eval_env):
                resource.close()
    if args.method != "dreamer" and not args.own_episodes_in_m:  # the task is over: its episodes join M now
        for episode in replay.episodes:
            multitask.add(episode)


def add_episode(args: Args, replay: Replay, multitask: Replay, episode: dict):
    """An episode joins M_τ, and M (shared arrays, no copy) unless --no-own-episodes-in-m (the authors' code: the
    episodes of a --task-sequence task join M for the tasks after it, when it is over)."""
    replay.add(episode)
    if args.method != "dreamer" and args.own_episodes_in_m:
        multitask.add(episode)


def open_task(task: Task, checkpoint: Optional[dict]) -> Task:
    """The envs, a fresh agent (or the checkpoint's), the batches' random stream, the logger and the progress bar."""
    args, replay = task.args, task.replay
    task.envs, task.eval_env = make_envs(args, task.env_id, task.seed, args.num_envs), make_envs(
        args, task.env_id, task.seed + 10_000, 1)
    task.agent = Agent(task.envs.single_observation_space.shape, task.envs.single_action_space.shape[0],
                       args).to(task.device)
    task.policy = Policy(task.agent, task.device, args.eval_action)
    task.step = first_update_fits(GraphedUpdate(task.agent, task.addressing, args) if args.cuda_graph else
                                  functools.partial(update, task.agent, task.addressing, args=args), args, task.device)
    # updates: done so far; round_at, round_left: the episode count of the current round of C updates and the
    # updates it still has to do (a run stopped mid-round finishes it; one killed after a round does not redo it)
    task.counters = {"updates": 0, "next_eval": args.eval_every}
    if checkpoint is not None:
        task.counters = load_checkpoint(os.path.join(task.path, "checkpoint.pt"), checkpoint, task.agent)
        task.rng = np.random.default_rng([args.seed, len(replay)])  # fresh stream: resume is not bit-identical
    task.batch_rng = np.random.default_rng([task.seed, len(replay), 1])
    task.logger = Logger(task.path, args)
    for folder in (["videos"] if args.capture_video else []) + (["addressing"] if task.addressing else []):
        os.makedirs(os.path.join(task.path, folder), exist_ok=True)
    print(f"run: {task.path} | {task.env_id} ({args.obs_type}) | method {args.method} | device {task.device} | "
          f"{sum(p.numel() for p in task.agent.parameters()) / 1e6:.2f}M parameters | {len(replay)} episodes on disk "
          f"({task.env_steps} steps) | multitask buffer {len(task.multitask)} episodes", flush=True)
    from tqdm import tqdm

    # a bar over env steps and, inside each round of C updates, one over its updates (updates/s, the round's ETA);
    # without a terminal on stderr (nohup, CI, sweeps) or with --plain-log: plain lines, at least one per
    # --log-interval-seconds inside a round and one per collected episode(s)
    task.progress = tqdm(total=args.total_steps, initial=min(task.env_steps, args.total_steps), unit="step",
                         dynamic_ncols=True, disable=True if args.plain_log else None)
    task.start, task.last_line, task.noticed = (time.time(), task.env_steps), time.time(), False
    return task


def train_round(task: Task):
    """(a) of Algorithm 2 for the latest episode: C updates (per env), each one the host's plan, then the addressing
    step, the batch mix and the agent's step on the device. Its metrics stay on the device until the round ends."""
    from tqdm import tqdm

    args, counters = task.args, task.counters
    if counters.get("round_at") != len(task.replay):
        counters["round_at"], counters["round_left"] = len(task.replay), args.updates_per_episode * args.num_envs
    update_metrics, timings, picks, done = [], {}, [], 0
    round_start, todo = time.time(), counters["round_left"]
    round_bar = tqdm(total=todo, unit="update", desc="updates", leave=False, dynamic_ncols=True,
                     disable=task.progress.disable)
    for x, waited in sample_batches(task.replay, args.batch_size, args.seq_len, task.batch_rng, task.device, todo):
        if STOP["signal"]:  # finish the current update, not the round
            break
        plan = plan_update(args, task.multitask, task.addressing, task.rng, task.device, task.name, counters["updates"])
        out = task.step(x, plan)
        out["timings"]["batch_sampling"] += waited
        counters["updates"], done = counters["updates"] + 1, done + 1
        sync_slow_target(task.agent, counters["updates"], args.slow_target_every)
        if not task.noticed:  # the first update of this process: on a CPU, what the run would cost
            task.noticed, notice = True, first_update_notice(args, task.device, task.env_steps,
                                                             time.time() - round_start)
            if notice:
                task.progress.write(notice)
        update_metrics.append({k: v.detach() for k, v in out["metrics"].items()})
        for k, v in out["timings"].items():
            timings[k] = timings.get(k, 0.0) + v
        if out["picks"] is not None:  # a mixed batch: what it borrowed
            picks.append(out["picks"])
        round_bar.update()  # no host sync: tqdm only reads the clock
        if task.progress.disable and time.time() - task.last_line >= args.log_interval_seconds:
            print(round_line(task.env_steps, args.total_steps, done, todo, time.time() - round_start), flush=True)
            task.last_line = time.time()
    round_bar.close()
    return update_metrics, timings, picks, done


def round_metrics(task: Task, update_metrics: list, timings: dict, picks: list, done: int) -> dict:
    """The round's means over the updates that logged each key, read from the device once, and checked."""
    sums, counts = {}, {}
    for row in update_metrics:
        for k, v in row.items():
            sums[k], counts[k] = sums.get(k, 0.0) + v, counts.get(k, 0) + 1
    metrics = {k: v.item() / counts[k] for k, v in sums.items()}
    check_finite(task, update_metrics, metrics, done)
    if "addressing/refresh_seconds" in sums:  # a sum of refreshes, not a per-update mean
        metrics["addressing/refresh_seconds"] = sums["addressing/refresh_seconds"].item()
    metrics.update({f"time/{k}_per_update": v / max(done, 1) for k, v in timings.items()})
    if task.args.method != "dreamer" and done:
        if picks:  # the picks' indices into their pools, read once: (episode ids, starts) of each mixed batch
            chosen = torch.stack([j for _, j in picks]).cpu().numpy()  # (mixed updates, borrow)
            picks = [(ids[0][j], ids[1][j]) for (ids, _), j in zip(picks, chosen)]
        metrics.update(picks_metrics(picks, task.multitask, task.addressing, done, task.args.seq_len))
    metrics["charts/updates"] = task.counters["updates"]
    return metrics


def end_round(task: Task, update_metrics: list, timings: dict, picks: list, done: int):
    """After a round: its metrics, then (when it did any update) the checkpoints and the log line, then the stop
    check, and the round's pictures: open-loop predictions (--capture-video) and what q̂ picks."""
    args = task.args
    metrics = round_metrics(task, update_metrics, timings, picks, done)
    task.counters["round_left"] -= done
    if done:  # the checkpoints first: a kill between the two loses this row rather than repeating it
        save_checkpoints(task)
        task.logger.log(task.env_steps, metrics)
    check_stop()
    if args.capture_video and args.obs_type == "pixels":  # open-loop predictions of images only
        batch = to_torch(task.replay.sample(4, args.seq_len, task.rng), task.device)
        write_gif(os.path.join(task.path, "videos", f"openloop_{task.env_steps:08d}.gif"),
                  open_loop_frames(task.agent.wm, batch))
    draw_addressing(task)


def draw_addressing(task: Task):
    """Every --address-plot-every episodes: q̂ over D for 16 current chunks (report.addressing_figure), as a PNG
    and in TensorBoard."""
    addressing, multitask = task.addressing, task.multitask
    if addressing is None or addressing.candidate_embeddings is None or len(task.replay) % task.args.address_plot_every:
        return
    from report import addressing_figure  # the plotting lives in report.py

    x = to_torch(task.replay.sample(16, task.args.seq_len, task.rng), task.device)
    candidates = addressing.candidates[0]
    fig = addressing_figure(addressing.probs(x).cpu().numpy(), [multitask.tasks[e] for e in candidates],
                            np.array([multitask.returns[e] for e in candidates]),
                            f"{task.args.method} on {task.name}, step {task.env_steps}", addressing.candidate_rewards)
    fig.savefig(os.path.join(task.path, "addressing", f"q_{task.env_steps:08d}.png"), dpi=80)
    task.logger.writer.add_figure("addressing/probabilities", fig, task.env_steps)  # closes the figure


def evaluate_if_due(task: Task):
    """Every --eval-every env steps once prefilled: --eval-episodes episodes with the actor's mode, logged as eval/
    at the current step, then a checkpoint (a resumed run does not repeat this evaluation)."""
    args, policy, counters = task.args, task.policy, task.counters
    due = args.eval_episodes and task.env_steps >= counters["next_eval"]
    if not (due and len(task.replay) >= args.prefill_episodes):
        return
    episodes = []
    for i in range(args.eval_episodes):
        policy.reset()
        (episode,), frames = run_episodes(task.eval_env, lambda o: policy.act(o, None, task.rng),
                                          [task.seed * 1_000_003 + 7919 * task.env_steps + i], task.name,
                                          record=args.capture_video and i == 0)
        episodes.append(episode)
        if frames:
            write_gif(os.path.join(task.path, "videos", f"eval_{task.env_steps:08d}.gif"), frames)
    eval_metrics = episode_metrics("eval", episodes)
    while counters["next_eval"] <= task.env_steps:
        counters["next_eval"] += args.eval_every
    save_checkpoints(task)
    task.logger.log(task.env_steps, eval_metrics)
    task.progress.write(f"step {task.env_steps}: " + ", ".join(f"{k} {v:.2f}" for k, v in eval_metrics.items()))
    sys.stdout.flush()


def collect(task: Task):
    """(c) of Algorithm 2: one episode per env (random actions while prefilling), each stored atomically to M_τ
    (and to M, unless --no-own-episodes-in-m), logged with the run's speed."""
    args, replay = task.args, task.replay
    seeds = [task.seed * 1_000_003 + len(replay) + i for i in range(args.num_envs)]  # episode k's seed, N or not
    if len(replay) < args.prefill_episodes:
        action_size = task.envs.single_action_space.shape[0]
        act = lambda o: task.rng.uniform(-1, 1, (len(o), action_size)).astype(np.float32)  # noqa: E731
    else:
        task.policy.reset(args.num_envs)
        act = lambda o: task.policy.act(o, args.expl_noise, task.rng)  # noqa: E731
    episodes, _ = run_episodes(task.envs, act, seeds, task.name)
    for episode in episodes:
        save_episode(os.path.join(task.path, "episodes"), len(replay), episode)
        add_episode(args, replay, task.multitask, episode)
        steps = (len(episode["reward"]) - 1) * args.action_repeat
        task.env_steps += steps
        task.progress.update(steps)
        sps = (task.env_steps - task.start[1]) / (time.time() - task.start[0])
        task.logger.log(task.env_steps, {**episode_metrics("charts", [episode]), "charts/episodic_length": steps,
                                         "charts/SPS": sps, "charts/episodes": len(replay)})
    task.progress.set_postfix(ret=f"{float(episode['return']):.1f}", sps=f"{sps:.1f}")
    if task.progress.disable:  # no terminal (nohup, CI): one plain line per round instead of the bar
        print(f"step {task.env_steps}/{args.total_steps} | episode {len(replay)} | return "
              f"{np.mean([float(ep['return']) for ep in episodes]):.1f} | {sps:.1f} steps/s", flush=True)
        task.last_line = time.time()


def load_multitask_buffer(args: Args, obs_shape, action_size: int, rng) -> Replay:
    """M: the prior episodes (the same K are drawn again on resume: the same seed, the same files)."""
    multitask = Replay()
    if args.prior_dirs:
        for episode in load_prior_episodes(args.prior_dirs, args.prior_min_return, args.prior_max_episodes,
                                           obs_shape, action_size, rng):
            multitask.add(episode)
        counts = {t: multitask.tasks.count(t) for t in sorted(set(multitask.tasks))}
        print(f"multitask buffer: {len(multitask)} prior episodes {counts}, "
              f"{multitask.memory_bytes() / 2**30:.2f} GiB in memory", flush=True)
        check_prior_episodes(args, multitask)
    return multitask


def main(args: Args, given: frozenset = frozenset()):
    """Everything that can be checked (flags, env ids, prior episodes, the resumed folder and its checkpoints) is
    checked before the run folder is created or touched."""
    args, run_path, device = start_run(args, given)  # section 10: the checked args, the run folder's path, the device
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    tasks = task_list(args)
    probe = make_env(args, tasks[0], args.seed)
    obs_shape, action_size = probe.observation_space.shape, probe.action_space.shape[0]
    check_memory(args, probe.observation_space, action_size, len(tasks))  # section 10: M and the replay must fit
    probe.close()
    multitask = load_multitask_buffer(args, obs_shape, action_size, rng)
    task_paths = [run_path] if len(tasks) == 1 else [os.path.join(run_path, f"{k}_{env_id.split('/')[-1]}")
                                                     for k, env_id in enumerate(tasks)]
    address_path = os.path.join(run_path, "address.pt")
    checkpoints, saved_address, lock = open_run_folder(args, run_path, task_paths, address_path, given)  # noqa: F841
    if args.collect_expert:
        return collect_expert_episodes(args, run_path)
    addressing = Addressing(obs_shape, action_size, args, device) if args.method in ADDRESSED_METHODS else None
    if addressing is not None and saved_address is not None:
        load_addressing(address_path, addressing, saved_address)

    # Algorithm 1: tasks in order; the agent restarts per task, M and f_φ carry over
    for k, (env_id, task_path) in enumerate(zip(tasks, task_paths)):
        train_task(args, env_id, args.seed + 1000 * k, task_path, device, multitask, addressing, rng, address_path,
                   checkpoints.pop(task_path))


# ----------------------------------------------------------------------------------------------------------
# 10. Speed and reliability (the same math)
# ----------------------------------------------------------------------------------------------------------
def set_speed_options(module: nn.Module, precision: str, channels_last: bool) -> nn.Module:
    """--precision and --channels-last for every conv stack and MLP inside module (the RSSM itself stays fp32)."""
    for m in module.modules():
        if isinstance(m, (ConvEncoder, ConvDecoder, MLP)):
            m.bf16 = precision == "bf16"
        if isinstance(m, (ConvEncoder, ConvDecoder)) and channels_last:
            m.channels_last = True
            m.to(memory_format=torch.channels_last)  # conv weights (4-D) only
    return module


def padded_pool(pool: Pool, cap: int) -> Pool:
    """--cuda-graph: the pool's chunks, embeddings and mask padded to a power of two (at most --address-candidates)
    rows, so that a captured update serves until M outgrows it; q̂ never picks the padding (pool.valid)."""
    real = len(pool.embeddings)
    size = min(1 << (real - 1).bit_length(), cap)  # refresh embeds at most cap candidates
    pad = lambda t: torch.cat([t, t.new_zeros((size - len(t), *t.shape[1:]))])  # noqa: E731
    return Pool(pool.ids, {k: pad(v) for k, v in pool.chunks.items()}, pad(pool.reward_mask), pad(pool.embeddings),
                torch.arange(size, device=pool.embeddings.device) < real)  # (N_p, ...)


@contextlib.contextmanager
def timed(timings: dict, key: str):
    """Adds the block's wall time to timings[key]: the logs' time/<key>_per_update."""
    t0 = time.perf_counter()
    yield
    timings[key] = timings.get(key, 0.0) + time.perf_counter() - t0


def graph_inputs(x: dict, plan: UpdatePlan) -> dict:
    """Every tensor an update reads, by name: the static inputs of its CUDA graph."""
    inputs = {f"x.{k}": v for k, v in x.items()}
    inputs.update({f"m_batch.{k}": v for k, v in (plan.m_batch or {}).items()})
    if plan.pool is not None:
        inputs.update({f"pool.chunks.{k}": v for k, v in plan.pool.chunks.items()})
        inputs.update({f"pool.{k}": getattr(plan.pool, k) for k in ("reward_mask", "embeddings", "valid")
                       if getattr(plan.pool, k) is not None})
    return inputs


class GraphedUpdate:
    """--cuda-graph: `update` captured as CUDA graphs and replayed, one launch instead of ~1,000. A graph has fixed
    shapes: one per kind of update (its tensors' shapes, and mixed or not: α decides which rows are borrowed). The
    first `warmup` updates of a kind run eagerly on a side stream, as a capture needs (cuBLAS, the allocator and the
    optimisers' state set up). Each replay first copies x and the plan into static tensors that all graphs share (the
    memory-mode pool only after a refresh made a new one). A capture that fails prints one line; the run goes on
    eagerly."""

    def __init__(self, agent: Agent, addressing: Optional[Addressing], args: Args, warmup: int = 3):
        self.agent, self.addressing, self.args, self.warmup = agent, addressing, args, warmup
        self.graphs, self.seen, self.failed, self.stream, self.mempool = {}, {}, False, None, None
        self.static = {}  # (name, shape) -> [the graphs' input tensor, the tensor last copied into it]

    def __call__(self, x: dict, plan: UpdatePlan) -> dict:
        inputs = graph_inputs(x, plan)  # name -> tensor: everything the graph reads
        key = (tuple((k, tuple(v.shape)) for k, v in inputs.items()), plan.mixed)
        if self.failed or (key not in self.graphs and self.seen.get(key, 0) < self.warmup):
            self.seen[key] = self.seen.get(key, 0) + 1
            return self.on_side_stream(lambda: update(self.agent, self.addressing, x, plan, self.args))
        if key not in self.graphs:
            try:
                self.graphs[key] = self.capture(key, inputs, plan)
            except Exception as e:
                self.failed = True
                self.recover()
                print(f"--cuda-graph: capture failed, updates run eagerly ({type(e).__name__}: {str(e)[:160]})",
                      flush=True)
                return self(x, plan)
        graph, t0 = self.graphs[key], time.perf_counter()
        for name, source in inputs.items():  # no input changes in place: one copied before holds the same values
            static = self.static[(name, tuple(source.shape))]
            if static[1] is not source:  # (the memory-mode pool: until the next refresh)
                static[0].copy_(source, non_blocking=True)
                static[1] = source
        graph.replay()
        metrics = dict(zip(graph.metric_names, graph.metrics.clone().unbind()))
        timings = {"batch_sampling": 0.0, "graph_replay": time.perf_counter() - t0}
        if plan.refresh_seconds is not None:
            metrics["addressing/refresh_seconds"] = torch.tensor(plan.refresh_seconds)
            timings["addressing"] = plan.refresh_seconds
        picks = (plan.pool.ids, graph.picks.clone()) if plan.mixed else None
        return {"metrics": metrics, "timings": timings, "picks": picks}

    def capture(self, key: tuple, inputs: dict, plan: UpdatePlan) -> types.SimpleNamespace:
        """Record `update` on the static inputs; the metrics it returns become one vector. A memory-mode pool padded
        to another size retires the graphs of the old size (it may shrink too: a refresh's random phases change the
        count of candidate chunks, so near a power of two the padding can switch back and forth, each switch a new
        capture), and the static tensors no graph reads any more."""
        pool_rows = lambda k: dict(k[0]).get("pool.embeddings")  # noqa: E731
        self.graphs = {k: g for k, g in self.graphs.items() if pool_rows(k) == pool_rows(key)}
        wanted = {entry for k in [key, *self.graphs] for entry in k[0]}
        self.static = {k: v for k, v in self.static.items() if k in wanted}
        self.mempool = self.mempool if self.graphs else None  # a fresh pool once none is left in use
        static = {}
        for name, v in inputs.items():
            static[name] = self.static.setdefault((name, tuple(v.shape)), [v.clone(), v])[0]
        part = lambda prefix: {k[len(prefix):]: v for k, v in static.items() if k.startswith(prefix)}  # noqa: E731
        x, static_plan = part("x."), UpdatePlan(plan.mixed, part("m_batch.") or None)
        if plan.pool is not None:
            static_plan.pool = Pool(plan.pool.ids, part("pool.chunks."), static.get("pool.reward_mask"),
                                    static.get("pool.embeddings"), static.get("pool.valid"))

        def recorded():
            out = update(self.agent, self.addressing, x, static_plan, self.args)
            picks = out["picks"][1] if out["picks"] is not None else None
            return list(out["metrics"]), torch.stack([v.detach().float() for v in out["metrics"].values()]), picks

        replay, (names, vector, picks) = self.record(recorded)  # vector: (K,) the K metrics
        for opt in list(self.agent.optimizers().values()) + ([self.addressing.opt] if self.addressing else []):
            opt.zero_grad(set_to_none=True)  # the gradients the capture left in the pool are no one's to read
        return types.SimpleNamespace(replay=replay, metric_names=names, metrics=vector, picks=picks)

    def record(self, fn):
        """fn captured as a CUDA graph (its kernels are recorded, not run): (replay, fn's outputs as static tensors).
        One memory pool serves every graph (they never run at once)."""
        graph = torch.cuda.CUDAGraph()
        if self.addressing is not None:  # the picks' own generator: each replay advances it as eager draws would
            graph.register_generator_state(self.addressing.generator)
        self.mempool = self.mempool or torch.cuda.graph_pool_handle()
        with torch.cuda.graph(graph, pool=self.mempool, stream=self.stream, capture_error_mode="thread_local"):
            outputs = fn()
        return graph.replay, outputs

    def recover(self):
        """What a failed capture leaves behind (torch ~2.11): the capture stream current and the generators marked as
        capturing, so that the next eager draw would fail. Back to the default stream and to plain generator states."""
        torch.cuda.set_stream(torch.cuda.default_stream())
        generators = [torch.cuda.default_generators[torch.cuda.current_device()]]
        for generator in generators + ([self.addressing.generator] if self.addressing else []):
            generator.graphsafe_set_state(generator.clone_state())
        torch.cuda.synchronize()

    def on_side_stream(self, fn):
        """An eager update on the capture's stream (ordered after and before the default stream's work)."""
        self.stream = self.stream or torch.cuda.Stream()
        self.stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(self.stream):
            out = fn()
        torch.cuda.current_stream().wait_stream(self.stream)
        return out


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise UsageError(f"--device {name!r} is not a torch device (auto, cpu, cuda, cuda:N)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UsageError(f"--device {name}: CUDA is not available on this machine")
    return device


def native_bf16(device: torch.device, cpuinfo: str = "/proc/cpuinfo") -> Tuple[bool, str]:
    """Whether the device multiplies bf16 matrices in hardware, and what was found. Without it (a CPU with AVX2
    only) bf16 is emulated: measured 13x slower than fp32 at the paper's size."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported(), f"CUDA {torch.cuda.get_device_name(device)}"
    try:
        with open(cpuinfo) as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])
    except OSError:  # not Linux: no flags to read, so bf16 counts as emulated
        flags = []
    found = [flag for flag in ("avx512_bf16", "amx_bf16") if flag in flags]
    return bool(found), f"CPU {torch.backends.cpu.get_cpu_capability()}" + (f" with {'+'.join(found)}" if found else
                                                                           ", no avx512_bf16 or amx_bf16")


def check_precision(precision: str, device: torch.device) -> None:
    """--precision bf16 only where bf16 is fast: elsewhere one line that says why, instead of a run 13x slower."""
    native, found = native_bf16(device)
    if precision == "bf16" and not native:
        raise UsageError(f"--precision bf16: {found}, so bf16 would be emulated (about 13x slower than fp32 on such "
                         f"a CPU); use --precision fp32")


def first_update_notice(args: Args, device, env_steps: int, seconds: float) -> Optional[str]:
    """On a CPU, for pixels at the paper's size (n x L >= 50 x 50, 64x64 images): what the first update took and
    what the run's updates would take at that speed, and the one-minute alternative. None elsewhere."""
    if torch.device(device).type != "cpu" or args.obs_type != "pixels" or args.batch_size * args.seq_len < 2500 \
            or args.image_size < 64:
        return None
    episode_steps = episode_agent_steps(args) * args.action_repeat  # env steps of an episode
    updates = max(args.total_steps - env_steps, 0) / episode_steps * args.updates_per_episode
    days = updates * seconds / 86400
    return (f"note: on this CPU one update at the paper's size took {seconds:.1f} s, so the {updates:,.0f} updates "
            f"to --total-steps {args.total_steps:,} would take about "
            + (f"{days:,.1f} days (a GPU job)" if days >= 2 else f"{24 * days:.1f} hours")
            + ". A one-minute look on a CPU: python sweep.py sweeps/smoke.toml --workers 2, or --obs-type state")


def check_memory(args: Args, obs_space, action_size: int, num_tasks: int, meminfo: str = "/proc/meminfo"):
    """Refuse at start a run whose M and replay will not fit in memory by its end (the kernel's OOM killer would end
    it hours in, without a line of its own): the K longest prior episodes (lengths from the file names) and each
    task's own episodes up to --total-steps, against MemAvailable. --force starts anyway."""
    if args.force or args.collect_expert or not os.path.exists(meminfo):  # not Linux: nothing to weigh it against
        return
    step = obs_space.dtype.itemsize * int(np.prod(obs_space.shape)) + 4 * action_size + 5  # + reward, terminal
    names = [p for d in args.prior_dirs for folder in episode_folders(d) for p in list_episode_files(folder)]
    lengths = sorted(int((re.findall(r"-(\d+)\.npz$", p) or [episode_agent_steps(args)])[0]) + 1
                     for p in names)[-args.prior_max_episodes:]  # NNNNNN-LEN.npz, else this run's length
    episodes = -(-args.total_steps // (episode_agent_steps(args) * args.action_repeat)) + args.num_envs - 1
    prior, own = sum(lengths) * step, num_tasks * episodes * (episode_agent_steps(args) + 1) * step
    with open(meminfo) as f:
        available = next(int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable:"))
    if prior + own > available:
        raise UsageError(f"M ({len(lengths)} prior episodes, {prior / 2**30:.1f} GiB) and the replay up to "
                         f"--total-steps {args.total_steps:,} ({own / 2**30:.1f} GiB) will not fit in the "
                         f"{available / 2**30:.1f} GiB of memory available: lower --prior-max-episodes or "
                         f"--total-steps, use --obs-type state, or give --force")


def first_update_fits(step, args: Args, device):
    """The update, with an out-of-memory at the first one (the paper's size on a small card) as one line naming
    sizes that fit better instead of a traceback: the update's activations grow with --batch-size x --seq-len."""
    first = [True]

    def guarded(x, plan):
        try:
            return step(x, plan)
        except torch.OutOfMemoryError:
            if not first[0]:
                raise
            n, length = args.batch_size, args.seq_len
            raise UsageError(f"out of memory on {device} at the first update (--batch-size {n} --seq-len {length}): "
                             f"--batch-size {max(n // 2, 1)} or --seq-len {max(length // 2, 2)} halve its activations",
                             1) from None
        finally:
            first[0] = False
    return guarded


class UsageError(Exception):
    """Bad input from the command line or from files, or a run that had to stop: printed as one line; exit code 2,
    or `code` (1: non-finite losses; 128 + signal number: stopped by SIGINT/SIGTERM)."""

    def __init__(self, message: str, code: int = 2):
        super().__init__(message)
        self.code = code


def flag(name: str) -> str:
    """An Args field as the command line spells it: address_lr -> --address-lr."""
    return "--" + name.replace("_", "-")


def given_flags(argv: list) -> set:
    """The Args fields named on a command line (tyro spells them --foo-bar, --foo-bar=x, --no-foo-bar)."""
    names = {f.name for f in dataclasses.fields(Args)}
    given = {a[2:].split("=")[0].replace("-", "_") for a in argv if a.startswith("--")}
    return {n if n in names else n[3:] for n in given if n in names or n[3:] in names}


def parse_args(argv: list) -> Tuple[Args, set]:
    """The command line as Args, and the flags it names. tyro reports a parse error as a box of 4-9 lines: here it is
    one line like every other bad input, `--flag: what is wrong` (exit 2); --help still prints tyro's help."""
    box = io.StringIO()
    try:
        with contextlib.redirect_stderr(box):
            args = tyro.cli(Args, args=argv)
    except SystemExit as e:
        if e.code:  # --help exits with 0, its text on stdout
            raise UsageError(parse_error_line(box.getvalue())) from None
        raise
    sys.stderr.write(box.getvalue())  # tyro's warnings, if any
    return args, given_flags(argv)


def parse_error_line(box: str) -> str:
    """tyro's error box as one line: a bad value, a bad choice (with the allowed ones), a missing value, an unknown
    flag (with tyro's nearest one); any other error as the box's words."""
    text = " ".join(re.sub(r"\x1b\[[0-9;]*m|[│╭╮╰╯─]", " ", box).split())  # the box's words, on one line
    if m := re.search(r"Error parsing (\S+): (.*?) Argument helptext", text):
        return f"{m[1]}: {m[2]}"
    if m := re.search(r"invalid choice '(.*?)' for argument '(\S+)'\. Expected one of \((.*?)\)\.", text):
        return f"{m[2]}: {m[1]!r} is not one of {m[3].replace(chr(39), '')}"
    if m := re.search(r"Missing value for argument '(\S+)'", text):
        return f"{m[1]}: needs a value"
    if m := re.search(r"Unrecognized options: (\S+?),? .*?(?:Perhaps you meant: (--\S+)|For full)", text):
        return f"{m[1]}: " + ("unknown flag" if m[1].startswith("-") else "a value no flag takes") + (
            f" (did you mean {m[2]}?)" if m[2] else "")
    return text.split(" For full helptext")[0]


# the flags that may be given beside --resume (they change neither the networks nor what was collected); the other
# flags come from the run's args.json
RESUME_FLAGS = ("total_steps", "device", "eval_every", "eval_episodes", "capture_video", "track", "wandb_project",
                "plain_log", "log_interval_seconds", "precision", "channels_last", "cuda_graph", "force")


# flags added after runs were saved, with the value that was those runs' only behaviour: an args.json without one
# resumes with this value; any other missing flag is refused
ADDED_FLAGS = {"address_x_net": "shared", "preset": None, "address_adam_eps": None, "address_weight_decay": 0.0,
               "address_candidates_mode": "memory", "address_logit_scale": 1.0, "address_oversample_ends": False,
               "own_episodes_in_m": True, "reward_mask_borrowed": "other-tasks", "vrama_objective": "imagine",
               "addressed_wm_rule": "rows", "cuda_graph": None,
               "init": "torch", "eval_action": "mean", "force": False}


def check_args(args: Args) -> None:
    """Refuse bad input with a one-line message naming the flag (raised as UsageError, printed by main)."""
    positive = ["total_steps", "eval_every", "action_repeat", "time_limit", "image_size", "deter_size", "stoch_size",
                "hidden_size", "cnn_depth", "mlp_units", "horizon", "batch_size", "seq_len", "updates_per_episode",
                "prefill_episodes", "prior_max_episodes", "address_batch", "address_units", "address_cnn_depth",
                "address_refresh", "address_candidates", "address_plot_every", "model_lr", "actor_lr", "value_lr",
                "address_lr", "grad_clip", "address_grad_clip", "address_logit_scale", "num_envs"]
    for name in positive + ["obs_std", "address_adam_eps"]:  # the last two may be None (a default)
        if getattr(args, name) is not None and not getattr(args, name) > 0:  # `not >`: NaN is refused too
            raise UsageError(f"{flag(name)} must be > 0 (got {getattr(args, name)})")
    for name in ["eval_episodes", "address_imagine_starts", "log_interval_seconds"]:
        if not getattr(args, name) >= 0:  # NaN is refused too
            raise UsageError(f"{flag(name)} must be >= 0 (got {getattr(args, name)})")
    if not 0.0 <= args.address_weight_decay < 1.0:
        raise UsageError(f"--address-weight-decay must be in [0, 1) (got {args.address_weight_decay})")
    if not 0.0 < args.gamma <= 1.0 or not 0.0 <= args.return_lambda <= 1.0:
        raise UsageError("--gamma must be in (0, 1] and --return-lambda in [0, 1]")
    if not 0.0 <= args.address_prob <= 1.0 or not 0.0 <= args.current_fraction <= 1.0:
        raise UsageError("--address-prob and --current-fraction must be in [0, 1]")
    if args.method == "dreamer" and args.prior_dirs:
        raise UsageError("--prior-dirs needs a method that uses prior data (uniform, vrama, rrama, rbrama)")
    if args.seq_len < 2 or args.horizon < 2:
        raise UsageError(f"--seq-len and --horizon must be >= 2 (got {args.seq_len}, {args.horizon})")
    if conv_sizes(args.image_size)[-1] < 1:
        raise UsageError(f"--image-size must be >= 46 for the four stride-2 convs (got {args.image_size})")
    check_env_args(args)  # section 3: what this script's environments need
    if not task_list(args):
        raise UsageError("--task-sequence names no task")
    if args.track and importlib.util.find_spec("wandb") is None:
        raise UsageError("--track needs wandb: pip install wandb")
    if episode_agent_steps(args) < args.seq_len:
        raise UsageError(f"--seq-len {args.seq_len} is longer than an episode ({episode_agent_steps(args)} agent "
                         f"steps); lower it or raise --time-limit")
    for env_id in task_list(args):
        make_env_spec(env_id)  # raises a UsageError naming --env-id
    device = resolve_device(args.device)
    check_precision(args.precision, device)
    if args.cuda_graph and device.type != "cuda":
        raise UsageError(f"--cuda-graph needs a CUDA device (--device {args.device} is {device})")


def resolve_run(args: Args, given: set):
    """The run's args and folder, checked, nothing written: a new folder's name, or --resume's folder with its saved
    args and the RESUME_FLAGS given beside it (any other flag there is refused)."""
    if not args.resume:
        env_name = "__".join(t.replace("/", "_") for t in task_list(args)[:1]) + ("_seq" if args.task_sequence else "")
        return args, os.path.join(args.run_dir, f"{env_name}__{args.exp_name}__{args.method}__{args.seed}__"
                                                f"{int(time.time())}")
    args_path = os.path.join(args.resume, "args.json")
    if not os.path.isfile(args_path):
        raise UsageError(f"--resume {args.resume}: no args.json there (not a run folder)")
    refused = sorted(given - set(RESUME_FLAGS) - {"resume"})
    if refused:
        raise UsageError(f"--resume continues a run with its saved args: {', '.join(flag(n) for n in refused)} may "
                         f"not be given with it (only {', '.join(flag(n) for n in RESUME_FLAGS)})")
    try:
        with open(args_path) as f:
            saved = {**ADDED_FLAGS, **json.load(f)}
        missing = sorted(flag(f.name) for f in dataclasses.fields(Args) if f.name not in saved)
        if missing:  # a default filled in here could differ from what the run was trained with
            raise UsageError(f"saved by an older version of this script (no {', '.join(missing)}); resume it with that "
                             f"version")
        fields = {f.name: saved[f.name] for f in dataclasses.fields(Args)}  # flags since removed are dropped
        # --cuda-graph not given: the default of the device resumed on (graphs or not, the update's math is the same);
        # --force holds for the process that was given it
        given_now = {"cuda_graph": None, "force": False, **{k: getattr(args, k) for k in given & set(RESUME_FLAGS)}}
        resumed = dataclasses.replace(Args(**fields), resume=args.resume, **given_now)
        check_args(resumed)
    except (ValueError, TypeError, AttributeError, UsageError) as e:  # JSONDecodeError is a ValueError
        raise UsageError(f"{args_path}: {e}") from None
    return resumed, args.resume


def start_run(args: Args, given: frozenset):
    """The run's args (--preset's, the defaults that depend on the env, or --resume's saved ones) checked, its
    folder's path and its device: nothing written yet."""
    args = resolve_defaults(apply_preset(args, set(given)))
    check_args(args)
    args, run_path = resolve_run(args, set(given))
    device = resolve_device(args.device)
    if args.cuda_graph is None:  # the default: CUDA graphs wherever there is CUDA (saved so in args.json)
        args = dataclasses.replace(args, cuda_graph=device.type == "cuda")
    return args, run_path, device


def open_run(args: Args, run_path: str, rewrite_args: bool):
    """Create (or reopen) the run folder and lock it for this process (the lock goes with the process, even on
    kill -9): a second writer gets one line. Writes args.json for a new run, or a resumed one given RESUME_FLAGS."""
    try:
        os.makedirs(run_path, exist_ok=True)
        lock = open(os.path.join(run_path, ".lock"), "a")
    except OSError as e:
        raise UsageError(f"{'--resume' if args.resume else '--run-dir'}: cannot write {run_path} ({e.strerror})") \
            from None
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        raise UsageError(f"{run_path}: another process is writing this run folder (it holds its .lock)") from None
    if rewrite_args or not args.resume:
        with disk_write(os.path.join(run_path, "args.json"), "w") as f:
            json.dump(dataclasses.asdict(dataclasses.replace(args, resume=None)), f, indent=2)
    return lock


def open_run_folder(args: Args, run_path: str, task_paths: list, address_path: str, given: frozenset):
    """Each task's checkpoint and f_φ's read (and checked) before the folder is touched; then the folder made and
    locked, and SIGINT/SIGTERM set to stop at the next safe point. Returns the checkpoints by task folder, f_φ's, and
    the lock (held till the process exits)."""
    checkpoints = {p: read_checkpoint(os.path.join(p, "checkpoint.pt"), args) for p in task_paths}
    saved_address = read_checkpoint(address_path, args)
    lock = open_run(args, run_path, rewrite_args=bool(given & set(RESUME_FLAGS)))
    STOP["run_path"] = run_path
    signal.signal(signal.SIGINT, request_stop)
    signal.signal(signal.SIGTERM, request_stop)
    return checkpoints, saved_address, lock


def load_addressing(path: str, addressing: "Addressing", saved: dict):
    """f_φ, its frozen copy (--address-x-net frozen: its saved initial weights) and its optimiser from address.pt."""
    load_state(path, addressing.net, saved["net"])
    if addressing.x_net is not addressing.net:
        load_state(path, addressing.x_net, saved["x_net"])
    load_optimizer(addressing.opt, saved["opt"])


STOP = {"signal": None, "run_path": None}  # set by SIGINT/SIGTERM: the loops stop at their next safe point


def request_stop(signum, frame):
    """SIGINT or SIGTERM (what clusters send before preemption): stop after the current update or env step, the run
    folder holding only complete episodes and a checkpoint consistent with them; a second signal stops at once."""
    if STOP["signal"] is not None:
        raise KeyboardInterrupt
    STOP["signal"] = signum


def resume_hint() -> str:
    run_path = STOP["run_path"]
    return f"; continue with: python {os.path.basename(__file__)} --resume {run_path}" if run_path else ""


def check_stop():
    if STOP["signal"] is not None:
        raise UsageError(f"stopped by {signal.Signals(STOP['signal']).name}{resume_hint()}", 128 + STOP["signal"])


def checked_args(args: Args) -> dict:
    """What a checkpoint must have been saved with (as JSON has it): all args but those --resume may change."""
    saved = json.loads(json.dumps(dataclasses.asdict(args)))
    return {k: v for k, v in saved.items() if k not in RESUME_FLAGS + ("resume", "run_dir")}


@contextlib.contextmanager
def disk_write(path: str, mode: str = "wb", keep_prev: bool = False):
    """PATH written whole or not at all: a new file goes to a temp file beside it, then is renamed over PATH (the old
    one kept as PATH.prev with keep_prev); an append ("a") is cut back to its old size on failure. A kill or a full
    disk leaves every earlier file complete and no temp file; a full disk stops the run with one line naming the
    file and the free space (--resume continues once space is freed)."""
    append = mode.startswith("a")
    target = path if append else os.path.join(os.path.dirname(path), f".{os.path.basename(path)}.tmp")
    size = os.path.getsize(path) if append and os.path.exists(path) else 0
    try:
        with open(target, mode) as f:
            yield f
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.truncate(target, size) if append else os.remove(target)
        if isinstance(e, OSError) and e.errno == errno.ENOSPC:
            free = shutil.disk_usage(os.path.dirname(os.path.abspath(path))).free
            raise UsageError(f"{path}: no space left on the device ({free / 2**20:,.0f} MiB free): stopped, the "
                             f"files before it complete{resume_hint()}", 1) from None
        raise
    if keep_prev and os.path.exists(path):
        os.replace(path, path + ".prev")
    if not append:
        os.replace(target, path)


def write_checkpoint(path: str, payload: dict):
    """Atomic like the episodes; the one before stays as PATH.prev until the new one is in place, for a damaged newest
    file to fall back to."""
    with disk_write(path, keep_prev=True) as f:
        torch.save(payload, f)


# what checkpoints written before issue 126 pickled besides tensors and plain types: numpy's RNG state, an ndarray of
# uint32. Allowed to load so that those runs resume; anything else pickled is refused (loading it could run code)
OLD_NUMPY_STATE = [np._core.multiarray._reconstruct, np.ndarray, np.dtype, np.dtypes.UInt32DType]


def read_checkpoint(path: str, args: Args) -> Optional[dict]:
    """The newest loadable of PATH and PATH.prev (on the CPU; None when neither exists), saying so when it falls
    back; one line naming the file when neither loads or when it was saved with other args than args.json's."""
    unreadable = []
    for candidate in (path, path + ".prev"):
        if not os.path.exists(candidate):
            continue
        try:
            with torch.serialization.safe_globals(OLD_NUMPY_STATE):
                payload = torch.load(candidate, map_location="cpu", weights_only=True)
            saved = payload.get("args", {})  # checkpoints written before it was stored: shapes are checked on load
        except Exception as e:
            foreign = re.search(r"GLOBAL (\S+) was not an allowed global", str(e))
            if foreign:  # weights_only refused to build it
                raise UsageError(f"{candidate}: holds a pickled {foreign[1]}, not only tensors and plain types: not "
                                 f"loaded, as loading it could run code") from None
            unreadable.append(f"{candidate}: not a readable checkpoint ({type(e).__name__}: {str(e)[:80]!r})")
            continue
        now = checked_args(args)
        diff = [f"{k} {saved[k]!r} there, {now[k]!r} in args.json" for k in saved if k in now and saved[k] != now[k]]
        if diff:
            raise UsageError(f"{candidate} does not match args.json: " + "; ".join(diff))
        if unreadable:
            print(f"warning: {unreadable[0]}; falling back to {candidate}", flush=True)
        return payload
    if unreadable:
        raise UsageError("; ".join(unreadable) + " (remove it to restart the networks from the episodes)")
    return None


def load_state(path: str, module, state_dict: dict):
    try:
        module.load_state_dict(state_dict)
    except RuntimeError as e:  # torch gives a line per tensor: the first one names the mismatch
        raise UsageError(f"{path} does not match args.json: {str(e).splitlines()[1].strip()[:200]}") from None


def save_checkpoint(path: str, agent: Agent, state: dict, args: Args):
    name, keys, *rest = np.random.get_state()  # numpy's uint32 keys as a list: a weights_only load builds no ndarray
    payload = {"agent": agent.state_dict(), "optimizers": {k: o.state_dict() for k, o in agent.optimizers().items()},
               "state": state, "rng": {"python": random.getstate(), "numpy": (name, keys.tolist(), *rest),
                                       "torch": torch.get_rng_state()}, "args": checked_args(args)}
    write_checkpoint(path, payload)


def load_optimizer(opt, saved: dict):
    """An optimiser's saved state under this run's `capturable` (--cuda-graph may differ from the saving run's)."""
    capturable = opt.param_groups[0]["capturable"]
    opt.load_state_dict({**saved, "param_groups": [{**g, "capturable": capturable} for g in saved["param_groups"]]})


def load_checkpoint(path: str, payload: dict, agent: Agent) -> dict:
    load_state(path, agent, payload["agent"])
    for name, opt in agent.optimizers().items():
        load_optimizer(opt, payload["optimizers"][name])
    random.setstate(payload["rng"]["python"])
    np.random.set_state(payload["rng"]["numpy"])
    torch.set_rng_state(payload["rng"]["torch"])
    return payload["state"]


def save_checkpoints(task: Task):
    """checkpoint.pt (agent, optimisers, state, RNG states) and address.pt (f_φ, its frozen copy, its optimiser)."""
    save_checkpoint(os.path.join(task.path, "checkpoint.pt"), task.agent, task.counters, task.args)
    if task.addressing is not None:
        net, x_net, opt = task.addressing.net, task.addressing.x_net, task.addressing.opt
        write_checkpoint(task.address_path, {"net": net.state_dict(), "x_net": x_net.state_dict(),
                                             "opt": opt.state_dict(), "args": checked_args(task.args)})


def check_finite(task: Task, update_metrics: list, metrics: dict, done: int):
    """One check per round (the sums carry any NaN or inf): the round is then neither saved nor logged, and the run
    stops with a line naming the first bad metric and its update."""
    if all(map(np.isfinite, metrics.values())) and all(p.isfinite().all() for p in task.agent.parameters()):
        return
    bad = [(i, k) for i, row in enumerate(update_metrics) for k, v in row.items() if not v.isfinite()]
    i, key = (bad or [(done - 1, "weights")])[0]
    task.logger.log(task.env_steps, {"errors/non_finite_update": task.counters["updates"] - done + i + 1})
    raise UsageError(f"non-finite {key} at update {task.counters['updates'] - done + i + 1}: stopped without saving "
                     f"its round (is a learning rate too high?)", 1)


if __name__ == "__main__":
    try:
        main(*parse_args(sys.argv[1:]))
    except UsageError as e:
        print(f"{'error: ' if e.code < 128 else ''}{e}", file=sys.stderr)
        sys.exit(e.code)
    except KeyboardInterrupt:  # a second Ctrl-C, or one before the run folder exists
        print(f"interrupted{resume_hint()}", file=sys.stderr)
        sys.exit(130)
