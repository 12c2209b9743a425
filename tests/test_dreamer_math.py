"""Exact math of the Dreamer core on small hand-checked cases."""
import dataclasses
import json
import math
import os

import numpy as np
import pytest
import torch

import rama_dreamer as rd
from helpers import synthetic_replay


def test_lambda_return_hand_case():
    # H=3, one trajectory; worked by hand: next values [1.0, 1.5, 2.0], inputs r + γ(1-λ)v' = [1.45, 2.675, 3.9]
    # R2 = 3.9 + 0.45*2 = 4.8; R1 = 2.675 + 0.45*4.8 = 4.835; R0 = 1.45 + 0.45*4.835 = 3.62575
    reward = torch.tensor([[1.0], [2.0], [3.0]])
    value = torch.tensor([[0.5], [1.0], [1.5]])
    pcont = torch.full((3, 1), 0.9)
    returns = rd.lambda_return(reward, value, pcont, torch.tensor([2.0]), lam=0.5)
    assert torch.allclose(returns[:, 0], torch.tensor([3.62575, 4.835, 4.8]), atol=1e-5)


def test_lambda_return_limits():
    reward, value = torch.tensor([[1.0], [2.0]]), torch.tensor([[10.0], [20.0]])
    pcont, boot = torch.full((2, 1), 0.5), torch.tensor([40.0])
    # λ=1: discounted Monte-Carlo return with bootstrap: 1 + .5*(2 + .5*40) = 12 ; 2 + .5*40 = 22
    assert torch.allclose(rd.lambda_return(reward, value, pcont, boot, 1.0)[:, 0], torch.tensor([12.0, 22.0]))
    # λ=0: one-step TD targets: 1 + .5*20 = 11 ; 2 + .5*40 = 22
    assert torch.allclose(rd.lambda_return(reward, value, pcont, boot, 0.0)[:, 0], torch.tensor([11.0, 22.0]))


def _state(mean, std):
    mean, std = torch.tensor(mean, requires_grad=True), torch.tensor(std)
    return {"mean": mean, "std": std}


def test_kl_with_free_nats():
    # KL(N(0,2) || N(0,1)) per dim = log(1/2) + 4/2 - 1/2 = 1.5 - ln 2 ; two dims -> 3 - 2 ln 2 ≈ 1.6137
    post, prior = _state([[0.0, 0.0]], [[2.0, 2.0]]), _state([[0.0, 0.0]], [[1.0, 1.0]])
    expected = 3.0 - 2.0 * math.log(2.0)
    loss, value = rd.kl_with_free_nats(post, prior, free_nats=0.0)
    assert loss.item() == pytest.approx(expected, abs=1e-5) and value.item() == pytest.approx(expected, abs=1e-5)
    loss, value = rd.kl_with_free_nats(post, prior, free_nats=3.0)
    assert loss.item() == pytest.approx(3.0) and value.item() == pytest.approx(expected, abs=1e-5)
    # below the free nats, no gradient reaches the model; at 0 free nats it does. The means differ (0.5 against 0),
    # so that dKL/dμ_q = (μ_q − μ_p) / σ_p² = 0.5 per dim, averaged over the one (B, T) entry: a leaking clip would
    # show here. KL(N(0.5, 2) || N(0, 1)) per dim = 1.5 − ln 2 + 0.125 ≈ 0.932, both dims 1.864 < 3
    post, prior = _state([[0.5, 0.5]], [[2.0, 2.0]]), _state([[0.0, 0.0]], [[1.0, 1.0]])
    loss, value = rd.kl_with_free_nats(post, prior, free_nats=3.0)
    assert value.item() == pytest.approx(3.25 - 2.0 * math.log(2.0), abs=1e-5)
    assert loss.item() == pytest.approx(3.0)
    loss.backward()
    assert torch.equal(post["mean"].grad, torch.zeros(1, 2))
    post["mean"].grad = None
    rd.kl_with_free_nats(post, prior, free_nats=0.0)[0].backward()
    assert torch.allclose(post["mean"].grad, torch.full((1, 2), 0.5))
    # KL averages over (B, T) before the clip (Dreamer v1): one KL of 0 and one of 2*0.5 -> mean 0.5
    post, prior = _state([[0.0, 0.0], [1.0, 1.0]], [[1.0, 1.0]] * 2), _state([[0.0, 0.0]] * 2, [[1.0, 1.0]] * 2)
    assert rd.kl_with_free_nats(post, prior, 0.0)[0].item() == pytest.approx(0.5)


