"""The authors' configuration (--preset authors-code): each flag's effect on a small hand-checked case, and the preset."""
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


def _episode(task: str, value: float, length: int = 21):
    return {"obs": np.full((length, 3), value, np.float32), "action": np.zeros((length, 2), np.float32),
            "reward": np.zeros(length, np.float32), "terminal": np.zeros(length, bool), "task": task}


def _spy_update(monkeypatch, args, current, multitask, addressing=None, task="now", seed=0):
    """One rd.update with every train_step argument recorded."""
    seen, real = {}, rd.train_step

    def spy(agent, batch, args, reward_mask=None, model_mask=None, step_model=True):
        seen.update(batch=batch, reward_mask=reward_mask, model_mask=model_mask, step_model=step_model)
        return real(agent, batch, args, reward_mask, model_mask, step_model)

    monkeypatch.setattr(rd, "train_step", spy)
    rng = np.random.default_rng(seed)
    agent = rd.Agent((3,), 2, args)
    x = rd.to_torch(current.sample(args.batch_size, 5, rng), "cpu")
    rd.update(agent, addressing, x, rd.plan_update(args, multitask, addressing, rng, "cpu", task, 0), args)
    return seen


def test_reward_mask_of_borrowed_rows_same_task_or_all(monkeypatch):
    current, multitask = rd.Replay(), rd.Replay()
    current.add(_episode("now", 0.0))
    multitask.add(_episode("now", 1.0))  # a prior chunk of the same task (Table 1)
    base = rd.Args(obs_type="state", method="uniform", address_prob=1.0, **{**SMALL, "batch_size": 8})
    seen = _spy_update(monkeypatch, base, current, multitask)
    assert seen["reward_mask"].tolist() == [1.0] * 8  # the paper: a same-task chunk keeps its reward loss
    assert torch.all(seen["batch"]["obs"][4:] == 1)  # ... and rows 4: are borrowed ones (not an unmixed batch)
    seen = _spy_update(monkeypatch, dataclasses.replace(base, reward_mask_borrowed="all"), current, multitask)
    assert seen["reward_mask"].tolist() == [1.0] * 4 + [0.0] * 4  # the authors' code: every borrowed row masked
    assert torch.all(seen["batch"]["obs"][4:] == 1)  # ... and those rows are the borrowed ones


def test_addressed_wm_rule_masks_rows_or_skips_the_model_step(monkeypatch):
    current, multitask = rd.Replay(), rd.Replay()
    current.add(_episode("now", 0.0))
    multitask.add(_episode("before", 1.0))
    base = rd.Args(obs_type="state", method="uniform", address_prob=1.0, wm_on_addressed=False,
                   **{**SMALL, "batch_size": 8})
    seen = _spy_update(monkeypatch, base, current, multitask)
    assert seen["model_mask"].tolist() == [1.0] * 4 + [0.0] * 4 and seen["step_model"]
    seen = _spy_update(monkeypatch, dataclasses.replace(base, addressed_wm_rule="batch"), current, multitask)
    assert seen["model_mask"] is None and not seen["step_model"]
    # without --no-wm-on-addressed the rule is not read: the model trains on the whole batch
    seen = _spy_update(monkeypatch, dataclasses.replace(base, addressed_wm_rule="batch", wm_on_addressed=True),
                       current, multitask)
    assert seen["model_mask"] is None and seen["step_model"]


def test_skipping_the_model_step_still_trains_actor_and_value():
    args = rd.resolve_defaults(rd.Args(obs_type="state", **SMALL))
    rng = np.random.default_rng(0)
    batch = rd.to_torch(synthetic_replay((3,), 2, 2, 20, rng).sample(4, 5, rng), "cpu")
    for step_model in (True, False):
        torch.manual_seed(0)
        agent = rd.Agent((3,), 2, args)
        before = {k: v.clone() for k, v in agent.state_dict().items()}
        out = rd.train_step(agent, batch, args, step_model=step_model)
        moved = {k.split(".")[0] for k, v in agent.state_dict().items() if not torch.equal(v, before[k])}
        assert moved == ({"wm", "actor", "value"} if step_model else {"actor", "value"})
        assert ("losses/model_grad_norm" in out["metrics"]) == step_model


