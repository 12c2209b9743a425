"""RAMa: the addressing math (Eqs. 1-3), batch mixing and masking, prior folders, and runs of every method."""
import dataclasses
import glob
import json
import os

import numpy as np
import pytest
import torch

import rama_dreamer as rd
from helpers import TINY, run_script, synthetic_replay

SMALL = dict(deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8, horizon=3, free_nats=3.0, obs_std=1.0,
             batch_size=4, seq_len=5, address_units=8, address_cnn_depth=2, address_batch=6)


def test_straight_through_selects_exactly_and_passes_gradients():
    torch.manual_seed(0)
    logits = torch.randn(3, 5, requires_grad=True)
    chunks = torch.randn(5, 4, 2)  # m=5 chunks of T=4 steps
    one_hot, index = rd.straight_through_sample(logits)
    selected = rd.select_chunks(one_hot, chunks)
    assert torch.equal(selected, chunks[index])  # forward pass: exactly M_j, bit for bit
    assert torch.equal(one_hot.detach(), torch.nn.functional.one_hot(index, 5).float())
    selected.sum().backward()
    # the gradient is that of the probabilities: d/dlogits of Σ_j p_j s_j, with s_j = sum of chunk j
    probs = logits.detach().softmax(-1)
    s = chunks.sum((1, 2))
    expected = probs * (s[None] - (probs * s[None]).sum(-1, keepdim=True))
    assert torch.allclose(logits.grad, expected, atol=1e-5)


def test_reinforce_sign_and_baseline():
    logits = torch.zeros(2, 3, requires_grad=True)
    index = torch.tensor([0, 2])
    advantage = torch.tensor([1.0, -1.0])
    loss = rd.reinforce_loss(logits, index, advantage, standardize=False)
    # loss = -mean(A log q) with q = 1/3: -(1*log(1/3) - 1*log(1/3))/2 = 0
    assert loss.item() == pytest.approx(0.0, abs=1e-6)
    loss.backward()
    # a gradient step (logits -= grad) raises q of the pick with A>0 and lowers q of the pick with A<0
    stepped = (logits - logits.grad).softmax(-1)
    assert stepped[0, 0] > 1 / 3 and stepped[1, 2] < 1 / 3
    # hand value: row 0 picks 0 with A=2: -(2 * log(1/3)) / 2 (row 1 has A=0)
    loss = rd.reinforce_loss(torch.zeros(2, 3), index, torch.tensor([2.0, 0.0]), standardize=False)
    assert loss.item() == pytest.approx(np.log(3.0))


def test_reinforce_standardized_advantages_the_default():
    """--address-standardize (on by default, as the authors' code): A → (A − mean) / std over the batch, so the
    picks with A above the batch's mean gain probability and those below lose it, whatever A's sign."""
    assert rd.Args().address_standardize
    logits = torch.zeros(3, 3, requires_grad=True)
    index = torch.tensor([0, 1, 2])
    advantage = torch.tensor([1.0, 2.0, 3.0])  # all positive; standardised: (−1, 0, 1) (mean 2, sample std 1)
    loss = rd.reinforce_loss(logits, index, advantage, standardize=True)
    assert loss.item() == pytest.approx(0.0, abs=1e-6)  # −mean(Â log ⅓) with Σ Â = 0
    loss.backward()
    # d loss / d logit of row i's pick = −Â_i (1 − ⅓) / 3: row 0 +2/9, row 1 0, row 2 −2/9
    picked = logits.grad[torch.arange(3), index]
    assert torch.allclose(picked, torch.tensor([2 / 9, 0.0, -2 / 9]), atol=1e-6)
    stepped = (logits - logits.grad).softmax(-1)
    assert stepped[0, 0] < 1 / 3 and stepped[2, 2] > 1 / 3  # row 0's A = 1 > 0, yet below the mean: it loses
    # the raw advantages would have raised all three picks
    logits.grad = None
    rd.reinforce_loss(logits, index, advantage, standardize=False).backward()
    assert torch.all(logits.grad[torch.arange(3), index] < 0)
    # one row: nothing to standardise over (its std is undefined): the raw advantage is used
    single = rd.reinforce_loss(torch.zeros(1, 3), torch.tensor([0]), torch.tensor([2.0]), standardize=True)
    assert single.item() == pytest.approx(2.0 * np.log(3.0))


