"""One action-repeat wrapper for every family (DMC, the kitchen, Meta-World), with one time-limit rule: an episode is
truncated once it has taken --time-limit env steps, so it lasts ceil(time_limit / repeat) agent steps."""
import inspect
import os

import gymnasium
import numpy as np
import pytest

from helpers import TINY, run_script
import rama_dreamer as rd
import rama_metaworld as rm


class Counter(gymnasium.Env):
    """A stand-in env: reward 1 per env step, success at env step `success_at`, its own end at `own_limit`."""

    def __init__(self, success_at=None, own_limit=10**9, terminate_at=None):
        self.success_at, self.own_limit, self.terminate_at = success_at, own_limit, terminate_at
        self.steps, self.observed = 0, 0
        self.observation_space = self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, **kwargs):
        self.steps = 0
        return self.observe(), {}

    def step_physics(self, action):
        self.steps += 1
        info = {} if self.success_at is None else {"success": self.steps == self.success_at}
        return 1.0, self.steps == self.terminate_at, self.steps >= self.own_limit, info

    def observe(self):
        self.observed += 1
        return self.steps


def play(env):
    env.reset()
    lengths, returns, infos = 0, 0.0, []
    while True:
        obs, reward, terminated, truncated, info = env.step(None)
        lengths, returns = lengths + 1, returns + reward
        infos.append(info)
        if terminated or truncated:
            return lengths, returns, infos, obs


@pytest.mark.parametrize("repeat, limit, length", [(2, 10, 5), (3, 10, 4), (1, 7, 7), (4, 4, 1)])
def test_an_episode_is_ceil_of_limit_over_repeat_agent_steps(repeat, limit, length):
    inner = Counter()
    steps, total, infos, last_obs = play(rd.ActionRepeat(inner, repeat, limit))
    assert steps == length == -(-limit // repeat)
    assert total == limit and last_obs == limit  # every env step's reward, and no step past the limit
    assert inner.observed == 1 + steps  # one observation per agent step (and the reset's): none in between
    assert all("success" not in info for info in infos)  # an env without success reports none


def test_success_at_any_repeated_step_counts_and_the_env_may_end_first():
    _, _, infos, _ = play(rd.ActionRepeat(Counter(success_at=3), 2, 10))
    assert [info["success"] for info in infos] == [False, True, False, False, False]  # env step 3: agent step 2
    steps, total, _, _ = play(rd.ActionRepeat(Counter(own_limit=5), 2, 10))
    assert steps == 3 and total == 5  # the env's own truncation ends the last repeat early
    steps, total, _, _ = play(rd.ActionRepeat(Counter(terminate_at=4), 3, 10))
    assert steps == 2 and total == 4


def test_the_two_scripts_share_the_wrapper_word_for_word():
    assert inspect.getsource(rd.ActionRepeat) == inspect.getsource(rm.ActionRepeat)


def _episode(S, env_id, repeat, limit, seed=3, expert=False, wrapped=True):
    """Length and return of one episode of env_id (state observations) with seeded random actions or the expert.
    wrapped False: the same episode without ActionRepeat, each action sent `repeat` times to the env's own step()
    and the episode ended at `limit` env steps or by the env: the reference the wrapper must reproduce."""
    start = {"kitchen_start": "random"} if env_id.startswith("kitchen/") else {}  # the start FACTS were measured from
    args = S.resolve_defaults(S.Args(env_id=env_id, obs_type="state", action_repeat=repeat, time_limit=limit, **start))
    env = S.make_env(args, env_id, seed)
    assert isinstance(env, S.ActionRepeat)
    env = env if wrapped else env.unwrapped
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    if expert:
        from kitchen_env import scripted_action

        act = lambda: scripted_action(env.unwrapped)  # noqa: E731
    else:
        act = lambda: rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)  # noqa: E731
    steps, env_steps, total, done = 0, 0, 0.0, False
    while not done:
        action, steps = act(), steps + 1
        for _ in range(1 if wrapped else repeat):
            _, reward, terminated, truncated, _ = env.step(action)
            env_steps, total = env_steps + 1, total + reward
            done = terminated or truncated or (not wrapped and env_steps >= limit)
            if done:
                break
    env.close()
    return steps, round(total, 4)


# Measured with each family's own repeat loop, before the one wrapper (commit f6e53a2): the same lengths
# and returns, except DMC at a repeat that does not divide the limit (333 agent steps then, floor; 334 now, ceil).
FACTS = [(rd, "dmc/cartpole-balance", 2, 1000, False, (500, 349.515)),
         (rd, "dmc/cartpole-balance", 3, 1000, False, (334, 336.6347)),
         (rd, "dmc/walker-walk", 2, 1000, False, (500, 37.9514)),
         (rd, "kitchen/bluebox", 2, 500, True, (250, 49.2288)),
         (rd, "kitchen/bluebox", 3, 500, True, (167, 48.4563)),
         (rm, "metaworld/reach", 2, 500, False, (250, 559.6352)),
         (rm, "metaworld/reach", 3, 500, False, (167, 624.9685)),
         (rm, "metaworld/drawer-close", 2, 200, False, (100, 6.5921))]


