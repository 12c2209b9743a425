"""The fast paths compute what the plain path computes: same losses and gradients on a fixed batch (within a stated
tolerance), the batches of the task's own stream, same episodes with and without parallel envs."""
import copy
import dataclasses
import os

import numpy as np
import pytest
import torch
import torch.nn as nn

import rama_dreamer as rd
from helpers import TINY, run_script, synthetic_replay

PIXEL = dict(deter_size=16, stoch_size=4, hidden_size=16, mlp_units=16, cnn_depth=4, horizon=3, batch_size=3,
             seq_len=4, free_nats=3.0, obs_std=1.0)


def _pixel_batch(seed=0, n=3, seq_len=4):
    rng = np.random.default_rng(seed)
    return rd.to_torch(synthetic_replay((64, 64, 3), 2, 2, 10, rng).sample(n, seq_len, rng), "cpu")


def _wm_loss(agent, batch, seed=0):
    torch.manual_seed(seed)  # the posterior samples
    loss, _, metrics = rd.world_model_loss(agent.wm, batch, 3.0, 1.0)
    return loss, metrics


def test_channels_last_gives_the_plain_losses_and_gradients():
    """Memory layout only: fp32 results agree to float rounding (tolerance 1e-4 relative)."""
    torch.manual_seed(0)
    plain = rd.Agent((64, 64, 3), 2, rd.Args(**PIXEL, channels_last=False))
    fast = copy.deepcopy(plain)
    rd.set_speed_options(fast, "fp32", channels_last=True)
    assert fast.wm.encoder.net[0].weight.is_contiguous(memory_format=torch.channels_last)
    batch = _pixel_batch()
    (loss_plain, m_plain), (loss_fast, m_fast) = _wm_loss(plain, batch), _wm_loss(fast, batch)
    assert torch.allclose(loss_fast, loss_plain, rtol=1e-4)
    g_plain = torch.autograd.grad(loss_plain, list(plain.wm.parameters()))
    g_fast = torch.autograd.grad(loss_fast, list(fast.wm.parameters()))
    for a, b in zip(g_fast, g_plain):
        assert torch.allclose(a, b, rtol=1e-3, atol=1e-5)


def test_bf16_losses_stay_close_to_fp32():
    """bf16 convs and MLP hidden layers: world-model terms within 1% and imagined returns within 2% of fp32."""
    torch.manual_seed(0)
    fp32 = rd.Agent((64, 64, 3), 2, rd.Args(**PIXEL))
    bf16 = copy.deepcopy(fp32)
    rd.set_speed_options(bf16, "bf16", channels_last=True)
    assert bf16.wm.decoder.bf16 and bf16.value.bf16 and not fp32.value.bf16
    # bf16 is in effect, not only flagged: the hidden layers compute in bfloat16, the output layer in fp32
    dtypes = {}

    def record(name):
        def hook(module, inputs, output):  # returns None: the output is left as it is
            dtypes.setdefault(name, output.dtype)
        return hook

    bf16.value.hidden[0].register_forward_hook(record("hidden"))
    bf16.value.out.register_forward_hook(record("out"))
    bf16.wm.encoder.net[0].register_forward_hook(record("conv"))
    batch = _pixel_batch()
    with torch.no_grad():
        (_, m32), (_, m16) = _wm_loss(fp32, batch), _wm_loss(bf16, batch)
    for key in ("losses/obs_loglik", "losses/reward_loglik", "losses/kl"):
        assert abs(float(m16[key] - m32[key])) <= 0.01 * abs(float(m32[key].detach())) + 1e-3, key
    feats = torch.randn(3, 5, fp32.wm.rssm.feat_size)
    r32, _, v32, _ = rd.imagined_returns(fp32.wm, fp32.value, feats, 0.99, 0.95)
    r16, _, v16, _ = rd.imagined_returns(bf16.wm, bf16.value, feats, 0.99, 0.95)
    assert v16.dtype == torch.float32  # output layers stay fp32
    assert dtypes == {"hidden": torch.bfloat16, "out": torch.float32, "conv": torch.bfloat16}
    assert not torch.equal(v16, v32)  # bf16's rounding shows
    assert torch.allclose(r16, r32, rtol=0.02, atol=0.02)