def test_rbrama_subtracts_the_predicted_reward_of_x(monkeypatch):
    args = rd.Args(obs_type="state", method="rbrama", address_standardize=False, **SMALL)
    agent = rd.Agent((3,), 2, args)
    addressing = rd.Addressing((3,), 2, args, "cpu")
    rng = np.random.default_rng(0)
    replay = synthetic_replay((3,), 2, 2, 20, rng)
    x, m = rd.to_torch(replay.sample(4, 5, rng), "cpu"), rd.to_torch(replay.sample(6, 5, rng), "cpu")
    x["obs"][:, 0, 0], m["obs"][:, 0, 0] = torch.tensor([1.0, 2.0, 3.0, 4.0]), torch.arange(6.0) * 10
    # a stand-in reward sum per chunk, read from the chunk itself: the same whether x and M_j share one filter pass
    monkeypatch.setattr(rd, "predicted_reward_sum", lambda wm, batch: batch["obs"][:, 0, 0])
    seen = {}
    real = rd.reinforce_loss

    def spy(logits, index, advantage, standardize):
        seen["index"], seen["advantage"] = index, advantage
        return real(logits, index, advantage, standardize)

    monkeypatch.setattr(rd, "reinforce_loss", spy)
    addressing.train(agent, x, m, args)
    expected = torch.arange(6.0)[seen["index"]] * 10 - torch.tensor([1.0, 2.0, 3.0, 4.0])  # Eq. 3
    assert torch.allclose(seen["advantage"], expected)


def test_stop_grad_on_fx():
    emb_x = torch.randn(2, 4, requires_grad=True)
    emb_m = torch.randn(3, 4, requires_grad=True)
    rd.address_logits(emb_x, emb_m, stop_grad_x=True).sum().backward()
    assert emb_x.grad is None and emb_m.grad is not None and emb_m.grad.abs().sum() > 0
    emb_x.grad = None
    rd.address_logits(emb_x, emb_m, stop_grad_x=False).sum().backward()
    assert emb_x.grad.abs().sum() > 0
    # default: on for the REINFORCE variants, off for VRAMa
    assert rd.Addressing((3,), 2, rd.Args(method="rrama", **SMALL), "cpu").stop_grad_x
    assert not rd.Addressing((3,), 2, rd.Args(method="vrama", **SMALL), "cpu").stop_grad_x


def test_frozen_x_net_keeps_f_of_x_still_while_phi_learns():
    rng = np.random.default_rng(0)
    replay = synthetic_replay((3,), 2, 2, 20, rng)
    x, m = rd.to_torch(replay.sample(4, 5, rng), "cpu"), rd.to_torch(replay.sample(6, 5, rng), "cpu")
    for x_net in ("shared", "frozen"):
        args = rd.Args(obs_type="state", method="rrama", address_x_net=x_net, **SMALL)
        agent = rd.Agent((3,), 2, args)
        torch.manual_seed(0)
        addressing = rd.Addressing((3,), 2, args, "cpu")
        assert (addressing.x_net is addressing.net) == (x_net == "shared")  # the paper: one f_φ for x and M_j
        x_before, m_before = addressing.embed_x(x).detach(), addressing.embed(m).detach()
        assert torch.equal(x_before, addressing.net(x["obs"], x["action"]).detach())  # a copy: the same start
        for _ in range(3):
            addressing.train(agent, x, m, args)
        assert not torch.allclose(addressing.embed(m), m_before)  # f(M_j) learned either way
        # under the stop-gradient the shared weights still move f(x); the frozen copy does not
        assert torch.equal(addressing.embed_x(x), x_before) == (x_net == "frozen")


def small_addressing(method: str):
    """Args, an agent and an Addressing at SMALL sizes over a 3-d state, with n = 4 chunks x and m = 6 chunks M_j."""
    args = rd.Args(obs_type="state", method=method, **SMALL)
    agent = rd.Agent((3,), 2, args)
    addressing = rd.Addressing((3,), 2, args, "cpu")
    rng = np.random.default_rng(0)
    replay = synthetic_replay((3,), 2, 2, 20, rng)
    x, m = rd.to_torch(replay.sample(4, 5, rng), "cpu"), rd.to_torch(replay.sample(6, 5, rng), "cpu")
    return args, agent, addressing, x, m


def test_vrama_gradient_reaches_phi_only():
    args, agent, addressing, x, m = small_addressing("vrama")
    agent_before = {k: v.clone() for k, v in agent.state_dict().items()}
    phi_before = {k: v.clone() for k, v in addressing.net.state_dict().items()}
    metrics = addressing.train(agent, x, m, args)
    assert metrics["addressing/grad_norm"] > 0
    assert all(torch.equal(v, agent_before[k]) for k, v in agent.state_dict().items())
    assert any(not torch.equal(v, phi_before[k]) for k, v in addressing.net.state_dict().items())
    assert all(p.grad is None for p in agent.parameters())


def test_pinned_gru_gates_pass_no_gradient_to_phi():
    # f_φ's GRU with every update gate at exactly 1 (sigmoid(100) in float32) keeps its zero start: every embedding
    # and logit is 0 whatever φ, so the step's gradient is exactly 0
    args, agent, addressing, x, m = small_addressing("rrama")
    units = addressing.net.gru.hidden_size
    with torch.no_grad():
        addressing.net.gru.bias_ih_l0[units:2 * units] = 100.0
    metrics = addressing.train(agent, x, m, args)
    assert metrics["addressing/grad_norm"] == 0
    assert metrics["addressing/entropy"].item() == pytest.approx(np.log(6))  # q uniform over the m = 6 chunks


