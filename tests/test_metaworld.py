"""rama_metaworld.py: the Meta-World wrapper (spaces, upright images, task sets, seeding, truncation, expert)
and few-step runs of every method with a tiny prior buffer."""
import glob
import json
import os
import re

import numpy as np
import pytest

from helpers import TINY, run_script
from rama_metaworld import (ActionRepeat, MetaWorldEnv, UsageError, _sample_rand_vecs, expert_action, make_env_spec,
                            task_vectors)


@pytest.fixture(scope="module")
def push():
    env = MetaWorldEnv("metaworld/push", seed=0)
    yield env
    env.close()


def _random_actions(n, seed=0):
    return np.random.default_rng(seed).uniform(-1, 1, (n, 4)).astype(np.float32)


def _wood(image):  # the table's brown wood, told apart from the grey background and the red robot
    r, g, b = (image[..., i].astype(int) for i in range(3))
    return (r - g >= 15) & (g - b >= 10) & (r - g < 60)


def test_env_spec_names():
    assert make_env_spec("metaworld/push")["task"] == "push-v3"
    assert make_env_spec("metaworld/peg-insert-side-v3") == {"suite": "metaworld", "task": "peg-insert-side-v3",
                                                               "name": "peg-insert-side"}
    for name in ("sweep-into", "dial-turn", "drawer-close"):
        assert make_env_spec(f"metaworld/{name}")["name"] == name
    for bad in ("metaworld/pushh", "dmc/push", "push"):
        with pytest.raises(UsageError, match="--env-id"):
            make_env_spec(bad)
    with pytest.raises(UsageError, match="--camera"):
        MetaWorldEnv("metaworld/push", 0, camera="nope")


def test_spaces_and_dtypes(push):
    obs, _ = push.reset(seed=0)
    assert push.action_space.shape == (4,) and push.observation_space.shape == (64, 64, 3)
    assert obs.shape == push.observation_space.shape and obs.dtype == np.uint8
    obs, reward, terminated, truncated, info = push.step(np.ones(4, np.float32))
    assert obs.shape == (64, 64, 3) and obs.dtype == np.uint8 and isinstance(reward, float)
    assert terminated is False and truncated is False
    assert push.render().dtype == np.uint8 and push.task_vector.dtype == np.float32
    state_env = MetaWorldEnv("metaworld/push", seed=0, obs_type="state")
    state, _ = state_env.reset(seed=0)
    assert state_env.observation_space.shape == (39,) and state.shape == (39,) and state.dtype == np.float32
    assert np.all(state[-3:] == 0)  # the goal (part of the task vector) is hidden from the agent
    state_env.close()


@pytest.mark.parametrize("camera", ["corner2_moved", "corner2"])
def test_images_upright(camera):
    env = MetaWorldEnv("metaworld/push", seed=0, camera=camera)
    image, _ = env.reset(seed=0)
    wood = _wood(image)
    assert wood[48:].mean() > 0.15 and wood[:16].mean() < 0.02  # the table at the bottom, background on top
    assert not np.array_equal(image, image[::-1])
    env.close()


def test_task_sets_distinct_and_disjoint():
    train, new = task_vectors("push", "train", 0), task_vectors("push", "new", 0)
    assert train.shape == (50, 6) and new.shape == (50, 6) and train.dtype == np.float32
    assert len(np.unique(train, axis=0)) == 50 and len(np.unique(new, axis=0)) == 50
    assert not (train[:, None] == new[None]).all(-1).any()
    _sample_rand_vecs.cache_clear()  # drawn again, not read from the cache: seed-reproducible
    assert np.array_equal(train, task_vectors("push", "train", 0))
    assert not np.array_equal(train, task_vectors("push", "train", 1))  # runs differ (paper, Sec. 5)
    with pytest.raises(UsageError):
        task_vectors("push", "test", 0)