def test_logit_scale_sharpens_q_hat_over_d():
    args = rd.Args(obs_type="state", method="rrama", **SMALL)
    rng = np.random.default_rng(0)
    x = rd.to_torch(synthetic_replay((3,), 2, 2, 20, rng).sample(3, 5, rng), "cpu")
    for scale in (1.0, 10.0):
        torch.manual_seed(0)
        addressing = rd.Addressing((3,), 2, dataclasses.replace(args, address_logit_scale=scale), "cpu")
        addressing.candidate_embeddings = torch.randn(7, 8)
        logits = addressing.embed_x(x).detach() @ addressing.candidate_embeddings.T  # (3, 7)
        assert torch.allclose(addressing.probs(x), (scale * logits).softmax(-1), atol=1e-6)
    assert rd.Args().address_logit_scale == 1.0


def test_fresh_candidates_are_scored_per_mixed_batch_without_d(monkeypatch):
    current, multitask = rd.Replay(), rd.Replay()
    current.add(_episode("now", 0.0))
    for value in (1.0, 2.0):
        multitask.add(_episode("before", value))
    args = rd.Args(obs_type="state", method="rrama", address_prob=1.0, address_candidates_mode="fresh",
                   **{**SMALL, "batch_size": 8})
    addressing = rd.Addressing((3,), 2, args, "cpu")
    seen = _spy_update(monkeypatch, args, current, multitask, addressing)
    assert addressing.candidate_embeddings is None  # no embeddings of M kept between updates
    episode_ids, starts = addressing.candidates  # the m fresh chunks q̂ picked from
    assert len(episode_ids) == args.address_batch
    borrowed = seen["batch"]["obs"][4:, 0, 0]  # the 4 picked rows: the first obs of each, 1 or 2 by episode
    assert set(borrowed.tolist()) <= {1.0, 2.0}


def test_oversample_ends_clips_starts_to_the_last_chunk():
    replay = rd.Replay()
    replay.add(_episode("a", 0.0, length=21))  # T+1 = 21 steps; chunks of L = 5 start at 0..16
    draws = 20_000
    _, starts = replay.sample_ids(draws, 5, np.random.default_rng(0), oversample_ends=True)
    assert starts.min() == 0 and starts.max() == 16
    # a start uniform over 0..20, clipped to 16: P(16) = 5/21, every other start 1/21
    for start, p in ((16, 5 / 21), (0, 1 / 21), (8, 1 / 21)):
        se = np.sqrt(p * (1 - p) / draws)
        assert abs(np.mean(starts == start) - p) < 4 * se
    _, plain = replay.sample_ids(draws, 5, np.random.default_rng(0))
    assert abs(np.mean(plain == 16) - 1 / 17) < 4 * np.sqrt((1 / 17) * (16 / 17) / draws)


def test_weight_decay_shrinks_phi_by_one_minus_wd_per_step():
    """With a zero gradient Adam's step is 0, so one step leaves (1 − wd)·θ: the authors' var.assign((1 − wd)·var)."""
    args = rd.Args(obs_type="state", method="rrama", address_weight_decay=0.25, address_adam_eps=1e-5, **SMALL)
    addressing = rd.Addressing((3,), 2, args, "cpu")
    assert addressing.opt.param_groups[0]["eps"] == 1e-5
    before = [p.detach().clone() for p in addressing.net.parameters()]
    rd.optimizer_step(addressing.opt, sum(p.sum() for p in addressing.net.parameters()) * 0.0,
                      addressing.net.parameters(), 100.0)
    for p, b in zip(addressing.net.parameters(), before):
        assert torch.allclose(p, 0.75 * b, atol=1e-7)
    assert rd.Addressing((3,), 2, rd.Args(obs_type="state", **SMALL), "cpu").opt.param_groups[0]["eps"] == 1e-4


