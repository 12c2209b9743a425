"""Tests of kitchen_env.py: spaces, reward bookkeeping, seeding, the scripted expert, renders, clean exit."""
import os
import subprocess
import sys

import gymnasium
import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import kitchen_env  # noqa: E402  (sets MUJOCO_GL before mujoco is imported)

TASKS = ["bluebox", "bluecone"]


def blue_pixels(frame):
    """Count of clearly blue pixels: the object and the target zone are the only blue things in the scene."""
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    return int(np.sum((b > 150) & (b > r + 80) & (b > g + 40)))


def rollout(env, seed, policy, steps=500):
    """Return of one episode, and its initial and final distances (cm)."""
    _, info = env.reset(seed=seed)
    start, total = info["distance"], 0.0
    for _ in range(steps):
        _, reward, terminated, truncated, info = env.step(policy(env))
        total += reward
        if terminated or truncated:
            break
    return total, start, info["distance"]


@pytest.mark.parametrize("obs_type", ["pixels", "state"])
@pytest.mark.parametrize("active_joints", [3, 7])
def test_spaces_and_dtypes(obs_type, active_joints):
    env = kitchen_env.KitchenEnv(active_joints=active_joints, obs_type=obs_type)
    assert env.action_space.shape == (active_joints,) and env.action_space.dtype == np.float32
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    obs, info = env.reset(seed=0)
    expected = (64, 96, 3) if obs_type == "pixels" else (23,)
    assert obs.shape == env.observation_space.shape == expected
    assert obs.dtype == env.observation_space.dtype == (np.uint8 if obs_type == "pixels" else np.float32)
    assert env.observation_space.contains(obs)
    assert info["distance"] == pytest.approx(50.0) and info["success"] is False
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs) and isinstance(reward, float)
    assert terminated is False and truncated is False and set(info) >= {"distance", "success"}
    env.close()


def test_other_observation_size():
    env = kitchen_env.KitchenEnv(width=64, height=48)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (48, 64, 3) and env.render().shape == (48, 64, 3)
    assert env.render_frame(160, 120).shape == (120, 160, 3)
    env.close()


@pytest.mark.parametrize("task", TASKS)
@pytest.mark.parametrize("start", ["fixed", "random"])
def test_rewards_telescope_and_truncate_at_500(task, start):
    env = kitchen_env.KitchenEnv(task=task, obs_type="state", start=start)
    env.action_space.seed(1)
    # a random start, then the expert, so that the object really moves and rewards are not all zero
    policy = lambda e: e.action_space.sample() if e._steps < 50 else kitchen_env.scripted_action(e)  # noqa: E731
    _, info = env.reset(seed=1)
    start, rewards = info["distance"], []
    for step in range(500):
        _, reward, terminated, truncated, info = env.step(policy(env))
        rewards.append(reward)
        assert not terminated and truncated == (step == 499)
    assert start == pytest.approx(50.0, abs=1e-9)
    assert sum(rewards) == pytest.approx(start - info["distance"], abs=1e-6)
    assert max(np.abs(rewards)) > 0.1  # the object moved
    env.close()


def test_seeding():
    def first(seed):
        env = kitchen_env.KitchenEnv(start="random")
        env.action_space.seed(seed)
        frames, rewards = [env.reset(seed=seed)[0]], []
        start = env.object_pos()
        for _ in range(20):
            obs, reward, *_ = env.step(kitchen_env.scripted_action(env))
            frames.append(obs)
            rewards.append(reward)
        env.close()
        return np.stack(frames), np.array(rewards), start

    frames_a, rewards_a, start_a = first(7)
    frames_b, rewards_b, start_b = first(7)
    _, _, start_c = first(8)
    assert np.array_equal(frames_a, frames_b) and np.array_equal(rewards_a, rewards_b)
    assert np.array_equal(start_a, start_b)
    assert np.linalg.norm(start_a[:2] - start_c[:2]) > 1e-3  # a different seed moves the object's start


@pytest.mark.parametrize("task", TASKS)
def test_scripted_expert_pushes_object_into_zone(task):
    env = kitchen_env.KitchenEnv(task=task, obs_type="state")  # no rendering: fast
    returns, successes = [], []
    for seed in range(5):
        returns.append(rollout(env, seed, kitchen_env.scripted_action)[0])
        successes.append(env._info()["success"])
    env.close()
    assert sum(r >= 40 for r in returns) >= 3 and sum(successes) >= 3, (returns, successes)
    assert max(returns) <= 50.0 + 1e-6  # the initial distance bounds the return