def test_active_vector_comes_from_the_set(push):
    train = task_vectors("push", "train", 0)
    seen = set()
    for seed in range(10):
        push.reset(seed=seed)
        assert any(np.array_equal(push.task_vector, v) for v in train)
        seen.add(push.task_index)
    assert len(seen) >= 5
    push.reset(seed=3)
    index, vector = push.task_index, push.task_vector
    push.reset(seed=3)
    assert push.task_index == index and np.array_equal(push.task_vector, vector)
    new_env = MetaWorldEnv("metaworld/push", seed=0, obs_type="state", task_set="new")
    new_env.reset(seed=3)
    assert not any(np.array_equal(new_env.task_vector, v) for v in train)
    new_env.close()


def _rollout(env, seed, steps=10):
    frames, rewards = [env.reset(seed=seed)[0]], []
    for action in _random_actions(steps):
        obs, reward, _, _, _ = env.step(action)
        frames.append(obs)
        rewards.append(reward)
    return np.stack(frames), np.array(rewards)


@pytest.mark.slow
def test_reproducible_under_seed(push):
    frames, rewards = _rollout(push, seed=5)
    other = MetaWorldEnv("metaworld/push", seed=0)  # a second env in the process: its own renderer
    frames2, rewards2 = _rollout(other, seed=5)
    assert np.array_equal(frames, frames2) and np.array_equal(rewards, rewards2)
    frames3, _ = _rollout(push, seed=5)  # rendering `other` did not disturb `push`
    assert np.array_equal(frames, frames3)
    other.close()
    different = MetaWorldEnv("metaworld/push", seed=1)  # another run: another task set
    frames4, rewards4 = _rollout(different, seed=5)
    assert not np.array_equal(frames[0], frames4[0]) and not np.array_equal(rewards, rewards4)
    different.close()
    # reset() without a seed draws from the env's own generator, seeded at construction
    indices = []
    for _ in range(2):
        env = MetaWorldEnv("metaworld/push", seed=7, obs_type="state")
        indices.append([env.reset() is not None and env.task_index for _ in range(5)])
        env.close()
    assert indices[0] == indices[1] and len(set(indices[0])) > 1


def test_truncation_at_500_env_steps():
    env = ActionRepeat(MetaWorldEnv("metaworld/push", seed=0, obs_type="state"), 2, 500)
    for _ in range(2):  # the env is reusable after truncation
        env.reset(seed=0)
        steps, truncated = 0, False
        for action in _random_actions(300):
            _, reward, terminated, truncated, _ = env.step(action)
            steps += 1
            assert 0.0 <= reward <= 20.0 and not terminated  # two env steps of 0..10 each
            if truncated:
                break
        assert truncated and steps == 250 and env.unwrapped._env.curr_path_length == 500
    env.close()


@pytest.mark.slow
def test_expert_succeeds_with_env_step_rewards_in_0_10():
    env = MetaWorldEnv("metaworld/push", seed=0, obs_type="state")
    successes, rewards = [], []
    for seed in range(3):
        env.reset(seed=seed)
        done = False
        while not done:
            _, reward, _, done, _ = env.step(expert_action(env))
            rewards.append(reward)
        successes.append(env.last_success)
    assert np.mean(successes) >= 2 / 3
    assert min(rewards) >= 0.0 and max(rewards) <= 10.0 and max(rewards) > 5.0
    env.close()


def test_expert_acts_from_pixels_env(push):
    push.reset(seed=0)
    for _ in range(100):
        push.step(expert_action(push))
    assert push.last_success  # the pixel env keeps the state the scripted policy needs


def run(*flags, check=True):
    return run_script("rama_metaworld.py", *flags, check=check)


@pytest.fixture(scope="module")
def expert_prior(tmp_path_factory):
    root = tmp_path_factory.mktemp("prior")
    run("--env-id", "metaworld/push", "--collect-expert", "2", "--exp-name", "expert", "--run-dir", str(root), *TINY)
    (run_path,) = glob.glob(os.path.join(root, "*"))
    return run_path