def test_vrama_posterior_objective_imagines_nothing_and_reaches_phi_through_values_only(monkeypatch):
    args = rd.resolve_defaults(rd.Args(obs_type="state", method="vrama", vrama_objective="posterior", **SMALL))
    rng = np.random.default_rng(0)
    m = rd.to_torch(synthetic_replay((3,), 2, 2, 20, rng).sample(3, 5, rng), "cpu")
    torch.manual_seed(0)
    agent = rd.Agent((3,), 2, args)
    monkeypatch.setattr(rd, "imagine", lambda *a: pytest.fail("the posterior objective imagines nothing"))

    def grad_on_one_hot():
        torch.manual_seed(1)  # the same posterior samples each time
        one_hot = torch.eye(3, requires_grad=True)
        loss = rd.vrama_loss(agent, one_hot, m, 3, 0.99, 0.95, objective="posterior")
        return loss, torch.autograd.grad(loss, one_hot)[0]

    loss, grad = grad_on_one_hot()
    with torch.no_grad():  # another reward head: the loss moves, its gradient does not (rewards are detached)
        for p in agent.wm.reward.parameters():
            p.add_(torch.randn_like(p))
    loss2, grad2 = grad_on_one_hot()
    assert loss2.item() != pytest.approx(loss.item()) and torch.allclose(grad, grad2, atol=1e-6)
    assert grad.abs().sum() > 0
    # by hand: −(γ^t-weighted mean) of the λ-returns along the chunks' own posteriors (L = 5 steps, 4 returns)
    torch.manual_seed(1)
    post, _ = agent.wm.rssm.observe(agent.wm.encoder(m["obs"]), m["action"])
    feats = agent.wm.rssm.feat(post).transpose(0, 1)  # (L, n, F)
    reward, value = agent.wm.reward(feats).squeeze(-1), agent.value(feats).squeeze(-1)  # (L, n)
    returns = rd.lambda_return(reward[:-1], value[:-1], torch.full_like(reward[:-1], 0.99), value[-1], 0.95)
    weights = 0.99 ** torch.arange(4.0)[:, None]
    assert loss2.item() == pytest.approx(-(weights * returns).mean().item(), rel=1e-5)


def test_vrama_posterior_objective_trains_phi_only():
    args = rd.Args(obs_type="state", method="vrama", vrama_objective="posterior", address_stop_grad_x=True, **SMALL)
    agent, addressing = rd.Agent((3,), 2, args), rd.Addressing((3,), 2, args, "cpu")
    assert addressing.stop_grad_x
    rng = np.random.default_rng(0)
    replay = synthetic_replay((3,), 2, 2, 20, rng)
    x, m = rd.to_torch(replay.sample(4, 5, rng), "cpu"), rd.to_torch(replay.sample(6, 5, rng), "cpu")
    agent_before = {k: v.clone() for k, v in agent.state_dict().items()}
    phi_before = {k: v.clone() for k, v in addressing.net.state_dict().items()}
    addressing.train(agent, x, m, args)
    assert all(torch.equal(v, agent_before[k]) for k, v in agent.state_dict().items())
    assert any(not torch.equal(v, phi_before[k]) for k, v in addressing.net.state_dict().items())
    assert all(p.grad is None for p in agent.parameters())


def test_own_episodes_join_m_only_with_the_papers_algorithm_2():
    replay, multitask = rd.Replay(), rd.Replay()
    rd.add_episode(rd.Args(method="rrama"), replay, multitask, _episode("now", 0.0))
    assert len(replay) == 1 and multitask.tasks == ["now"]  # the paper: stored to M as it comes
    rd.add_episode(rd.Args(method="rrama", own_episodes_in_m=False), replay, multitask, _episode("now", 0.0))
    assert len(replay) == 2 and len(multitask) == 1  # the authors' code: M_τ only
    rd.add_episode(rd.Args(method="dreamer"), replay, multitask, _episode("now", 0.0))
    assert len(multitask) == 1  # Dreamer keeps no M


