"""The critic's guards and what tells its failures apart: --reward-scale, --slow-target and the imagination
diagnostics (imagine/*), in both scripts (their shared sections are one text)."""
import glob
import json
import os

import numpy as np
import pytest
import torch

import rama_dreamer as rd
import rama_metaworld as rmw
from helpers import TINY, run_script, synthetic_replay

SMALL = dict(obs_type="state", deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8, horizon=3, free_nats=0.0,
             obs_std=1.0, batch_size=2, seq_len=4)


def _batch():
    rng = np.random.default_rng(0)
    return rd.to_torch(synthetic_replay((5,), 2, episodes=1, length=12, rng=rng).sample(2, 4, rng), "cpu")


def _step(agent, batch, args, seed=0):
    torch.manual_seed(seed)  # the same imagined actions in both calls
    return {k: float(v.detach()) for k, v in rd.train_step(agent, batch, args)["metrics"].items()}


def test_reward_scale_is_the_same_step_as_scaled_rewards():
    """--reward-scale s on rewards r is exactly the update the agent makes on rewards s·r with scale 1."""
    scaled_args, plain_args = rd.Args(reward_scale=0.1, **SMALL), rd.Args(**SMALL)
    torch.manual_seed(3)
    first = rd.Agent((5,), 2, scaled_args)
    second = rd.Agent((5,), 2, plain_args)
    second.load_state_dict(first.state_dict())
    batch = _batch()
    got = _step(first, batch, scaled_args)
    expected = _step(second, {**batch, "reward": batch["reward"] * 0.1}, plain_args)
    assert got == pytest.approx(expected, rel=1e-6, abs=1e-6)
    assert got != pytest.approx(_step(second, batch, plain_args), rel=1e-3)  # the scale did change the update


def test_slow_target_bootstraps_from_its_copy_until_synced():
    """With --slow-target the λ-returns (so the actor's loss) come from the copy, the value learns towards them, and
    the copy moves only when sync_slow_target says so."""
    target_args, plain_args = rd.Args(slow_target=True, **SMALL), rd.Args(**SMALL)
    torch.manual_seed(4)
    agent = rd.Agent((5,), 2, target_args)
    twin = rd.Agent((5,), 2, plain_args)  # its value is agent's target: the same returns
    twin.load_state_dict({k: v for k, v in agent.state_dict().items() if not k.startswith("value_target.")})
    assert not any(p.requires_grad for p in agent.value_target.parameters())
    with torch.no_grad():  # the value drifts away from its target
        agent.value.out.bias.add_(50.0)
    copy = {k: v.clone() for k, v in agent.value_target.state_dict().items()}
    batch = _batch()
    got, expected = _step(agent, batch, target_args), _step(twin, batch, plain_args)
    assert got["losses/actor"] == pytest.approx(expected["losses/actor"], rel=1e-5)
    assert got["charts/imagined_return"] == pytest.approx(expected["charts/imagined_return"], rel=1e-5)
    assert got["losses/value"] > expected["losses/value"] + 100  # fitted from 50 away
    assert all(torch.equal(v, copy[k]) for k, v in agent.value_target.state_dict().items())  # no gradient step
    rd.sync_slow_target(agent, updates=150, every=100)  # not a multiple: nothing moves
    assert all(torch.equal(v, copy[k]) for k, v in agent.value_target.state_dict().items())
    rd.sync_slow_target(agent, updates=200, every=100)
    for k, v in agent.value_target.state_dict().items():
        assert torch.equal(v, agent.value.state_dict()[k])
    assert rd.Agent((5,), 2, plain_args).value_target is None  # off by default: Dreamer v1


def test_imagination_diagnostics_hand_case():
    actor = rd.Actor(feat_size=6, action_size=2, units=8, init_std=5.0, min_std=1e-4)
    with torch.no_grad():  # a zero output layer: pre-tanh std softplus(softplus^-1(5)) + 1e-4
        actor.net.out.weight.zero_()
        actor.net.out.bias.zero_()
    start = {"stoch": torch.zeros(3, 2), "deter": torch.zeros(3, 4)}
    reward = torch.tensor([[1.0, 3.0], [2.0, 6.0]])  # (H=2, N=2)
    value = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    actions = torch.tensor([[[0.995, 0.2], [-1.0, 0.0]], [[0.5, 0.5], [0.1, -0.2]]])  # (H, N, A): 2 of 8 saturated
    got = {k: float(v) for k, v in rd.imagination_diagnostics(actor, start, actions, reward, value).items()}
    assert got == pytest.approx({"imagine/reward_mean": 3.0, "imagine/reward_max": 6.0, "imagine/value_first": 1.5,
                                 "imagine/value_last": 3.5, "imagine/actor_std": 5.0001,
                                 "imagine/saturated_actions": 0.25}, rel=1e-5)