def test_vrama_start_subset_is_the_full_loss_when_it_covers_every_start():
    args = rd.Args(obs_type="state", method="vrama", **SMALL)
    agent = rd.Agent((3,), 2, args)
    rng = np.random.default_rng(0)
    m = rd.to_torch(synthetic_replay((3,), 2, 2, 20, rng).sample(6, 5, rng), "cpu")
    logits = torch.zeros(4, 6, requires_grad=True)
    one_hot, _ = rd.straight_through_sample(logits)
    losses = []
    for starts in (0, 4 * 5, 7):  # all n·L, exactly n·L, a random 7 of them
        torch.manual_seed(0)
        losses.append(rd.vrama_loss(agent, one_hot, m, 3, 0.99, 0.95, starts))
    assert torch.equal(losses[0], losses[1])
    assert not torch.equal(losses[0], losses[2])
    (grad,) = torch.autograd.grad(losses[2], logits)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0  # φ still learns through a subset


@pytest.mark.parametrize("obs_shape", [(3,), (64, 64, 3)])
def test_vrama_selecting_embeddings_or_frames_is_the_same_forward_pass(obs_shape):
    """A one-hot row picks one chunk, so encoding the picked frames equals picking the encodings: the loss is the
    same. The straight-through gradients differ (pixel space against embedding space) but both reach the logits."""
    args = rd.Args(obs_type="pixels" if len(obs_shape) == 3 else "state", cnn_depth=2, **SMALL)
    agent = rd.Agent(obs_shape, 2, args)
    rng = np.random.default_rng(0)
    m = rd.to_torch(synthetic_replay(obs_shape, 2, 2, 20, rng).sample(6, 5, rng), "cpu")
    logits = torch.randn(4, 6, requires_grad=True)
    torch.manual_seed(1)
    one_hot, index = rd.straight_through_sample(logits)
    losses, grads = [], []
    for select in ("embeddings", "frames"):
        torch.manual_seed(0)
        losses.append(rd.vrama_loss(agent, one_hot, m, 3, 0.99, 0.95, select=select))
        grads.append(torch.autograd.grad(losses[-1], logits, retain_graph=True)[0])
    assert torch.allclose(losses[0], losses[1], rtol=1e-5, atol=1e-6)
    assert all(torch.isfinite(g).all() and g.abs().sum() > 0 for g in grads)
    assert not torch.allclose(grads[0], grads[1])
    assert all(p.grad is None for p in agent.parameters())


def test_address_layer_norm_keeps_the_gru_input_in_range():
    """Large unnormalised inputs (raw states): with the layer norm the GRU sees O(1) inputs; without it they scale
    with the inputs and saturate the GRU."""
    torch.manual_seed(0)
    obs, action = 100 * torch.randn(2, 5, 3), torch.randn(2, 5, 2)
    for layer_norm, bounded in ((True, True), (False, False)):
        net = rd.AddressNet((3,), 2, units=16, cnn_depth=2, layer_norm=layer_norm)
        gru_input = net.inp(torch.cat([net.encoder(obs), action], -1))  # (2, 5, 16)
        assert (gru_input.abs().max() < 5) == bounded
    assert not rd.Args().address_layer_norm  # off by default: the paper's f_φ


@pytest.mark.parametrize("obs_shape", [(3,), (64, 64, 3)])
def test_address_net_reads_actions_and_observations_not_rewards(obs_shape):
    """Section 4.2: f_φ consumes actions concatenated with observation embeddings. At the defaults the stored
    rewards of a chunk do not change its embedding; the actions and the observations do."""
    torch.manual_seed(0)
    args = rd.Args(**SMALL)
    assert not args.address_reward_input
    addressing = rd.Addressing(obs_shape, 2, args, "cpu")
    rng = np.random.default_rng(0)
    batch = rd.to_torch(synthetic_replay(obs_shape, 2, 2, 20, rng).sample(3, 5, rng), "cpu")
    emb = addressing.embed(batch)  # (3, units)
    for key, change in (("reward", 100.0), ("action", 0.5), ("obs", 0.5)):
        changed = {**batch, key: batch[key] + change}
        assert torch.equal(addressing.embed(changed), emb) == (key == "reward"), key
    # --address-reward-input: one more input column, and then the rewards do matter
    net = rd.AddressNet(obs_shape, 2, units=8, cnn_depth=2, reward_input=True)
    plain = rd.AddressNet(obs_shape, 2, units=8, cnn_depth=2)
    assert net.inp[0].in_features == plain.inp[0].in_features + 1
    assert not torch.equal(net(batch["obs"], batch["action"], batch["reward"]),
                           net(batch["obs"], batch["action"], batch["reward"] + 100.0))


