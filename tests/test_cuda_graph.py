"""--cuda-graph: `update` captured as CUDA graphs (GraphedUpdate). On a CPU: the flag is refused with one line, the
padded memory-mode pool is never picked from, and GraphedUpdate's plumbing (static inputs, the pool copied only after
a refresh, outputs, keys, retired graphs, the capture-failure fallback) gives the eager updates' losses and
parameters, with a CPU stand-in for the capture. With CUDA: the same against real graphs (issue 39, item 7)."""
import copy
import dataclasses
import json

import numpy as np
import pytest
import torch

import rama_dreamer as rd
from helpers import synthetic_replay

SMALL = dict(obs_type="state", deter_size=8, stoch_size=4, hidden_size=8, mlp_units=8, horizon=3, free_nats=3.0,
             obs_std=1.0, batch_size=6, seq_len=5, address_units=8, address_cnn_depth=2, address_batch=7,
             address_refresh=2, address_prob=0.5)
METHODS = {"dreamer": {}, "uniform": {}, "rrama": {}, "rbrama": {}, "vrama": {},
           "rrama_fresh": {"method": "rrama", "address_candidates_mode": "fresh"},
           "rrama_frozenx": {"method": "rrama", "address_x_net": "frozen"},  # the walker tables' rrama_frozenx row
           "vrama_batch_rule": {"method": "vrama", "wm_on_addressed": False, "addressed_wm_rule": "batch",
                                "address_candidates_mode": "fresh"}}


def test_cuda_graph_is_refused_on_a_cpu():
    args = rd.resolve_defaults(rd.Args(obs_type="state", env_id="dmc/cartpole-balance", device="cpu",
                                       cuda_graph=True))
    with pytest.raises(rd.UsageError, match=r"^--cuda-graph needs a CUDA device \(--device cpu is cpu\)$"):
        rd.check_args(args)


def test_a_resumed_run_takes_the_default_of_the_device_it_resumes_on(tmp_path):
    """A run saved on a GPU (cuda_graph True) resumes on a CPU without the flag: graphs change speed, not the math,
    so --cuda-graph is the resuming device's default (None, resolved by main) unless given again."""
    saved = rd.resolve_defaults(rd.Args(obs_type="state", env_id="dmc/cartpole-balance", cuda_graph=True))
    (tmp_path / "args.json").write_text(json.dumps(dataclasses.asdict(saved)))
    resumed, _ = rd.resolve_run(rd.Args(resume=str(tmp_path), device="cpu"), {"resume", "device"})
    assert resumed.cuda_graph is None and resumed.device == "cpu"
    with pytest.raises(rd.UsageError, match=r"--cuda-graph needs a CUDA device"):
        rd.resolve_run(rd.Args(resume=str(tmp_path), device="cpu", cuda_graph=True), {"resume", "device",
                                                                                         "cuda_graph"})


def test_padded_pool_is_never_picked():
    args = rd.resolve_defaults(rd.Args(**{**SMALL, "method": "rrama", "cuda_graph": True}))
    rng = np.random.default_rng(0)
    multitask = synthetic_replay((3,), 2, 5, 20, rng, task="before")
    addressing = rd.Addressing((3,), 2, dataclasses.replace(args, cuda_graph=False), "cpu")
    plan = rd.plan_update(args, multitask, addressing, rng, "cpu", "now", 0)
    real = len(addressing.candidate_embeddings)  # 5 episodes of 20 steps: 15 to 20 chunks of 5, padded to 32
    assert 16 <= real <= 20 and len(plan.pool.embeddings) == 32 and plan.pool.valid.sum() == real
    assert all(len(v) == 32 for v in plan.pool.chunks.values()) and len(plan.pool.reward_mask) == 32
    x = rd.to_torch(multitask.sample(400, args.seq_len, rng), "cpu")  # 400 rows, each picking once
    picks = addressing.pick(x, plan.pool)
    assert picks.max() < real and len(set(picks.tolist())) > real // 2  # the real rows are picked, padding never
    smaller = dataclasses.replace(args, address_candidates=20)  # at the cap: no padding beyond it
    rd.plan_update(smaller, multitask, addressing, rng, "cpu", "now", 0)
    assert len(addressing.pool.embeddings) == min(32, 20)