@pytest.mark.parametrize("task", TASKS)
def test_fixed_start_is_one_spot_the_expert_solves(task):
    """start="fixed" (the default, the paper's "initial object position"): every seed puts the object on the same spot,
    50 cm from the zone's centre on its left, yaw 0; the scripted pusher scores at least 45 of the 50 from there."""
    env = kitchen_env.KitchenEnv(task=task, obs_type="state")
    assert env.start == "fixed"
    starts = []
    for seed in range(3):
        total, start, _ = rollout(env, seed, kitchen_env.scripted_action)
        env.reset(seed=seed)
        starts.append(env.data.qpos[env._obj:env._obj + 7].copy())
        assert start == pytest.approx(50.0, abs=1e-9) and total >= 45, (seed, total)
    env.close()
    assert all(np.array_equal(s, starts[0]) for s in starts)
    angle = np.rad2deg(np.arctan2(starts[0][1] - kitchen_env.GOAL_XY[1], starts[0][0] - kitchen_env.GOAL_XY[0]))
    assert angle == pytest.approx(100.0) and np.allclose(starts[0][3:], [1, 0, 0, 0])  # yaw 0
    with pytest.raises(AssertionError, match="start must be"):
        kitchen_env.KitchenEnv(start="fixd")


def test_scripted_expert_with_seven_joints():
    env = kitchen_env.KitchenEnv(active_joints=7, obs_type="state")
    total, _, _ = rollout(env, 0, kitchen_env.scripted_action)
    env.close()
    assert total >= 40


@pytest.mark.parametrize("task", TASKS)
def test_random_actions_return_about_zero(task):
    env = kitchen_env.KitchenEnv(task=task, obs_type="state")
    env.action_space.seed(0)
    # Random accelerations rarely reach the object (about 1 episode in 20 moves it at all), so returns are ~0.
    returns = [rollout(env, seed, lambda e: e.action_space.sample())[0] for seed in range(4)]
    env.close()
    assert abs(np.mean(returns)) < 5 and all(abs(r) < 15 for r in returns), returns


def test_terminates_when_the_object_falls_off_the_table():
    env = kitchen_env.KitchenEnv(obs_type="state")
    env.reset(seed=0)
    env.data.qpos[env._obj:env._obj + 2] = [1.25, 0.0]  # just past the table's far edge (x = 1.12)
    for step in range(20):
        _, _, terminated, truncated, _ = env.step(np.zeros(3, np.float32))
        if terminated:
            break
    assert terminated and not truncated and step < 10
    env.close()


def test_blocked_arm_does_not_wind_up():
    # Driving the lift down into the table for a while: the servo target stays near the measured angle.
    env = kitchen_env.KitchenEnv(obs_type="state")
    env.reset(seed=0)
    for _ in range(60):
        env.step(np.array([0.0, 1.0, 0.0], np.float32))
    lead = env._target - env.data.qpos[env._qadr]
    assert np.all(np.abs(lead) <= kitchen_env.SLACK + 1e-9)
    assert env.knuckle_pos()[2] > kitchen_env.TABLE_Z - 0.01  # the table stopped the hand
    env.close()


@pytest.mark.parametrize("task", TASKS)
def test_render_not_blank_and_object_visible(task):
    env = kitchen_env.KitchenEnv(task=task)
    obs, _ = env.reset(seed=0)
    assert obs.std() > 20  # a scene, not a flat colour
    blue_with_object = blue_pixels(obs)
    assert blue_with_object >= 8  # the zone and the object
    env.data.qpos[env._obj + 2] -= 10.0  # hide the object below the floor: the blue count drops
    kitchen_env.mujoco.mj_forward(env.model, env.data)
    assert blue_pixels(env.render()) < blue_with_object - 2
    big = env.render_frame(480, 320)
    assert big.shape == (320, 480, 3) and big.std() > 20
    env.close()


def test_close_leaves_no_egl_error_at_exit():
    code = ("import kitchen_env; env = kitchen_env.KitchenEnv(); env.reset(seed=0);"
            "env.step(env.action_space.sample()); env.render_frame(240, 160); env.close(); print('ok')")
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120,
                            env={**os.environ, "MUJOCO_GL": "egl"})
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr
    assert "EGL" not in result.stderr, result.stderr


@pytest.mark.parametrize("env_id", ["Kitchen-BlueBox-v0", "Kitchen-BlueCone-v0"])
def test_gymnasium_make(env_id):
    env = gymnasium.make(env_id)
    obs, info = env.reset(seed=0)
    assert obs.shape == (64, 96, 3) and env.action_space.shape == (3,)
    assert env.unwrapped.task == ("bluebox" if "Box" in env_id else "bluecone")
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert env.render().shape == (64, 96, 3)
    env.close()


@pytest.mark.slow
def test_precheck_tool_writes_a_row_per_start_and_policy(tmp_path):
    """tools/kitchen_precheck.py, one episode each: a summary row for both starts and both policies."""
    import json

    out = tmp_path / "precheck.json"
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "tools", "kitchen_precheck.py"), "--episodes", "1",
                           "--out", str(out)], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(out.read_text())
    assert set(summary) == {"fixed/dreamer-init", "fixed/uniform", "random/dreamer-init", "random/uniform"}
    for row in summary.values():
        assert row["episodes"] == 1 and row["min_return"] <= row["mean_return"] <= row["max_return"]
        assert row["any_positive_reward"] in (0.0, 1.0) and row["object_moved"] in (0.0, 1.0)