def test_vrama_reduction_mean_and_sum(monkeypatch):
    """"mean" is Dreamer's γ^t-weighted mean over steps and starts; "sum" is Eq. 1's −Σ_t V_λ, mean over starts."""
    returns = torch.tensor([[1.0, 2.0], [3.0, 4.0]])  # (H-1=2 steps, N=2 starts)
    weights = torch.tensor([[1.0, 1.0], [0.5, 0.5]])
    monkeypatch.setattr(rd, "imagined_returns", lambda *a, **k: (returns, weights, None, None))
    monkeypatch.setattr(rd, "imagine", lambda *a: (None, None))
    args = rd.Args(obs_type="state", **SMALL)
    agent = rd.Agent((3,), 2, args)
    rng = np.random.default_rng(0)
    m = rd.to_torch(synthetic_replay((3,), 2, 2, 20, rng).sample(2, 5, rng), "cpu")
    one_hot = torch.eye(2)
    mean = rd.vrama_loss(agent, one_hot, m, 3, 0.99, 0.95, reduction="mean")
    total = rd.vrama_loss(agent, one_hot, m, 3, 0.99, 0.95, reduction="sum")
    assert mean.item() == pytest.approx(-(1 + 2 + 0.5 * 3 + 0.5 * 4) / 4)  # -1.625
    assert total.item() == pytest.approx(-((1 + 3) + (2 + 4)) / 2)  # -5
    assert rd.Args().vrama_reduction == "mean"


def test_reward_mask_zeroes_masked_chunks():
    args = rd.Args(obs_type="state", **SMALL)
    wm = rd.Agent((3,), 2, args).wm
    rng = np.random.default_rng(0)
    batch = rd.to_torch(synthetic_replay((3,), 2, 2, 20, rng).sample(4, 5, rng), "cpu")
    mask = torch.tensor([1.0, 1.0, 0.0, 0.0])
    torch.manual_seed(0)
    _, _, full = rd.world_model_loss(wm, batch, 3.0, 1.0, reward_mask=mask)
    # changing the rewards of the masked chunks changes nothing; changing a kept chunk's does
    changed = {**batch, "reward": batch["reward"].clone()}
    changed["reward"][2:] += 100.0
    torch.manual_seed(0)
    _, _, same = rd.world_model_loss(wm, changed, 3.0, 1.0, reward_mask=mask)
    assert same["losses/reward_loglik"].item() == pytest.approx(full["losses/reward_loglik"].item())
    changed["reward"][0] += 100.0
    torch.manual_seed(0)
    _, _, other = rd.world_model_loss(wm, changed, 3.0, 1.0, reward_mask=mask)
    assert other["losses/reward_loglik"].item() < full["losses/reward_loglik"].item() - 1.0
    # the masked mean equals the plain mean over the kept chunks
    loglik = rd.gaussian_loglik(torch.zeros(4, 5), batch["reward"], 0)
    assert rd.masked_mean(loglik, mask).item() == pytest.approx(loglik[:2].mean().item())


def test_model_mask_drops_chunks_from_every_term():
    """model_mask (B,) takes chunks out of the whole world-model loss (observations, rewards, KL), not only the
    reward term: what --no-wm-on-addressed's row rule relies on."""
    args = rd.Args(obs_type="state", **SMALL)
    wm = rd.Agent((3,), 2, args).wm
    rng = np.random.default_rng(0)
    batch = rd.to_torch(synthetic_replay((3,), 2, 2, 20, rng).sample(4, 5, rng), "cpu")
    mask = torch.tensor([1.0, 1.0, 0.0, 0.0])
    keys = ("losses/obs_loglik", "losses/reward_loglik", "losses/kl")

    def metrics(b, model_mask=mask):
        torch.manual_seed(0)  # the posterior samples: the same noise for every call
        return rd.world_model_loss(wm, b, 0.0, 1.0, model_mask=model_mask, obs_std=0.1)[2]

    full = metrics(batch)
    # the masked chunks' observations and rewards changed: no term moves with the mask, every term without it
    changed = {k: v.clone() for k, v in batch.items()}
    changed["obs"][2:] += 100.0
    changed["reward"][2:] += 100.0
    masked, unmasked = metrics(changed), (metrics(batch, None), metrics(changed, None))
    for key in keys:
        assert masked[key].item() == pytest.approx(full[key].item(), rel=1e-6), key
        assert abs(unmasked[1][key].item() - unmasked[0][key].item()) > 1e-3, key
    # a kept chunk's change moves every term
    changed["obs"][0] += 100.0
    changed["reward"][0] += 100.0
    other = metrics(changed)
    for key in keys:
        assert abs(other[key].item() - full[key].item()) > 1e-3, key