@pytest.mark.slow
def test_without_own_episodes_a_sequence_addresses_the_earlier_tasks_only(tmp_path):
    run_script("rama_dreamer.py", "--task-sequence", "walker-stand,walker-walk", "--method", "uniform",
               "--no-own-episodes-in-m", "--run-dir", str(tmp_path), *TINY, "--obs-type", "state")
    run_path = glob.glob(os.path.join(tmp_path, "*"))[0]

    def keys(task_folder):
        with open(os.path.join(run_path, task_folder, "metrics.jsonl")) as f:
            return set().union(*(json.loads(line) for line in f))

    assert not any(k.startswith("addressing/pick_fraction") for k in keys("0_walker-stand"))  # M empty: no picks
    assert "addressing/pick_fraction/walker-stand" in keys("1_walker-walk")  # the first task's episodes, once over
    assert "addressing/pick_fraction/walker-walk" not in keys("1_walker-walk")  # never the task's own


def test_preset_sets_the_authors_values_and_given_flags_win(capsys):
    args = rd.apply_preset(rd.Args(preset="authors-code", address_lr=3e-4), {"preset", "address_lr"})
    out = capsys.readouterr().out
    assert out.startswith("preset authors-code: ") and "--address-lr" in out.split("given flags kept")[1]
    assert args.address_lr == 3e-4  # given on the command line: kept
    expected = {"own_episodes_in_m": False, "address_adam_eps": 1e-5, "address_weight_decay": 1e-6,
                "address_candidates_mode": "fresh", "address_batch": 102, "address_oversample_ends": True,
                "reward_mask_borrowed": "all", "vrama_objective": "posterior", "address_stop_grad_x": True,
                "addressed_wm_rule": "batch", "address_cnn_depth": 32}
    assert {k: getattr(args, k) for k in expected} == expected
    assert rd.apply_preset(rd.Args(), set()) == rd.Args()  # no preset: the paper's defaults, untouched
    assert set(rd.PRESETS["authors-code"]) == set(expected) | {"address_lr"}
    # each is a field of Args whose default is the paper's, which the preset changes
    assert all(getattr(rd.Args(), k) != v for k, v in rd.PRESETS["authors-code"].items())
    import rama_metaworld as rm

    assert rm.PRESETS == rd.PRESETS


@pytest.mark.slow
def test_preset_run_records_its_values_and_keeps_own_episodes_out_of_m(tmp_path):
    prior = tmp_path / "prior"
    run_script("rama_dreamer.py", "--env-id", "dmc/walker-stand", "--obs-type", "state", "--run-dir", str(prior),
               *TINY)
    for preset in ([], ["--preset", "authors-code", "--address-cnn-depth", "4"]):
        out = tmp_path / ("authors" if preset else "paper")
        proc = run_script("rama_dreamer.py", "--env-id", "dmc/walker-walk", "--obs-type", "state", "--method",
                          "rrama", "--prior-dirs", str(prior), "--run-dir", str(out), *TINY, *preset)
        run_path = glob.glob(os.path.join(out, "*"))[0]
        with open(os.path.join(run_path, "args.json")) as f:
            saved = json.load(f)
        with open(os.path.join(run_path, "metrics.jsonl")) as f:
            keys = set().union(*(json.loads(line) for line in f))
        if preset:
            assert "preset authors-code:" in proc.stdout
            assert saved["preset"] == "authors-code" and saved["address_cnn_depth"] == 4 and saved["address_lr"] == 1e-4
            assert "addressing/pick_fraction/walker-walk" not in keys  # M: the prior's walker-stand episodes only
        else:
            assert saved["preset"] is None and saved["own_episodes_in_m"]
            assert "addressing/pick_fraction/walker-walk" in keys  # the run's own episodes were in M
        assert "addressing/pick_fraction/walker-stand" in keys