@pytest.mark.parametrize("script, env_id, repeat, limit, expert, expected", FACTS,
                         ids=[f"{f[1]}-r{f[2]}-l{f[3]}" for f in FACTS])
def test_each_familys_episodes_for_a_fixed_seed(script, env_id, repeat, limit, expert, expected):
    steps, total = _episode(script, env_id, repeat, limit, expert=expert)
    assert steps == expected[0] == -(-limit // repeat)
    # the wrapper's episode is the env's own, each action repeated by hand: the same length and return
    assert (steps, total) == _episode(script, env_id, repeat, limit, expert=expert, wrapped=False)
    assert total == pytest.approx(expected[1], abs=1e-3)  # and that of each family's loop before the wrapper


def test_a_cpu_users_first_pixel_update_gives_the_cost_of_the_run():
    """A (fake) 12 s first update on a CPU at the paper's size: the line gives it, the updates left and the days."""
    args = rd.resolve_defaults(rd.Args())  # the paper's run: 2M env steps, 1000-step episodes, C = 100
    line = rd.first_update_notice(args, "cpu", 0, 12.0)
    # 2,000,000 / 1,000 env steps per episode = 2,000 episodes x 100 updates = 200,000 updates x 12 s = 27.8 days
    assert "took 12.0 s" in line and "200,000 updates" in line and "about 27.8 days" in line
    assert "sweeps/smoke.toml" in line and "--obs-type state" in line
    assert "about 13.9 days" in rd.first_update_notice(args, "cpu", 1_000_000, 12.0)  # half the run is left
    assert rd.first_update_notice(args, "cuda", 0, 12.0) is None  # a GPU: no notice
    assert rd.first_update_notice(rd.resolve_defaults(rd.Args(obs_type="state")), "cpu", 0, 12.0) is None
    assert rd.first_update_notice(rd.resolve_defaults(rd.Args(batch_size=16)), "cpu", 0, 12.0) is None
    short = rd.resolve_defaults(rd.Args(total_steps=20_000))  # 2,000 updates x 12 s = 6.7 hours
    assert "about 6.7 hours" in rd.first_update_notice(short, "cpu", 0, 12.0)


def test_family_references_score_the_random_policy_and_the_expert():
    """tools/family_references.py, one episode each: the kitchen's expert pushes the box in (a return near the 50 cm
    it starts away), a random arm never moves it; Meta-World's drawer-close expert succeeds through the same envs."""
    from tools.family_references import score

    kitchen = {p: score(rd, "kitchen/bluebox", {}, p, episodes=1) for p in ("random", "expert")}
    assert kitchen["expert"]["success_rate"] == 1.0 and 40.0 < kitchen["expert"]["return"] <= 50.0
    assert kitchen["random"]["success_rate"] == 0.0 and abs(kitchen["random"]["return"]) < 1.0
    drawer = score(rm, "metaworld/drawer-close", {"task_set": "new"}, "expert", episodes=1)
    assert drawer["success_rate"] == 1.0 and drawer["episodes"] == 1



def test_table2_levels_are_keyed_by_the_sweeps_cells():
    """report.py --levels matches a level to a run by its cell's name: --table2's keys are cells of the Table 2 sweep,
    each at the script's default schedule (no action repeat of its own) on the `new` vectors, the env its cell runs."""
    import tomllib

    from tools.family_references import TABLE2

    with open(os.path.join(os.path.dirname(__file__), "..", "sweeps", "metaworld_table2.toml"), "rb") as f:
        cells = tomllib.load(f)["cells"]
    for cell, module, env_id, flags in TABLE2:
        assert module is rm and cell in cells and flags == {"task_set": "new"}
        assert env_id in cells[cell]["flags"] or env_id == "metaworld/push"  # push is the spec's common env

@pytest.mark.slow
def test_eval_actions_scores_a_checkpoint_with_each_evaluation_action(tmp_path):
    """tools/eval_actions.py on a tiny run: one row per evaluation action, the checkpoint's update count, the same
    numbers on a second call (same episode seeds and sample streams); a folder without a run is one line."""
    run_script("rama_dreamer.py", "--env-id", "dmc/cartpole-balance", "--obs-type", "state", *TINY,
               "--run-dir", str(tmp_path / "runs"))
    first = run_script("tools/eval_actions.py", str(tmp_path / "runs"), "--episodes", "2").stdout
    lines = first.strip().splitlines()
    assert "checkpoint after 4 updates, 2 episodes per action" in lines[0]  # 3 episodes of 100: 2 rounds of 2
    assert [line.split(" | ")[0] for line in lines[3:]] == ["| sample-mode", "| mean", "| explore"]
    assert all(line.endswith("| – |") for line in lines[3:])  # cartpole reports no success
    assert run_script("tools/eval_actions.py", str(tmp_path / "runs"), "--episodes", "2").stdout == first
    bad = run_script("tools/eval_actions.py", str(tmp_path), check=False)
    assert bad.returncode != 0 and bad.stderr.strip() == f"error: {tmp_path}: no run folder with checkpoint.pt"