def test_batch_merge_keeps_beta_n_current_chunks():
    rng = np.random.default_rng(0)
    current, multitask = rd.Replay(), rd.Replay()
    for i in range(2):
        ep = {"obs": np.zeros((21, 3), np.float32), "action": np.zeros((21, 2), np.float32),
              "reward": np.zeros(21, np.float32), "terminal": np.zeros(21, bool), "task": "now"}
        current.add(ep)
        multitask.add({**ep, "obs": np.ones((21, 3), np.float32), "task": "before"})
    args = rd.Args(obs_type="state", method="uniform", address_prob=1.0, current_fraction=0.25,
                   **{**SMALL, "batch_size": 8})
    agent = rd.Agent((3,), 2, args)
    seen = {}
    real = rd.train_step

    def spy(agent, batch, args, reward_mask=None, model_mask=None, step_model=True):
        seen.update(batch=batch, reward_mask=reward_mask, model_mask=model_mask)
        return real(agent, batch, args, reward_mask, model_mask, step_model)

    rd.train_step = spy
    try:
        rd.update(agent, None, rd.to_torch(current.sample(8, 5, rng), "cpu"),
                  rd.plan_update(args, multitask, None, rng, "cpu", "now", 0), args)
        obs = seen["batch"]["obs"]
        assert obs.shape[0] == 8
        assert torch.all(obs[:2] == 0) and torch.all(obs[2:] == 1)  # β·n = 2 current rows, then 6 borrowed
        assert seen["reward_mask"].tolist() == [1.0] * 2 + [0.0] * 6  # other task's rewards are masked
        assert seen["model_mask"] is None
        args = rd.Args(**{**vars(args), "wm_on_addressed": False})
        rd.update(agent, None, rd.to_torch(current.sample(8, 5, rng), "cpu"),
                  rd.plan_update(args, multitask, None, rng, "cpu", "now", 0), args)
        assert seen["model_mask"].tolist() == [1.0] * 2 + [0.0] * 6
        args = rd.Args(**{**vars(args), "address_prob": 0.0})
        rd.update(agent, None, rd.to_torch(current.sample(8, 5, rng), "cpu"),
                  rd.plan_update(args, multitask, None, rng, "cpu", "now", 0), args)
        # not mixed: the same n rows and masks, all of them x's rows, every mask one (a fixed-shape update)
        assert torch.all(seen["batch"]["obs"] == 0) and seen["batch"]["obs"].shape[0] == 8
        assert seen["reward_mask"].tolist() == [1.0] * 8 and seen["model_mask"].tolist() == [1.0] * 8
    finally:
        rd.train_step = real


def _write_episodes(folder, n, obs_shape=(24,), action_size=6, task="walker-stand", returns=None):
    os.makedirs(folder, exist_ok=True)
    for i in range(n):
        reward = np.zeros(11, np.float32)
        reward[1] = returns[i] if returns else i
        ep = {"obs": np.zeros((11, *obs_shape), np.float32), "action": np.zeros((11, action_size), np.float32),
              "reward": reward, "terminal": np.zeros(11, bool), "task": np.asarray(task),
              "return": np.asarray(reward.sum())}
        rd.save_episode(folder, i, ep)


def test_prior_loading_filters_subsamples_and_refuses_bad_folders(tmp_path):
    _write_episodes(tmp_path / "run" / "episodes", 10)
    rng = np.random.default_rng(0)
    eps = rd.load_prior_episodes([str(tmp_path / "run")], 5.0, 3, (24,), 6, rng)
    assert len(eps) == 3 and all(float(e["reward"].sum()) >= 5 for e in eps)
    assert len(rd.load_prior_episodes([str(tmp_path / "run")], None, 1000, (24,), 6, rng)) == 10
    with pytest.raises(rd.UsageError, match="no such folder"):
        rd.load_prior_episodes([str(tmp_path / "missing")], None, 10, (24,), 6, rng)
    os.makedirs(tmp_path / "empty")
    with pytest.raises(rd.UsageError, match="empty.*no episode files"):
        rd.load_prior_episodes([str(tmp_path / "empty")], None, 10, (24,), 6, rng)
    with pytest.raises(rd.UsageError, match=r"000000-10\.npz.*do not match"):
        rd.load_prior_episodes([str(tmp_path / "run")], None, 10, (64, 64, 3), 6, rng)
    with pytest.raises(rd.UsageError, match="--prior-min-return"):
        rd.load_prior_episodes([str(tmp_path / "run")], 1e9, 10, (24,), 6, rng)


def run(*flags, check=True):
    return run_script("rama_dreamer.py", *flags, check=check)