def test_tanh_normal_log_prob():
    out = torch.tensor([[0.7, -1.2, 0.3, -0.4]])  # two action dims: raw means (0.7, -1.2), raw stds (0.3, -0.4)
    dist = rd.tanh_normal(out, init_std=5.0, min_std=1e-4, mean_scale=5.0)
    y = torch.tensor([[0.3, -0.8]])
    expected = 0.0
    for raw_mean, raw_std, a in [(0.7, 0.3, 0.3), (-1.2, -0.4, -0.8)]:
        mean = 5.0 * math.tanh(raw_mean / 5.0)
        std = math.log1p(math.exp(raw_std + math.log(math.expm1(5.0)))) + 1e-4
        x = math.atanh(a)
        expected += -0.5 * ((x - mean) / std) ** 2 - math.log(std) - 0.5 * math.log(2 * math.pi) - math.log(1 - a * a)
    assert dist.log_prob(y).item() == pytest.approx(expected, abs=1e-4)
    sample = dist.rsample((1000,))
    assert sample.abs().max() <= 1.0
    # before training (raw std 0) the std equals init_std
    zero = rd.tanh_normal(torch.zeros(1, 2), 5.0, 0.0, 5.0)
    assert zero.base_dist.base_dist.stddev.item() == pytest.approx(5.0, rel=1e-5)


def _episode(length, task="t", offset=0):
    steps = np.arange(length + 1) + offset
    return {"obs": steps[:, None].astype(np.float32), "action": np.zeros((length + 1, 1), np.float32),
            "reward": steps.astype(np.float32), "terminal": np.zeros(length + 1, bool), "task": task}


def test_observe_is_the_step_by_step_filter_with_the_priors_after_the_loop():
    """observe runs the prior head once after the loop: its priors equal img_step's from each previous posterior (the
    same h_t and prior stats as a step-by-step filter), and each posterior is obs_step's from that h_t."""
    torch.manual_seed(0)
    rssm = rd.RSSM(action_size=2, embed_size=5, stoch_size=3, deter_size=4, hidden_size=6)
    embed, action = torch.randn(2, 4, 5), torch.randn(2, 4, 2)  # (B, T, E), (B, T, A)
    post, prior = rssm.observe(embed, action)
    assert set(prior) == {"mean", "std", "deter"} and prior["mean"].shape == (2, 4, 3)
    state = rssm.initial(2, "cpu")
    for t in range(4):
        step_prior = rssm.img_step(state, action[:, t])  # the prior as one imagined step computes it
        for k in ("mean", "std", "deter"):
            assert torch.allclose(prior[k][:, t], step_prior[k], atol=1e-6), (t, k)
        step_post = rssm.obs_step(step_prior["deter"], rssm.obs_embed(embed[:, t]))
        assert torch.allclose(post["mean"][:, t], step_post["mean"], atol=1e-6)
        assert torch.allclose(post["std"][:, t], step_post["std"], atol=1e-6)
        state = {k: post[k][:, t] for k in post}  # the next step starts from observe's own sample
    assert (prior["std"] > 0.1).all() and not torch.allclose(prior["mean"], post["mean"])


def test_replay_chunks_are_contiguous_and_uniform():
    replay = rd.Replay()
    for length, offset in [(9, 0), (19, 1000), (2, 5000)]:  # 10, 20 and 3 steps
        replay.add(_episode(length, offset=offset))
    seq_len = 5
    assert replay.num_chunks(seq_len) == 6 + 16 + 0
    rng = np.random.default_rng(0)
    batch = replay.sample(20000, seq_len, rng)
    assert batch["obs"].shape == (20000, seq_len, 1) and batch["reward"].shape == (20000, seq_len)
    first = batch["reward"][:, 0]
    assert np.all(np.diff(batch["reward"], axis=1) == 1)  # contiguous
    assert not np.any(first >= 5000)  # an episode shorter than L is never sampled
    # uniform over the 22 chunks: every start appears, each about 1/22 of the time
    starts, counts = np.unique(first, return_counts=True)
    assert len(starts) == 22
    assert np.all(np.abs(counts / 20000 - 1 / 22) < 0.01)
    # the last chunk of an episode ends at its last step
    assert first.max() == 1000 + 19 - seq_len + 1