def test_one_value_pass_matches_the_two_pass_update():
    """train_step computes the value once for both losses; its parameter updates equal those of the plain recipe:
    actor loss with the value frozen, then the value loss on a second pass over detached features."""
    args = rd.Args(obs_type="state", deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8, horizon=4,
                   free_nats=0.0, obs_std=1.0, batch_size=3, seq_len=5, imagine_after_model_step=True)
    torch.manual_seed(0)
    agent = rd.Agent((3,), 2, args)
    reference = copy.deepcopy(agent)
    rng = np.random.default_rng(0)
    batch = rd.to_torch(synthetic_replay((3,), 2, 2, 20, rng).sample(3, 5, rng), "cpu")

    torch.manual_seed(1)
    rd.train_step(agent, batch, args)

    torch.manual_seed(1)  # the plain recipe, step by step, with the same random draws
    ref = reference
    loss, post, _ = rd.world_model_loss(ref.wm, batch, args.free_nats, args.kl_scale, obs_std=args.obs_std)
    ref.model_opt.zero_grad()
    loss.backward()
    nn.utils.clip_grad_norm_(ref.wm.parameters(), args.grad_clip)
    ref.model_opt.step()
    with rd.Freeze(ref.wm, ref.value):
        start = {k: v.detach().flatten(0, 1) for k, v in post.items()}
        feats, _ = rd.imagine(ref.wm, ref.actor, start, args.horizon)
        returns, weights, _, _ = rd.imagined_returns(ref.wm, ref.value, feats, args.gamma, args.return_lambda)
        actor_loss = -(weights * returns).mean()
    ref.actor_opt.zero_grad()
    actor_loss.backward()
    nn.utils.clip_grad_norm_(ref.actor.parameters(), args.grad_clip)
    ref.actor_opt.step()
    value_pred = ref.value(feats[:-1].detach()).squeeze(-1)
    value_loss = -(weights * rd.gaussian_loglik(value_pred, returns.detach(), 0)).mean()
    ref.value_opt.zero_grad()
    value_loss.backward()
    nn.utils.clip_grad_norm_(ref.value.parameters(), args.grad_clip)
    ref.value_opt.step()

    for (name, p), p_ref in zip(agent.named_parameters(), ref.parameters()):
        assert torch.allclose(p, p_ref, atol=1e-6), name


def test_dreamer_v1_order_imagines_with_the_model_before_its_step():
    """The default (Dreamer v1): the world-model, actor and value losses all use the parameters before the update;
    the model steps last. Reference: the same three losses from one copy of the agent, then the three Adam steps."""
    args = rd.Args(obs_type="state", deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8, horizon=4,
                   free_nats=0.0, obs_std=1.0, batch_size=3, seq_len=5)
    assert not args.imagine_after_model_step and args.adam_eps == 1e-4
    torch.manual_seed(0)
    agent = rd.Agent((3,), 2, args)
    reference, model_first = copy.deepcopy(agent), copy.deepcopy(agent)
    assert reference.model_opt.defaults["eps"] == 1e-4
    rng = np.random.default_rng(0)
    batch = rd.to_torch(synthetic_replay((3,), 2, 2, 20, rng).sample(3, 5, rng), "cpu")
    torch.manual_seed(1)
    rd.train_step(agent, batch, args)

    torch.manual_seed(1)
    ref = reference
    loss, post, _ = rd.world_model_loss(ref.wm, batch, args.free_nats, args.kl_scale, obs_std=args.obs_std)
    with rd.Freeze(ref.wm, ref.value):
        start = {k: v.detach().flatten(0, 1) for k, v in post.items()}
        feats, _ = rd.imagine(ref.wm, ref.actor, start, args.horizon)
        returns, weights, _, _ = rd.imagined_returns(ref.wm, ref.value, feats, args.gamma, args.return_lambda)
    value_pred = ref.value(feats[:-1].detach()).squeeze(-1)
    value_loss = -(weights * rd.gaussian_loglik(value_pred, returns.detach(), 0)).mean()
    for opt, module, part_loss in ((ref.actor_opt, ref.actor, -(weights * returns).mean()),
                                   (ref.value_opt, ref.value, value_loss), (ref.model_opt, ref.wm, loss)):
        opt.zero_grad()
        part_loss.backward(inputs=list(module.parameters()))
        nn.utils.clip_grad_norm_(module.parameters(), args.grad_clip)
        opt.step()
    for (name, p), p_ref in zip(agent.named_parameters(), ref.parameters()):
        assert torch.allclose(p, p_ref, atol=1e-6), name
    # and the order matters: stepping the model first gives another actor
    torch.manual_seed(1)
    rd.train_step(model_first, batch, dataclasses.replace(args, imagine_after_model_step=True))
    assert not torch.allclose(rd.nn.utils.parameters_to_vector(model_first.actor.parameters()),
                              rd.nn.utils.parameters_to_vector(agent.actor.parameters()))