def test_picks_metrics_compare_picked_chunks_with_the_candidates():
    replay = rd.Replay()
    for task, rewards in [("a", [0, 1, 2, 3, 4, 5]), ("b", [0, 10, 10, 10, 10, 10])]:
        replay.add({"obs": np.zeros((6, 3), np.float32), "action": np.zeros((6, 1), np.float32),
                    "reward": np.array(rewards, np.float32), "terminal": np.zeros(6, bool), "task": task})
    assert replay.chunk_rewards([0, 0, 1], [1, 3, 0], 2).tolist() == [3.0, 7.0, 10.0]
    addressing = rd.Addressing((3,), 1, rd.Args(obs_type="state", method="rrama", **SMALL), "cpu")
    addressing.candidates = (np.array([0, 0, 1]), np.array([0, 2, 3]))  # chunk rewards 1, 5, 20
    addressing.candidate_rewards = replay.chunk_rewards(*addressing.candidates, 2)  # as refresh() sets them
    picks = [(np.array([1, 1]), np.array([1, 2])), (np.array([0]), np.array([4]))]  # chunk rewards 20, 20 | 9
    m = rd.picks_metrics(picks, replay, addressing, updates=4, seq_len=2)
    assert m["addressing/mixed_batches"] == 0.5
    assert m["addressing/pick_fraction/a"] == pytest.approx(1 / 3)
    assert m["addressing/pick_fraction/b"] == pytest.approx(2 / 3)
    assert m["addressing/picked_return"] == pytest.approx((50 + 50 + 15) / 3)
    assert m["addressing/candidate_return"] == pytest.approx((15 + 15 + 50) / 3)
    assert m["addressing/picked_chunk_reward"] == pytest.approx((20 + 9) / 2)  # mean of per-update means
    assert m["addressing/candidate_chunk_reward"] == pytest.approx((1 + 5 + 20) / 3)
    assert not any(k.startswith("addressing/pick_source/") for k in m)  # one policy in M: no split to report
    # M of a scripted pusher's and random episodes (collect_expert_episodes tags them) beside the agent's own
    replay.episodes[1]["policy"] = "expert"
    mixed = rd.Replay()
    for episode, policy in [(replay.episodes[0], None), (replay.episodes[1], "expert"), (replay.episodes[1], "random")]:
        mixed.add({**episode, **({"policy": np.asarray(policy)} if policy else {})})
    m = rd.picks_metrics([(np.array([1, 1, 2]), np.array([0, 1, 2])), (np.array([0]), np.array([0]))], mixed, None,
                         updates=2, seq_len=2)
    assert m["addressing/pick_source/expert"] == 0.5 and m["addressing/pick_source/random"] == 0.25
    assert m["addressing/pick_source/agent"] == 0.25


def metric_keys(run_path):
    with open(os.path.join(run_path, "metrics.jsonl")) as f:
        return set().union(*(json.loads(line) for line in f))


@pytest.fixture(scope="module")
def prior_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("prior")
    run("--env-id", "dmc/walker-stand", "--run-dir", str(root), *TINY)
    return glob.glob(os.path.join(root, "*"))[0]


@pytest.mark.slow
@pytest.mark.parametrize("method", ["uniform", "vrama", "rrama", "rbrama"])
def test_every_method_runs_with_prior_dirs(tmp_path, prior_run, method):
    run("--env-id", "dmc/walker-walk", "--method", method, "--prior-dirs", prior_run, "--run-dir", str(tmp_path),
        *TINY, "--prior-min-return", "0")
    run_path = glob.glob(os.path.join(tmp_path, "*"))[0]
    keys = metric_keys(run_path)
    assert {"addressing/pick_fraction/walker-stand", "addressing/picked_return", "losses/world_model"} <= keys
    assert "addressing/picked_chunk_reward" in keys
    if method != "uniform":
        assert {"addressing/loss", "addressing/entropy", "addressing/refresh_seconds",
                "addressing/candidate_chunk_reward"} <= keys
    if method in ("rrama", "rbrama"):
        assert {"addressing/bandit_reward_q", "addressing/bandit_reward_uniform"} <= keys
        assert glob.glob(os.path.join(run_path, "addressing", "q_*.png"))


@pytest.mark.slow
@pytest.mark.parametrize("method", ["vrama", "rrama"])
def test_methods_run_without_prior_dirs(tmp_path, method):
    # the first task of a sequence: M holds only the current task's own experience
    run("--env-id", "dmc/walker-stand", "--method", method, "--run-dir", str(tmp_path), *TINY)
    keys = metric_keys(glob.glob(os.path.join(tmp_path, "*"))[0])
    assert "addressing/pick_fraction/walker-stand" in keys and "addressing/loss" in keys


@pytest.mark.slow
def test_frozen_x_net_is_saved_and_resumed(tmp_path, prior_run):
    args = ["--env-id", "dmc/walker-walk", "--method", "rrama", "--prior-dirs", prior_run, "--run-dir", str(tmp_path),
            *TINY, "--prior-min-return", "0", "--address-x-net", "frozen"]
    run(*args)
    run_path = glob.glob(os.path.join(tmp_path, "*"))[0]
    saved = torch.load(os.path.join(run_path, "address.pt"), weights_only=False)
    # f_φ trained; x_net is its initial weights, so the two differ
    assert any(not torch.equal(v, saved["x_net"][k]) for k, v in saved["net"].items())
    run("--resume", run_path, "--total-steps", "500")
    resumed = torch.load(os.path.join(run_path, "address.pt"), weights_only=False)
    assert all(torch.equal(v, saved["x_net"][k]) for k, v in resumed["x_net"].items())  # still the same copy
    assert any(not torch.equal(v, saved["net"][k]) for k, v in resumed["net"].items())  # f_φ learned on