def test_defaults_keep_dreamer_v1():
    for module in (rd, rmw):
        args = module.Args()
        assert not args.slow_target and args.slow_target_every == 100 and args.reward_scale == 1.0


@pytest.mark.slow
def test_metaworld_run_with_both_guards_logs_raw_returns(tmp_path):
    """A few-step run with both guards: episodes on disk and the logged returns keep the raw rewards, and every round
    logs the diagnostics."""
    run_script("rama_metaworld.py", "--env-id", "metaworld/drawer-close", "--obs-type", "state", "--slow-target",
               "--slow-target-every", "2", "--reward-scale", "0.1", "--run-dir", str(tmp_path), *TINY)
    (run_path,) = glob.glob(os.path.join(tmp_path, "*"))
    with open(os.path.join(run_path, "metrics.jsonl")) as f:
        rows = [json.loads(line) for line in f]
    logged = [r["charts/episodic_return"] for r in rows if "charts/episodic_return" in r]
    stored = [float(np.load(p)["reward"].sum()) for p in sorted(glob.glob(os.path.join(run_path, "episodes", "*.npz")))]
    assert logged == pytest.approx(stored, rel=1e-4) and max(stored) > 0
    update_rows = [r for r in rows if "losses/value" in r]
    assert update_rows and all({"imagine/reward_max", "imagine/value_first", "imagine/value_last",
                                "imagine/actor_std", "imagine/saturated_actions"} <= set(r) for r in update_rows)


def test_critic_check_by_hand(tmp_path):
    """tools/critic_check.py on a made-up run: repeat 2, scale 0.1, γ 0.99 -> one step pays at most 2, the bound
    is 200. Values at the first imagined step 100, 300, 250, 150: peak 1.5, second half (250, 150) 1.0. Success
    0, 1, 0, 1, 1 after one prefill episode: the agent's 4 have one failure after the first success; the last 10
    (all 5) solved 3 of 5."""
    import sys

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tools"))
    import critic_check

    run = tmp_path / "exp" / "cell__dreamer__s1"
    run.mkdir(parents=True)
    (run / "args.json").write_text(json.dumps({"action_repeat": 2, "reward_scale": 0.1, "gamma": 0.99}))
    rows = [{"step": 500 * i, "imagine/value_first": v, "imagine/reward_max": m, "losses/actor_grad_norm": g}
            for i, (v, m, g) in enumerate([(100, 2.0, 1), (300, 3.0, 50), (250, 2.5, 2), (150, 1.0, 3)])]
    rows += [{"step": 500 * i, "charts/success_rate": s} for i, s in enumerate([0, 1, 0, 1, 1])]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    got = critic_check.check_run(str(run))
    assert got["bound"] == pytest.approx(200.0)
    assert got["value"] == pytest.approx(1.5) and got["late"] == pytest.approx(1.0)
    assert got["reward"] == pytest.approx(1.5) and got["grad"] == 50
    assert (got["failed"], got["episodes"], got["last10"]) == (1, 4, pytest.approx(0.6))
    assert "| cell__dreamer__s1 | 200 | 1.50 | 1.00 | 1.50 | 50 | 1 of 4 | 0.6 |" in critic_check.table([got])
    # the cell's row: a second seed that never solved and one that solved all of its 10 (value peak 0.8, grad 7)
    never = {**got, "run": "cell__dreamer__s2", "solved": False, "failed": 4, "episodes": 4, "last10": 0.0, "grad": 0}
    clean = {**got, "run": "cell__dreamer__s3", "failed": 0, "episodes": 9, "last10": 1.0, "value": 0.8, "grad": 7}
    assert "| cell | 3 | 1 | 1 of 13 | 1 of 3 | 0.80-1.50 | 50 |" in critic_check.cell_table([got, never, clean])


def test_truncated_normal_log_prob_hand_case():
    """log p(x) = log φ(z) − log σ − log(Φ(β) − Φ(α)); at loc 0, σ 1, x 0: −½ ln 2π − ln(Φ(1) − Φ(−1)) =
    −0.918939 − ln 0.682689 = −0.537223. Equal in both scripts."""
    for module in (rd, rmw):
        dist = module.TruncatedNormal(torch.tensor([0.0, 0.5]), torch.tensor([1.0, 0.1]))
        log_p = dist.log_prob(torch.tensor([0.0, 0.5]))
        assert log_p[0].item() == pytest.approx(-0.537223, abs=1e-5)
        # σ 0.1 at the centre, bounds 5 and 15 σ away: the untruncated density, −0.918939 − ln 0.1 = 1.383646
        assert log_p[1].item() == pytest.approx(1.383646, abs=1e-4)