def test_sample_batches_draws_the_tasks_own_stream_in_order():
    """The current-task batches are those of replay.sample with the task's generator, in order."""
    rng = np.random.default_rng(0)
    replay = synthetic_replay((3,), 2, 3, 20, rng)
    reference_rng = np.random.default_rng(7)
    expected = [rd.to_torch(replay.sample(4, 5, reference_rng), "cpu") for _ in range(3)]
    got = [x for x, _ in rd.sample_batches(replay, 4, 5, np.random.default_rng(7), "cpu", 3)]
    assert len(got) == 3
    for x, y in zip(got, expected):
        assert x["obs"].shape == (4, 5, 3)
        assert all(torch.equal(x[k], y[k]) for k in x)
    assert not torch.equal(got[0]["obs"], got[1]["obs"])  # a fresh batch each time


def test_policy_acts_in_several_envs_at_once():
    args = rd.Args(obs_type="state", deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8)
    policy = rd.Policy(rd.Agent((3,), 2, args), "cpu")
    policy.reset(num_envs=4)
    rng = np.random.default_rng(0)
    actions = policy.act(np.zeros((4, 3), np.float32), 0.3, rng)
    assert actions.shape == (4, 2) and actions.dtype == np.float32 and np.all(np.abs(actions) <= 1)
    assert policy.act(np.zeros((4, 3), np.float32), None, rng).shape == (4, 2)


@pytest.mark.slow
def test_parallel_envs_play_the_sequential_episodes():
    """Two envs in subprocesses (AsyncVectorEnv): with the same seeds and a deterministic policy, the same episodes
    as one env in this process played episode after episode."""
    args = rd.resolve_defaults(rd.Args(env_id="dmc/cartpole-balance", obs_type="state", time_limit=40))
    seeds = [11, 12]
    envs = rd.make_envs(args, args.env_id, 0, 2)
    act = lambda obs: np.tanh(obs[..., :1]).astype(np.float32)  # noqa: E731  deterministic, state-dependent
    try:
        parallel, _ = rd.run_episodes(envs, act, seeds, "cartpole-balance")
    finally:
        envs.close()
    env = rd.make_envs(args, args.env_id, 0, 1)
    try:
        for seed, episode in zip(seeds, parallel):
            (single,), _ = rd.run_episodes(env, act, [seed], "cartpole-balance")
            assert episode.keys() == single.keys()
            assert len(episode["reward"]) == 21  # 40 env steps / repeat 2, plus the reset step
            for key in ("obs", "action", "reward", "terminal", "return"):
                assert np.allclose(episode[key], single[key]), key
        assert not np.allclose(parallel[0]["obs"], parallel[1]["obs"])
    finally:
        env.close()


@pytest.mark.slow
def test_script_with_fast_paths_runs(tmp_path):
    """bf16 where this CPU has it natively (else refused, see below) and two collecting subprocesses
    together, end to end (pixels, tiny sizes)."""
    precision = "bf16" if rd.native_bf16(torch.device("cpu"))[0] else "fp32"
    proc = run_script("rama_dreamer.py", "--env-id", "dmc/walker-walk", *TINY, "--run-dir", str(tmp_path),
                      "--precision", precision, "--num-envs", "2", "--total-steps", "400")
    assert "episode 4" in proc.stdout
    (run,) = tmp_path.iterdir()
    assert len(list((run / "episodes").glob("*.npz"))) == 4


@pytest.mark.parametrize("flags, native", [(["fpu", "avx2"], False), (["avx2", "avx512_bf16"], True),
                                           (["amx_bf16"], True)])
def test_bf16_is_refused_without_native_support(monkeypatch, tmp_path, flags, native):
    """A CPU without AVX-512 BF16 or AMX emulates bf16 (13x slower than fp32): --precision bf16 is refused with one
    line naming the flag and suggesting fp32, before anything runs. fp32 is never refused."""
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nflags\t\t: " + " ".join(flags) + "\n")
    found = rd.native_bf16(torch.device("cpu"), str(cpuinfo))
    assert found[0] == native
    monkeypatch.setattr(rd, "native_bf16", lambda device: found)
    args = rd.resolve_defaults(rd.Args(env_id="dmc/cartpole-balance", device="cpu"))
    rd.check_args(args)
    if native:
        rd.check_args(dataclasses.replace(args, precision="bf16"))
    else:
        with pytest.raises(rd.UsageError, match=r"--precision bf16: CPU .*no avx512_bf16.*use --precision fp32"):
            rd.check_args(dataclasses.replace(args, precision="bf16"))