@pytest.mark.slow
def test_expert_prior_episodes_keep_their_task_vector(expert_prior):
    paths = sorted(glob.glob(os.path.join(expert_prior, "episodes", "*.npz")))
    assert len(paths) == 2
    train = task_vectors("push", "train", 1)
    for path in paths:
        with np.load(path) as ep:
            # 100 env steps at Meta-World's action repeat 1: 100 agent steps and the first observation
            assert ep["obs"].shape == (101, 64, 64, 3) and ep["action"].shape == (101, 4)
            assert any(np.allclose(ep["task_vector"], v) for v in train)  # stored for analysis, from the set
            assert ep["success"].dtype == bool and float(ep["return"]) > 100  # the expert pushes


@pytest.mark.slow
@pytest.mark.parametrize("method", ["dreamer", "uniform", "vrama", "rrama", "rbrama"])
def test_every_method_runs_on_new_vectors(tmp_path, expert_prior, method):
    prior = [] if method == "dreamer" else ["--prior-dirs", expert_prior]
    run("--env-id", "metaworld/push", "--task-set", "new", "--method", method, *prior, "--run-dir", str(tmp_path),
        *TINY)
    (run_path,) = glob.glob(os.path.join(tmp_path, "*"))
    with open(os.path.join(run_path, "metrics.jsonl")) as f:
        keys = set().union(*(json.loads(line) for line in f))
    assert {"charts/episodic_return", "charts/success_rate", "eval/success_rate", "losses/world_model"} <= keys
    if method != "dreamer":
        assert "addressing/pick_fraction/push" in keys
    new = task_vectors("push", "new", 1)
    with np.load(sorted(glob.glob(os.path.join(run_path, "episodes", "*.npz")))[0]) as ep:
        assert any(np.allclose(ep["task_vector"], v) for v in new)
    if method == "rrama":  # the offline check of f_φ reads a Meta-World run through rama_metaworld's own args
        proc = run_script("tools/addressing_offline.py", run_path, "--updates", "1", "--seeds", "0", "--eval-rows", "2")
        assert "| run | 1 |" in proc.stdout and "rrama, M = 2 prior" in proc.stdout


@pytest.mark.slow
@pytest.mark.parametrize("flags, shared", [([], 2), (["--task-set", "new", "--num-tasks", "10"], 1)])
def test_a_prior_on_the_runs_own_task_vectors_is_refused(tmp_path, expert_prior, flags, shared):
    """The expert prior ran on the train set of 50 (seed 1). The same set, or the new set of 10, which is draws 10-19
    of the same stream and so inside that train set, is refused before the run folder exists, in one line."""
    proc = run("--env-id", "metaworld/push", "--method", "rrama", "--prior-dirs", expert_prior, *flags,
               "--run-dir", str(tmp_path), *TINY, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    # both expert episodes share the train set (their vectors: indices 4 and 17 of it); the new set of 10 is draws
    # 10-19, which holds one of them
    assert f"--prior-dirs: {shared} of the prior's episodes of push ran on this run's own task vectors" in lines[0]
    assert not os.listdir(tmp_path)


@pytest.mark.slow
def test_bad_env_id_is_one_line(tmp_path):
    proc = run("--env-id", "metaworld/fly", "--run-dir", str(tmp_path), check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "--env-id" in lines[0], proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("task", ["push", "peg-insert-side", "sweep-into", "dial-turn", "drawer-close"])
def test_table2_tasks_build_and_step(task):
    env = MetaWorldEnv(f"metaworld/{task}", seed=3)
    try:
        obs, _ = env.reset(seed=1)
        assert obs.shape == (64, 64, 3) and obs.std() > 5  # a real picture, not a blank frame
        obs, reward, terminated, truncated, info = env.step(expert_action(env))
        assert 0.0 <= reward <= 20.0 and not terminated and not truncated and "success" in info
        assert len(task_vectors(task, "new", 3)) == 50
    finally:
        env.close()