def test_truncated_normal_samples_stay_in_bounds_with_the_truncated_mean():
    """Samples lie in [−1 + 1e-6, 1 − 1e-6], and their mean is the truncated mean: loc 0.9, σ 0.5 gives
    0.9 + 0.5 (φ(−3.8) − φ(0.2)) / (Φ(0.2) − Φ(−3.8)) = 0.9 + 0.5 (0.000292 − 0.391043) / (0.579260 − 0.000072) = 0.562674."""
    torch.manual_seed(0)
    dist = rmw.TruncatedNormal(torch.full((200_000,), 0.9), torch.full((200_000,), 0.5))
    sample = dist.sample()
    assert sample.min() >= -1 + 1e-6 - 1e-7 and sample.max() <= 1 - 1e-6 + 1e-7
    assert sample.mean().item() == pytest.approx(0.562674, abs=3e-3)


def test_truncated_normal_rsample_gradient_is_the_inverse_cdf_derivative():
    """The same uniform draw (the same seed) at loc and loc + h: the finite difference of the samples equals the
    autograd gradient, so the actor gets the gradient of the return through its truncated samples."""
    loc, scale, h = torch.tensor([0.3, -0.8], requires_grad=True), torch.tensor([0.4, 0.2]), 1e-3
    torch.manual_seed(5)
    sample = rmw.TruncatedNormal(loc, scale).rsample()
    sample.sum().backward()
    with torch.no_grad():
        torch.manual_seed(5)
        up = rmw.TruncatedNormal(loc + h, scale).rsample()
        torch.manual_seed(5)
        down = rmw.TruncatedNormal(loc - h, scale).rsample()
    assert loc.grad.numpy() == pytest.approx(((up - down) / (2 * h)).numpy(), rel=1e-2)
    assert (loc.grad > 0).all()


def test_trunc_normal_actor_mode_std_and_default():
    """--actor-dist trunc_normal: the mode is tanh of the mean output, the std 2 sigmoid(x / 2) + min in (min, 2 + min);
    Dreamer v1's tanh-normal stays the default in both scripts."""
    torch.manual_seed(0)
    actor = rmw.Actor(6, 3, 8, min_std=0.1, dist="trunc_normal")
    feat = torch.randn(4, 6)
    mean, raw_std = actor.net(feat).chunk(2, -1)
    assert torch.allclose(actor.mode(feat), torch.tanh(mean))
    assert torch.allclose(actor.std(feat), 2 * torch.sigmoid(raw_std / 2) + 0.1)
    assert rd.Args().actor_dist == rmw.Args().actor_dist == "tanh_normal"


@pytest.mark.slow
@pytest.mark.parametrize("script, env", [("rama_dreamer.py", "dmc/cartpole-balance"),
                                         ("rama_metaworld.py", "metaworld/drawer-close")])
def test_trunc_normal_actor_runs(tmp_path, script, env):
    """A few-step run of each script with the authors' actor: the actions it stored stay in [−1, 1] and it logs
    the actor's std."""
    run_script(script, "--env-id", env, "--obs-type", "state", "--actor-dist", "trunc_normal", "--actor-min-std",
               "0.1", "--expl-noise", "0", "--run-dir", str(tmp_path), *TINY)
    (run_path,) = glob.glob(os.path.join(tmp_path, "*"))
    actions = np.concatenate([np.load(p)["action"] for p in glob.glob(os.path.join(run_path, "episodes", "*.npz"))])
    assert np.abs(actions).max() <= 1.0
    with open(os.path.join(run_path, "metrics.jsonl")) as f:
        assert any("imagine/actor_std" in json.loads(line) for line in f)


def test_metaworld_defaults_are_the_authors_schedule():
    """Meta-World runs the authors' schedule (docs/deviations.md#metaworld-protocol), with raw rewards; DeepMind
    Control keeps the paper's: action repeat 2, one prefill episode, C = 100."""
    metaworld, dmc = rmw.Args(), rd.Args()
    assert (metaworld.action_repeat, metaworld.prefill_episodes, metaworld.updates_per_episode) == (1, 10, 50)
    assert (dmc.action_repeat, dmc.prefill_episodes, dmc.updates_per_episode) == (2, 1, 100)
    assert metaworld.reward_scale == dmc.reward_scale == 1.0 and metaworld.actor_dist == "tanh_normal"