@pytest.mark.slow
def test_bf16_refusal_is_one_line_on_this_machine(tmp_path):
    """The same check in a real run: on a CPU without native bf16, exit 2, one line, no run folder."""
    if rd.native_bf16(torch.device("cpu"))[0]:
        pytest.skip("this CPU has native bf16")
    proc = run_script("rama_dreamer.py", "--env-id", "dmc/cartpole-balance", "--obs-type", "state", *TINY,
                      "--run-dir", str(tmp_path), "--precision", "bf16", check=False)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "--precision bf16" in proc.stderr
    assert not any(tmp_path.iterdir())


def test_decoder_first_layer_as_a_matrix_product_equals_the_transposed_conv():
    """ConvDecoder computes its first transposed conv (on a 1x1 input) as a matrix product: same output and gradients
    as running nn.ConvTranspose2d itself."""
    torch.manual_seed(0)
    decoder = rd.ConvDecoder(10, (64, 64, 3), depth=4)
    feat = torch.randn(2, 3, 10, requires_grad=True)
    y = decoder(feat)
    plain = decoder.net(decoder.linear(feat.flatten(0, 1))[:, :, None, None]).unflatten(0, (2, 3))
    assert y.shape == plain.shape == (2, 3, 3, 64, 64) and torch.allclose(y, plain, atol=1e-6)
    params = [feat, decoder.net[0].weight, decoder.net[0].bias, decoder.linear.weight]
    g, g_ref = (torch.autograd.grad(out.square().sum(), params) for out in (y, plain))
    for a, b in zip(g, g_ref):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5)


def compiled_variant(monkeypatch, mode: str):
    """benchmarks/compiled_rssm.py as bench_update.py's --compare-to loads it: a copy of rama_dreamer.py, compiled."""
    import importlib.util

    monkeypatch.setenv("COMPILE", mode)
    spec = importlib.util.spec_from_file_location(f"compiled_{mode}", os.path.join("benchmarks", "compiled_rssm.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
@pytest.mark.parametrize("mode,method", [("steps", "dreamer"), ("steps", "vrama"), ("loops", "rrama")])
def test_the_compiled_rssm_variant_gives_the_scripts_updates(monkeypatch, mode, method):
    """torch.compile fuses kernels and changes nothing else: with the same seeds, three updates of the compiled copy
    give the script's losses and parameters to fp32 rounding (its random draws are torch's own), every method's
    RSSM use included (the filter, imagination under Freeze, VRAMa's imagination from the picks)."""
    from torch._dynamo.utils import counters

    compiled = compiled_variant(monkeypatch, mode)
    assert compiled.RSSM is not rd.RSSM and compiled.RSSM.img_step is not rd.RSSM.img_step  # a copy: rd untouched
    torch._dynamo.reset()
    counters.clear()  # dynamo counts the graphs it captures: none without a compile, none on a fallback to eager
    small = dict(obs_type="state", deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8, horizon=3, free_nats=0.0,
                 obs_std=1.0, batch_size=6, seq_len=5, address_units=8, address_batch=7, method=method)
    results = {}
    for module in (rd, compiled):
        args = module.resolve_defaults(module.Args(**small))
        rng = np.random.default_rng(0)
        replay = synthetic_replay((3,), 2, 3, 20, rng, task="now")
        multitask = synthetic_replay((3,), 2, 3, 20, rng, task="before")
        torch.manual_seed(1)
        agent = module.Agent((3,), 2, args)
        addressing = module.Addressing((3,), 2, args, "cpu") if method in module.ADDRESSED_METHODS else None
        torch.manual_seed(2)
        losses = []
        for i in range(3):
            x = module.to_torch(replay.sample(args.batch_size, args.seq_len, rng), "cpu")
            plan = module.plan_update(args, multitask, addressing, rng, "cpu", "now", i)
            out = module.update(agent, addressing, x, plan, args)
            losses.append({k: float(v.detach()) for k, v in out["metrics"].items()
                           if k.startswith(("losses/", "addressing/l"))})
        results[module] = losses, agent.state_dict()
        if module is rd:  # the script's own update compiles nothing
            assert counters["stats"]["unique_graphs"] == 0
    assert counters["stats"]["unique_graphs"] > 0  # the copy's updates ran compiled code
    (eager_losses, eager_params), (compiled_losses, compiled_params) = results[rd], results[compiled]
    for eager, fused in zip(eager_losses, compiled_losses):
        assert eager.keys() == fused.keys() and all(fused[k] == pytest.approx(eager[k], rel=1e-4, abs=1e-5)
                                                    for k in eager), (eager, fused)
    for k, v in eager_params.items():
        assert torch.allclose(compiled_params[k], v, rtol=1e-4, atol=1e-5), k