def test_episode_write_is_atomic(tmp_path, monkeypatch):
    episode = _episode(4)
    path = rd.save_episode(str(tmp_path), 3, episode)
    assert os.path.basename(path) == "000003-4.npz"
    loaded = rd.load_episode(path)
    for key in ("obs", "action", "reward", "terminal"):
        assert np.array_equal(loaded[key], episode[key])
    assert loaded["task"] == "t"
    assert os.listdir(tmp_path) == ["000003-4.npz"]  # no temp file left behind

    def crash(f, **arrays):
        f.write(b"half an episode")
        raise KeyboardInterrupt("killed mid-write")

    monkeypatch.setattr(rd.np, "savez_compressed", crash)
    with pytest.raises(KeyboardInterrupt):
        rd.save_episode(str(tmp_path), 4, episode)
    # the interrupted episode never appears under its final name, and listing ignores the temp file
    assert [os.path.basename(p) for p in rd.list_episode_files(str(tmp_path))] == ["000003-4.npz"]


def test_load_episode_names_bad_file(tmp_path):
    bad = tmp_path / "000000-10.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(rd.UsageError, match="000000-10.npz"):
        rd.load_episode(str(bad))


@pytest.mark.parametrize("shape", [(64, 64, 3), (64, 96, 3)])
def test_encoder_and_decoder_shapes(shape):
    encoder = rd.ConvEncoder(shape, depth=4)
    decoder = rd.ConvDecoder(10, shape, depth=4)
    obs = torch.zeros(2, 3, shape[2], shape[0], shape[1])
    assert encoder(obs).shape == (2, 3, encoder.embed_size)
    assert decoder(torch.zeros(2, 3, 10)).shape == obs.shape  # the kitchen: (3, 64, 96)


def test_dreamer_v1_parameter_counts():
    """Depth 32, 230 feature units (stoch 30 + deter 200), walker's 6 actions: Dreamer v1's counts, by hand.
    Decoder: dense 230->1024 (236,544); convT 1024->128 k5 (3,276,928); 128->64 k5 (204,864); 64->32 k6 (73,760);
    32->3 k6 (3,459). Encoder: convs 3->32, 32->64, 64->128, 128->256, k4 (1,568 + 32,832 + 131,200 + 524,544).
    RSSM: dense 36->200 (7,400); GRU 200->200 (241,200); dense 200->200 and 200->60 on both the prior side
    (40,200 + 12,060) and the posterior side ([h, e] 1224->200: 245,000, then 12,060)."""
    count = lambda module: sum(p.numel() for p in module.parameters())  # noqa: E731
    assert count(rd.ConvDecoder(230, (64, 64, 3), 32)) == 3_795_555
    assert count(rd.ConvEncoder((64, 64, 3), 32)) == 690_144
    assert count(rd.RSSM(6, 1024)) == 557_920
    # the kitchen's 96-pixel width changes only the last layer: kernel 6x9, stride 2x3 (32*3*54 + 3 = 5,187 params)
    assert count(rd.ConvDecoder(230, (64, 96, 3), 32)) == 3_795_555 - 3_459 + 5_187
    assert rd.decoder_last_layer(64) == (6, 2) and rd.decoder_last_layer(96) == (9, 3)
    with pytest.raises(rd.UsageError, match="--image-size"):
        rd.check_args(rd.resolve_defaults(rd.Args(image_size=24)))


def test_gaussian_loglik():
    mean, target = torch.zeros(1, 1, 2), torch.tensor([[[1.0, 2.0]]])
    expected = -0.5 * (1 + 4) - math.log(2 * math.pi)
    assert rd.gaussian_loglik(mean, target, 1).item() == pytest.approx(expected)
    # std 0.5: squared errors count 4x, and each dim's normaliser gains -log 0.5
    expected = -0.5 * (4 + 16) - 2 * math.log(0.5) - math.log(2 * math.pi)
    assert rd.gaussian_loglik(mean, target, 1, std=0.5).item() == pytest.approx(expected)