@pytest.mark.slow
def test_two_task_sequence(tmp_path):
    run("--task-sequence", "walker-stand,walker-walk", "--method", "rrama", "--run-dir", str(tmp_path), *TINY,
        "--obs-type", "state")
    run_path = glob.glob(os.path.join(tmp_path, "*"))[0]
    assert os.path.exists(os.path.join(run_path, "address.pt"))
    first, second = os.path.join(run_path, "0_walker-stand"), os.path.join(run_path, "1_walker-walk")
    assert len(rd.list_episode_files(os.path.join(first, "episodes"))) == 3
    assert len(rd.list_episode_files(os.path.join(second, "episodes"))) == 3
    # the second task addresses the first task's episodes (M carried over)
    assert "addressing/pick_fraction/walker-stand" in metric_keys(second)


@pytest.mark.slow
def test_bad_prior_dirs_are_one_line_errors(tmp_path):
    proc = run("--method", "rrama", "--prior-dirs", str(tmp_path / "nope"), "--run-dir", str(tmp_path), *TINY,
               check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "--prior-dirs" in lines[0], proc.stderr
    proc = run("--method", "dreamer", "--prior-dirs", str(tmp_path), *TINY, check=False)
    assert proc.returncode == 2 and "--prior-dirs" in proc.stderr


# tools/addressing_offline.py: f_φ trained on a finished run's objective with its world model held fixed
def test_offline_score_by_hand():
    from tools.addressing_offline import score

    class Fixed:  # an addressing model with given embeddings: f(x) = 0 and 1 for the 2 rows, f(M_j) = ln 2, 0, 0
        candidate_embeddings = torch.tensor([[np.log(2)], [0.0], [0.0]])
        logit_scale = 1.0

        def refresh(self, multitask, seq_len, cap, rng):
            self.candidates = (np.array([0, 1, 2]), np.zeros(3, int))

        def embed_x(self, x):
            return torch.tensor([[0.0], [1.0]])

    candidates = (np.array([0, 1, 2]), np.array([10.0, 20.0, 60.0]), np.array([1.0, 2.0, 3.0]))
    out = score(Fixed(), None, None, candidates, num_prior=1, seq_len=5, cap=10)
    # logits (0, 0, 0) and (ln 2, 0, 0): q̂ = (1/3, 1/3, 1/3) and (1/2, 1/4, 1/4). E_q̂[stored] = 30 and
    # 5 + 5 + 15 = 25 against the uniform 30; predicted 2 and 0.5 + 0.5 + 0.75 against 2; the prior chunk (episode 0)
    # gets 1/3 and 1/2; entropies ln 3 and 1.5 ln 2 against ln 3
    assert out["stored"] == pytest.approx(27.5 - 30.0) and out["predicted"] == pytest.approx(1.875 - 2.0)
    assert out["prior_mass"] == pytest.approx(5 / 12)
    assert out["entropy"] == pytest.approx((np.log(3) + 1.5 * np.log(2)) / 2 / np.log(3))
    assert out["embedding_norm"] == pytest.approx(np.log(2) / 3)
    assert out["logit_sd"] == pytest.approx((0 + np.log(2) * np.sqrt(2) / 3) / 2)  # s.d. of (ln 2, 0, 0): ln 2·√2/3


def test_offline_pinned_gates():
    from tools.addressing_offline import pinned_gates

    torch.manual_seed(0)
    net = rd.AddressNet((3,), 2, units=4, cnn_depth=8)
    batch = {"obs": torch.randn(5, 6, 3), "action": torch.randn(5, 6, 2), "reward": torch.zeros(5, 6)}
    assert pinned_gates(net, batch) == 0.0  # at initialisation no gate is anywhere near 0 or 1
    with torch.no_grad():
        net.gru.bias_ih_l0[4:6] = 100.0  # the update gates of units 0 and 1: sigmoid(~100) is 1.0 in float32
        net.gru.bias_ih_l0[6:8] = -100.0  # units 2 and 3: 0.0
    assert pinned_gates(net, batch) == 1.0
    with torch.no_grad():
        net.gru.bias_ih_l0[4] = 0.0  # unit 0 free again: 3 of the 4 gates pinned at every step
    assert pinned_gates(net, batch) == 0.75
    # with z = 1 units 1 keeps its zero start to the end (the step is nn.GRU's own), and z = 0 takes the candidate
    out = net(batch["obs"], batch["action"])  # (5, 4): the GRU's last state
    assert torch.equal(out[:, 1], torch.zeros(5)) and (out[:, 2:].abs() > 0).all()


def test_offline_variants_scale_the_logits_and_freeze_the_x_embedding():
    from tools.addressing_offline import VariantAddressing

    args = rd.Args(obs_type="state", method="rrama", **SMALL)
    agent = rd.Agent((3,), 2, args)
    rng = np.random.default_rng(0)
    replay = synthetic_replay((3,), 2, 2, 20, rng)
    x, m = rd.to_torch(replay.sample(4, 5, rng), "cpu"), rd.to_torch(replay.sample(6, 5, rng), "cpu")
    torch.manual_seed(0)
    plain = VariantAddressing((3,), 2, args, "cpu", logit_scale=1.0)
    torch.manual_seed(0)
    scaled = VariantAddressing((3,), 2, args, "cpu", logit_scale=0.25)
    # the same weights: f(M_j) scaled by 1/4, f(x) as it was, so every logit f(x)ᵀ f(M_j) is a quarter
    assert torch.allclose(scaled.embed(m), 0.25 * plain.embed(m)) and torch.equal(scaled.embed_x(x), plain.embed_x(x))
    for frozen in (False, True):
        torch.manual_seed(0)
        x_net = "frozen" if frozen else "shared"
        addressing = VariantAddressing((3,), 2, dataclasses.replace(args, address_x_net=x_net), "cpu", logit_scale=1.0)
        x_before, m_before = addressing.embed_x(x).detach(), addressing.embed(m).detach()
        seen = []
        real_embed_x = addressing.embed_x
        addressing.embed_x = lambda batch: seen.append(batch is x) or real_embed_x(batch)
        for _ in range(3):
            addressing.train(agent, x, m, args)
        assert seen == [True] * 3  # train embedded x, and only x, through embed_x
        assert not torch.allclose(addressing.embed(m), m_before)  # φ learned
        # the stop-gradient stops the gradient, but the shared weights still move f(x); the frozen copy does not
        assert torch.equal(real_embed_x(x), x_before) == frozen


def test_offline_tool_loads_state_checkpoints_from_before_the_plain_mlp_encoder():
    from tools.addressing_offline import load_weights

    args = rd.Args(obs_type="state", **SMALL)
    saved = rd.Agent((5,), 2, args).state_dict()
    # before commit 6170a30 the state encoder and decoder were modules holding their layers in `.net`
    old = {k.replace("wm.encoder.", "wm.encoder.net.").replace("wm.decoder.", "wm.decoder.net."): v
           for k, v in saved.items()}
    assert old.keys() != saved.keys()
    agent = rd.Agent((5,), 2, args)
    load_weights(agent, old, "checkpoint.pt")
    assert all(torch.equal(v, saved[k]) for k, v in agent.state_dict().items())
    with pytest.raises(rd.UsageError, match="checkpoint.pt"):  # anything else is still one line naming the file
        load_weights(agent, {"nope": torch.zeros(1)}, "checkpoint.pt")


@pytest.mark.slow
def test_offline_tool_on_a_tiny_rrama_run(tmp_path, prior_run):
    run("--env-id", "dmc/walker-walk", "--method", "rrama", "--prior-dirs", prior_run, "--run-dir", str(tmp_path),
        *TINY, "--prior-min-return", "0")
    run_path = glob.glob(os.path.join(tmp_path, "*"))[0]
    out = tmp_path / "offline.json"
    proc = run_script("tools/addressing_offline.py", run_path, "--updates", "2", "--eval-every", "1", "--seeds", "0",
                      "1", "--eval-rows", "3", "--out", str(out))
    assert "| fresh | 2 |" in proc.stdout and "| run | 0 |" in proc.stdout
    result = json.loads(out.read_text())
    rows = result["rows"]
    assert len(rows) == 2 * 2 * 3  # starts x seeds x scorings (updates 0, 1, 2)
    assert result["method"] == "rrama" and 0 < result["prior_share"] < 1  # M: the prior's and the run's episodes
    run_start = [r for r in rows if r["start"] == "run" and r["update"] == 0]
    fresh_start = [r for r in rows if r["start"] == "fresh" and r["update"] == 0]
    assert run_start[0]["predicted"] == run_start[1]["predicted"]  # the run's own f_φ, before any update
    assert fresh_start[0]["predicted"] != fresh_start[1]["predicted"]  # two freshly drawn f_φ
    assert all(0 <= r["prior_mass"] <= 1 and 0 < r["entropy"] <= 1 + 1e-9 and 0 <= r["pinned"] <= 1 for r in rows)
    assert all(np.isnan(r["grad_norm"]) == (r["update"] == 0) for r in rows)  # nan before any update
    # a run without f_φ is one line naming it
    run("--env-id", "dmc/walker-walk", "--method", "uniform", "--prior-dirs", prior_run, "--run-dir",
        str(tmp_path / "u"), *TINY, "--prior-min-return", "0")
    proc = run_script("tools/addressing_offline.py", glob.glob(str(tmp_path / "u" / "*"))[0], check=False)
    assert proc.returncode == 2 and "has no f_φ" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    proc = run_script("tools/addressing_offline.py", str(tmp_path / "nope"), check=False)  # not a run folder
    assert proc.returncode == 2 and "no args.json" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