class CPUGraphedUpdate(rd.GraphedUpdate):
    """GraphedUpdate with CUDA's two parts replaced for a CPU: `record` runs fn once to make its outputs and then
    puts every state back (a capture runs nothing), and a replay runs fn on the static inputs again, writing its
    results into those outputs. What a replay reads is only what GraphedUpdate copied into the static inputs."""

    def on_side_stream(self, fn):
        return fn()

    def recover(self):  # nothing of CUDA's to put back
        pass

    def record(self, fn):
        modules = [self.agent] + ([self.addressing.net] if self.addressing else [])
        opts = list(self.agent.optimizers().values()) + ([self.addressing.opt] if self.addressing else [])
        saved = ([copy.deepcopy(m.state_dict()) for m in modules], [copy.deepcopy(o.state_dict()) for o in opts],
                 torch.get_rng_state(), self.addressing.generator.get_state() if self.addressing else None)
        try:
            outputs = fn()
        finally:
            for m, state in zip(modules, saved[0]):
                m.load_state_dict(state)
            for o, state in zip(opts, saved[1]):
                o.load_state_dict(state)
            torch.set_rng_state(saved[2])
            if self.addressing:
                self.addressing.generator.set_state(saved[3])
        self.records = getattr(self, "records", 0) + 1

        def replay():
            names, vector, picks = fn()
            assert names == outputs[0]
            outputs[1].copy_(vector)
            if picks is not None:
                outputs[2].copy_(picks)
        return replay, outputs


def run_updates(args, device, graphed, updates=12, warmup=1):
    """`updates` updates of a method from the same seeds: eager (`update`) or through a GraphedUpdate class. M grows
    by 8 episodes before update 5, so the memory-mode pool outgrows its padding at the refresh of update 6."""
    rng = np.random.default_rng(0)
    replay = synthetic_replay((3,), 2, 3, 20, rng, task="now")
    multitask = synthetic_replay((3,), 2, 3, 20, rng, task="before")
    for episode in replay.episodes[:2]:
        multitask.add(episode)
    more = synthetic_replay((3,), 2, 8, 20, rng, task="before")
    xs = [rd.to_torch(replay.sample(args.batch_size, args.seq_len, rng), device) for _ in range(updates)]
    torch.manual_seed(1)
    eager_args = dataclasses.replace(args, cuda_graph=device != "cpu")  # capturable Adam needs CUDA
    agent = rd.Agent((3,), 2, eager_args).to(device)
    addressing = rd.Addressing((3,), 2, eager_args, device) if args.method in rd.ADDRESSED_METHODS else None
    step = graphed(agent, addressing, eager_args, warmup) if graphed else (
        lambda x, plan: rd.update(agent, addressing, x, plan, eager_args))
    torch.manual_seed(2)
    if addressing:
        addressing.generator.manual_seed(3)
    plan_rng, losses, picks = np.random.default_rng(4), [], []
    for i, x in enumerate(xs):
        if i == 5:
            for episode in more.episodes:
                multitask.add(episode)
        plan = rd.plan_update(args, multitask, addressing, plan_rng, device, "now", i)
        out = step(x, plan)
        losses.append({k: float(v.detach()) for k, v in out["metrics"].items() if k.startswith(("losses/", "addressing/"))})
        if plan.mixed:
            picks.append(out["picks"][1].tolist())
    params = {**{f"agent.{k}": v for k, v in agent.state_dict().items()},
              **({f"phi.{k}": v for k, v in addressing.net.state_dict().items()} if addressing else {})}
    return losses, picks, params, step