def test_obs_std_default_depends_on_the_observations():
    """1 for pixels (the paper's unit-variance decoder); 0.1 for a state vector, whose few dims would otherwise be
    cheaper to blur than to encode; the decoder term of the world-model loss uses it."""
    assert rd.resolve_defaults(rd.Args()).obs_std == 1.0
    assert rd.resolve_defaults(rd.Args(obs_type="state")).obs_std == 0.1
    assert rd.resolve_defaults(rd.Args(obs_type="state", obs_std=0.5)).obs_std == 0.5
    args = rd.Args(deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8, batch_size=2, seq_len=4)
    torch.manual_seed(0)
    wm = rd.WorldModel((5,), 2, args)
    rng = np.random.default_rng(0)
    batch = rd.to_torch(synthetic_replay((5,), 2, 1, 10, rng).sample(2, 4, rng), "cpu")
    torch.manual_seed(1)  # the same posterior samples in both calls
    unit = rd.world_model_loss(wm, batch, 0.0, 1.0, obs_std=1.0)[2]["losses/obs_loglik"]
    torch.manual_seed(1)
    tenth = rd.world_model_loss(wm, batch, 0.0, 1.0, obs_std=0.1)[2]["losses/obs_loglik"]
    # same squared error e: unit = -e/2 - 5c, tenth = -100 e/2 - 5 log 0.1 - 5c (c = log 2π / 2, 5 dims)
    squared = -2 * (unit + 5 * 0.5 * math.log(2 * math.pi))
    expected = -50 * squared - 5 * math.log(0.1) - 5 * 0.5 * math.log(2 * math.pi)
    assert tenth.item() == pytest.approx(expected.item(), rel=1e-5)


def test_actor_loss_trains_only_the_actor():
    args = rd.Args(deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8, horizon=3, free_nats=3.0, obs_std=1.0,
                   batch_size=2, seq_len=4)
    agent = rd.Agent((5,), 2, args)
    rng = np.random.default_rng(0)
    replay = synthetic_replay((5,), 2, episodes=1, length=10, rng=rng)
    batch = rd.to_torch(replay.sample(2, 4, rng), "cpu")
    before = {k: v.clone() for k, v in agent.state_dict().items()}
    # with zero model and value learning rates, only the actor may move
    for opt in (agent.model_opt, agent.value_opt):
        opt.param_groups[0]["lr"] = 0.0
    rd.train_step(agent, batch, args)
    for key, value in agent.state_dict().items():
        changed = not torch.equal(value, before[key])
        assert changed == key.startswith("actor."), key
    assert all(p.requires_grad for p in agent.parameters())  # Freeze restored gradients


def test_free_nats_default_depends_on_the_observations():
    """3 nats for pixels (the paper); 0 for a low-dimensional state, whose KL sits below 3 nats: the clamp would leave
    the prior without gradient and the imagined rollouts blind to the actions."""
    assert rd.resolve_defaults(rd.Args()).free_nats == 3.0
    assert rd.resolve_defaults(rd.Args(obs_type="state")).free_nats == 0.0
    assert rd.resolve_defaults(rd.Args(obs_type="state", free_nats=1.5)).free_nats == 1.5
    post, prior = _state([[0.5]], [[2.0]]), _state([[0.0]], [[1.0]])  # KL ≈ 0.93 nats, below 3
    (clamped,) = torch.autograd.grad(rd.kl_with_free_nats(post, prior, free_nats=3.0)[0], post["mean"])
    (free,) = torch.autograd.grad(rd.kl_with_free_nats(post, prior, free_nats=0.0)[0], post["mean"])
    assert torch.all(clamped == 0) and torch.all(free != 0)


