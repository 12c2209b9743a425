"""The update of Algorithm 2 as one fixed-shape, sync-free function: the same losses and parameters as the
variable-shape update it replaced, Gumbel-max picks that follow q, and no host sync inside."""
import dataclasses
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import rama_dreamer as rd
from helpers import synthetic_replay

SMALL = dict(obs_type="state", deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8, horizon=3, free_nats=3.0,
             obs_std=1.0, batch_size=6, seq_len=5, address_units=8, address_cnn_depth=2, address_batch=7,
             address_imagine_starts=4)
METHODS = {"dreamer": {}, "uniform": {}, "rrama": {}, "rbrama": {}, "vrama": {},
           "rrama_fresh": {"method": "rrama", "address_candidates_mode": "fresh"},
           "vrama_posterior_rows": {"method": "vrama", "vrama_objective": "posterior", "wm_on_addressed": False}}


def buffers(rng):
    """M_τ of task `now`, and M holding a prior task's episodes and two of `now` (so the reward mask has both)."""
    replay = synthetic_replay((3,), 2, 3, 20, rng, task="now")
    multitask = synthetic_replay((3,), 2, 3, 20, rng, task="before")
    for episode in replay.episodes[:2]:
        multitask.add(episode)
    return replay, multitask


def reference_update(agent, addressing, x, plan, args, train_index, mix_picks, multitask):
    """The update before it had a fixed shape (commit 33e394e), with the picks given: the batch is x, or β·n rows of
    x and the picked chunks gathered by the host when mixed; masks only when mixed."""
    if plan.m_batch is not None:
        m = plan.m_batch
        logits = rd.address_logits(addressing.embed_x(x), addressing.embed(m), addressing.stop_grad_x)
        if args.method == "vrama":
            probs = logits.softmax(-1)
            one_hot = F.one_hot(train_index, probs.shape[-1]).float() + (probs - probs.detach())
            loss = rd.vrama_loss(agent, one_hot, m, args.horizon, args.gamma, args.return_lambda,
                                 args.address_imagine_starts, args.vrama_select, args.vrama_reduction,
                                 args.vrama_objective)
        else:
            if args.method == "rbrama":  # x's baseline in M_j's filter pass, as since 2026-11-25 (the same sums up
                # to the posterior noise drawn: test_one_filter_pass_gives_each_chunks_reward_sum)
                sums = rd.predicted_reward_sum(agent.wm, {k: torch.cat([m[k], x[k]]) for k in ("obs", "action")})
                advantage = sums[:len(m["action"])][train_index] - sums[len(m["action"]):]
            else:
                advantage = rd.predicted_reward_sum(agent.wm, m)[train_index]
            loss = rd.reinforce_loss(logits, train_index, advantage, args.address_standardize)
        rd.optimizer_step(addressing.opt, loss, addressing.net.parameters(), args.address_grad_clip)
    batch, reward_mask, model_mask = x, None, None
    address_metrics = {"addressing/loss": loss.detach()} if plan.m_batch is not None else {}
    if plan.mixed:
        keep = rd.keep_rows(args)
        ids = (plan.pool.ids[0][mix_picks.numpy()], plan.pool.ids[1][mix_picks.numpy()])
        borrowed = rd.to_torch(multitask.gather(*ids, args.seq_len), "cpu")
        batch = {k: torch.cat([x[k][:keep], borrowed[k]], 0) for k in x}
        reward_mask = torch.tensor([1.0] * keep + [float(multitask.tasks[e] == "now") for e in ids[0]])
        if not args.wm_on_addressed:
            model_mask = torch.tensor([1.0] * keep + [0.0] * (len(x["reward"]) - keep))
    out = rd.train_step(agent, batch, args, reward_mask, model_mask)
    out["metrics"].update(address_metrics)
    return out


@pytest.mark.parametrize("name", list(METHODS))
def test_fixed_shape_update_matches_the_variable_shape_update(monkeypatch, name):
    args = rd.resolve_defaults(rd.Args(**{**SMALL, "method": name, **METHODS[name]}))
    rng = np.random.default_rng(0)
    replay, multitask = buffers(rng)
    xs = [rd.to_torch(replay.sample(args.batch_size, args.seq_len, rng), "cpu") for _ in range(3)]
    # mixed, not mixed, mixed (p = 1, 0, 1): both kinds of update, and a refresh of D between updates 0 and 2
    plans, versions = [], {}
    drawn = []  # every Gumbel-max pick of the new update, in order: the reference is given the same ones
    real_gumbel = rd.gumbel_max
    monkeypatch.setattr(rd, "gumbel_max", lambda *a: drawn.append(real_gumbel(*a)) or drawn[-1])
    for version in ("fixed", "reference"):
        torch.manual_seed(1)
        agent = rd.Agent((3,), 2, args)
        addressing = rd.Addressing((3,), 2, args, "cpu") if args.method in rd.ADDRESSED_METHODS else None
        torch.manual_seed(2)  # the same posterior and imagination noise in both
        losses, picks = [], iter(list(drawn))
        for i, x in enumerate(xs):
            if version == "fixed":
                plan = rd.plan_update(dataclasses.replace(args, address_prob=float(i != 1), address_refresh=2),
                                      multitask, addressing, rng, "cpu", "now", i)
                plans.append(plan)
                out = rd.update(agent, addressing, x, plan, args)
            else:
                plan = plans[i]
                train_index = next(picks) if plan.m_batch is not None else None
                mix_picks = (next(picks) if addressing else torch.arange(args.batch_size - rd.keep_rows(args))) \
                    if plan.pool is not None else None
                out = reference_update(agent, addressing, x, plan, args, train_index, mix_picks, multitask)
            losses.append({k: float(v.detach()) for k, v in out["metrics"].items()
                           if k.startswith(("losses/", "addressing/loss"))})
        params = {**{f"agent.{k}": v for k, v in agent.state_dict().items()},
                  **({f"phi.{k}": v for k, v in addressing.net.state_dict().items()} if addressing else {})}
        versions[version] = losses, params
    assert [p.mixed for p in plans] == ([False] * 3 if name == "dreamer" else [True, False, True])
    (fixed_losses, fixed_params), (ref_losses, ref_params) = versions["fixed"], versions["reference"]
    for fixed, ref in zip(fixed_losses, ref_losses):  # only the order of operations differs: fp32 rounding
        assert fixed.keys() == ref.keys() and all(fixed[k] == pytest.approx(ref[k], rel=1e-4, abs=1e-5) for k in ref)
    assert fixed_params.keys() == ref_params.keys()
    for k, v in fixed_params.items():
        assert torch.allclose(v, ref_params[k], rtol=1e-4, atol=1e-5), k