def check_same(eager, graphed, rtol=1e-4, atol=1e-5):
    (eager_losses, eager_picks, eager_params, _), (graph_losses, graph_picks, graph_params, _) = eager, graphed
    assert graph_picks == eager_picks
    for e, g in zip(eager_losses, graph_losses):
        assert e.keys() == g.keys()
        for k in e:
            assert g[k] == pytest.approx(e[k], rel=rtol, abs=atol) or k == "addressing/refresh_seconds", k
    for k, v in eager_params.items():
        assert torch.allclose(graph_params[k], v, rtol=rtol, atol=atol), k


@pytest.mark.parametrize("name", list(METHODS))
def test_graphed_update_plumbing_matches_eager_updates(name):
    args = rd.resolve_defaults(rd.Args(**{**SMALL, "method": name, **METHODS[name], "cuda_graph": True}))
    eager = run_updates(args, "cpu", None)
    graphed = run_updates(args, "cpu", CPUGraphedUpdate)
    check_same(eager, graphed)
    step = graphed[3]
    assert step.records >= 1 and not step.failed
    if name in ("rrama", "rbrama", "vrama"):  # memory mode: a capture per pool size, the smaller one retired
        assert step.records >= 2 and len({dict(k[0]).get("pool.embeddings") for k in step.graphs}) == 1
    if name != "dreamer":  # α decides the borrowed rows: a mixed and an unmixed batch have a graph each
        assert {k[1] for k in step.graphs} == {True, False}


def test_a_failed_capture_leaves_the_run_eager(capsys):
    class Failing(CPUGraphedUpdate):
        def record(self, fn):
            raise RuntimeError("operation not permitted when stream is capturing")

    args = rd.resolve_defaults(rd.Args(**{**SMALL, "method": "rrama", "cuda_graph": True}))
    eager, graphed = run_updates(args, "cpu", None), run_updates(args, "cpu", Failing)
    check_same(eager, graphed)
    assert graphed[3].failed and capsys.readouterr().out.count("--cuda-graph: capture failed") == 1


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("name", ["dreamer", "rrama", "vrama", "uniform", "rrama_fresh", "rrama_frozenx",
                                  "vrama_batch_rule"])
def test_cuda_graphs_match_eager_updates(name):
    args = rd.resolve_defaults(rd.Args(**{**SMALL, "method": name, **METHODS[name], "cuda_graph": True,
                                          "device": "cuda"}))
    eager = run_updates(args, "cuda", None)
    graphed = run_updates(args, "cuda", rd.GraphedUpdate)
    assert not graphed[3].failed and graphed[3].graphs
    check_same(eager, graphed, rtol=1e-3, atol=1e-4)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_failed_cuda_capture_leaves_the_run_eager(capsys):
    """A host sync inside the capture (here an .item()) fails it: one line, then eager updates equal to an eager
    run's, so the stream and the generators were put back."""
    class Syncing(rd.GraphedUpdate):
        def record(self, fn):
            return super().record(lambda: (fn(), torch.ones(1, device="cuda").item())[0])

    args = rd.resolve_defaults(rd.Args(**{**SMALL, "method": "rrama", "cuda_graph": True, "device": "cuda"}))
    eager, graphed = run_updates(args, "cuda", None), run_updates(args, "cuda", Syncing)
    check_same(eager, graphed, rtol=1e-3, atol=1e-4)
    assert graphed[3].failed and capsys.readouterr().out.count("--cuda-graph: capture failed") == 1


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_frozen_x_net_keeps_its_gru_weights_in_one_cudnn_buffer():
    """cuDNN runs a GRU from one buffer of its weights. A deepcopy leaves them apart, and then every call packs them
    again (a warning per run, and copies in each graphed update): --address-x-net frozen's copy is packed once."""
    args = rd.resolve_defaults(rd.Args(**{**SMALL, "method": "rrama", "address_x_net": "frozen", "device": "cuda"}))
    addressing = rd.Addressing((3,), 2, args, "cuda")
    grus = [m for m in addressing.x_net.modules() if isinstance(m, torch.nn.RNNBase)]
    assert grus and addressing.x_net is not addressing.net
    for gru in grus:
        assert len({w.untyped_storage().data_ptr() for w in gru._flat_weights}) == 1