def test_resume_of_a_run_saved_by_an_older_version_is_refused(tmp_path):
    """An args.json without a flag of today's script would get that flag's default, which the run may not have been
    trained with (--obs-std was 1 before it existed, 0.1 now for state): one line naming the flag instead."""
    saved = dataclasses.asdict(rd.resolve_defaults(rd.Args(obs_type="state")))
    (tmp_path / "args.json").write_text(json.dumps(saved))
    args, _ = rd.resolve_run(rd.Args(resume=str(tmp_path)), {"resume"})
    assert args.obs_type == "state" and args.obs_std == 0.1
    del saved["address_x_net"]  # a flag whose absence means its value: before it, f(x) was always f_φ's own
    (tmp_path / "args.json").write_text(json.dumps(saved))
    args, _ = rd.resolve_run(rd.Args(resume=str(tmp_path)), {"resume"})
    assert args.address_x_net == "shared" and rd.ADDED_FLAGS["address_x_net"] == "shared"
    # every flag added since resumes as the one behaviour there was: the authors' configuration's flags their
    # defaults; Dreamer v1's initialisation and evaluation action, made the defaults later, torch's and the mean
    changed = {"init": ("keras", "torch"), "eval_action": ("sample-mode", "mean")}
    assert all(getattr(rd.Args(), name) == value for name, value in rd.ADDED_FLAGS.items() if name not in changed)
    assert all((getattr(rd.Args(), name), rd.ADDED_FLAGS[name]) == pair for name, pair in changed.items())
    for name in changed:
        del saved[name]
    (tmp_path / "args.json").write_text(json.dumps(saved))
    args, _ = rd.resolve_run(rd.Args(resume=str(tmp_path)), {"resume"})
    assert (args.init, args.eval_action) == ("torch", "mean")
    del saved["obs_std"]  # an args.json written before the flag existed
    (tmp_path / "args.json").write_text(json.dumps(saved))
    with pytest.raises(rd.UsageError, match=r"args.json: saved by an older version .*--obs-std"):
        rd.resolve_run(rd.Args(resume=str(tmp_path)), {"resume"})


def test_keras_init_is_dreamer_v1s():
    """--init keras (the default): Glorot-uniform weights (bound sqrt(6 / (fan_in + fan_out))), zero biases,
    orthogonal recurrent GRU weights, and v1's one bound over [h, e] for the split posterior layer; --init torch keeps
    torch's defaults (non-zero biases)."""
    args = rd.resolve_defaults(rd.Args(obs_type="state", deter_size=200, stoch_size=30, hidden_size=200,
                                       mlp_units=400))
    torch.manual_seed(0)
    agent = rd.Agent((24,), 6, args)
    layers = [m for m in agent.modules() if isinstance(m, torch.nn.Linear) and m.weight.shape == (400, 400)]
    assert len(layers) >= 6  # the hidden layers of the reward, value and actor MLPs
    for layer in layers:  # 400 x 400: bound sqrt(6 / 800) = 0.0866, std of U(-b, b) = b / sqrt(3) = 0.05
        assert layer.weight.abs().max() <= math.sqrt(6 / 800) + 1e-7
        assert layer.weight.std().item() == pytest.approx(math.sqrt(6 / 800) / math.sqrt(3), rel=0.02)
        assert torch.all(layer.bias == 0)
    gru = agent.wm.rssm.gru  # weight_hh (3H, H) with orthonormal columns
    gram = gru.weight_hh.T @ gru.weight_hh
    assert torch.allclose(gram, torch.eye(200), atol=1e-5) and torch.all(gru.bias_hh == 0)
    split = max(agent.wm.rssm.obs_deter.weight.abs().max(), agent.wm.rssm.obs_embed.weight.abs().max())
    bound = math.sqrt(6 / (200 + agent.wm.encoder.embed_size + 200))  # v1: Dense(h ++ e -> 200)
    assert bound * 0.95 < split <= bound
    torch_init = rd.Agent((24,), 6, dataclasses.replace(args, init="torch"))
    assert any((m.bias != 0).any() for m in torch_init.modules() if isinstance(m, torch.nn.Linear) and
               m.bias is not None)


def test_eval_action_is_v1s_sampled_mode():
    """Dreamer v1's evaluation action: the most likely of 100 samples of the tanh-normal. With a small std it is the
    tanh of the mean; with the initial std of 5 the density peaks near ±1, so it saturates where the mean rule does
    not."""
    torch.manual_seed(0)
    actor = rd.Actor(8, 2, 16, init_std=5.0)
    feat = torch.randn(256, 8)
    sampled, mean = actor.mode(feat), actor.mode(feat, "mean")
    assert sampled.shape == mean.shape == (256, 2)
    assert sampled.abs().mean() > 0.95 and mean.abs().mean() < 0.5
    narrow = rd.Actor(8, 2, 16, init_std=1e-3, min_std=1e-4)
    assert torch.allclose(narrow.mode(feat), narrow.mode(feat, "mean"), atol=0.02)