def test_one_filter_pass_gives_each_chunks_reward_sum(monkeypatch):
    """RbRAMa filters M_j and x in one pass: without posterior noise (zeroed here), each chunk's predicted reward sum
    is the one its own pass gives, so the concatenation changes only which noise each row draws."""
    torch.manual_seed(0)
    agent = rd.Agent((3,), 2, rd.resolve_defaults(rd.Args(**SMALL)))
    rng = np.random.default_rng(0)
    replay = synthetic_replay((3,), 2, 3, 20, rng)
    a, b = (rd.to_torch(replay.sample(n, 5, rng), "cpu") for n in (7, 6))
    monkeypatch.setattr(torch, "randn_like", torch.zeros_like)
    both = rd.predicted_reward_sum(agent.wm, {k: torch.cat([a[k], b[k]]) for k in ("obs", "action")})  # (13,)
    alone = torch.cat([rd.predicted_reward_sum(agent.wm, a), rd.predicted_reward_sum(agent.wm, b)])
    assert both.shape == (13,) and torch.allclose(both, alone, atol=1e-5)
    assert not torch.allclose(both[:6], both[7:])  # the chunks differ: the check compares something


def test_gumbel_max_picks_follow_q():
    q = torch.tensor([0.05, 0.1, 0.15, 0.3, 0.4])  # a fixed q over 5 candidates
    draws = 20_000
    generator = torch.Generator().manual_seed(0)
    picks = rd.gumbel_max(q.log().expand(draws, 5), generator)  # (draws,)
    frequency = torch.bincount(picks, minlength=5).double() / draws
    standard_error = (q.double() * (1 - q.double()) / draws).sqrt()
    assert torch.all((frequency - q.double()).abs() < 4 * standard_error), frequency
    again = rd.gumbel_max(q.log().expand(draws, 5), torch.Generator().manual_seed(0))
    assert torch.equal(picks, again)  # the update's own generator: the same seed, the same picks


def no_host_sync(monkeypatch):
    """Make .item(), .cpu(), .tolist(), .numpy() and bool/float/int of a tensor raise when rama_dreamer.py calls them."""
    for name in ("item", "cpu", "tolist", "numpy", "__bool__", "__float__", "__int__"):
        real = getattr(torch.Tensor, name)

        def guarded(self, *a, _real=real, _name=name, **k):
            if sys._getframe(1).f_code.co_filename == rd.__file__:
                raise AssertionError(f"host sync inside the update: Tensor.{_name}")
            return _real(self, *a, **k)

        monkeypatch.setattr(torch.Tensor, name, guarded)


@pytest.mark.parametrize("name", list(METHODS))
def test_update_has_no_host_sync(monkeypatch, name):
    args = rd.resolve_defaults(rd.Args(**{**SMALL, "method": name, **METHODS[name]}))
    rng = np.random.default_rng(0)
    replay, multitask = buffers(rng)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    agent = rd.Agent((3,), 2, args).to(device)
    addressing = rd.Addressing((3,), 2, args, device) if args.method in rd.ADDRESSED_METHODS else None
    plans = [rd.plan_update(dataclasses.replace(args, address_prob=p), multitask, addressing, rng, device, "now", 1)
             for p in (1.0, 0.0)]  # planned first: the host's part may read what it likes
    xs = [rd.to_torch(replay.sample(args.batch_size, args.seq_len, rng), device) for _ in plans]
    with monkeypatch.context() as patch:
        no_host_sync(patch)
        if device == "cuda":
            torch.cuda.set_sync_debug_mode("error")
        try:
            for x, plan in zip(xs, plans):
                rd.update(agent, addressing, x, plan, args)
        finally:
            if device == "cuda":
                torch.cuda.set_sync_debug_mode("default")


def test_the_sync_guard_trips_on_the_scripts_reads_only(monkeypatch):
    """A tensor read from here passes; the same read in code compiled under the script's file name trips it."""
    namespace = {"torch": torch}
    exec(compile("def half(n):\n    return int(torch.tensor(n // 2))\n", rd.__file__, "exec"), namespace)
    with monkeypatch.context() as patch:
        no_host_sync(patch)
        assert torch.ones(()).item() == 1.0 and int(torch.tensor(3)) == 3
        with pytest.raises(AssertionError, match="host sync inside the update: Tensor.__int__"):
            namespace["half"](6)
