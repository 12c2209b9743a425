"""report.py: hand-checked table numbers from a synthetic results folder, curves, and single-run curves."""
import json
import os
import shutil

import numpy as np
import pytest

from helpers import run_script
import report


def write_run(folder, name, returns, args=None, sub=None):
    """A results run folder: args.json and a metrics.jsonl with one training episode per 100 steps (+ other lines)."""
    run = folder / name
    (run / (sub or "")).mkdir(parents=True, exist_ok=True)
    (run / "args.json").write_text(json.dumps(args or {"env_id": "dmc/x", "method": "dreamer", "seed": 1}))
    rows = []
    for i, value in enumerate(returns):
        rows += [{"step": 100 * (i + 1), "charts/episodic_return": value}, {"step": 100 * (i + 1), "losses/kl": 1.0}]
    (run / (sub or "") / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return run


@pytest.fixture
def results(tmp_path):
    exp = tmp_path / "results" / "exp"
    # task walk, dreamer: run averages 1, 2, 3, 10
    write_run(exp, "walk__dreamer__s1", [0.0, 2.0])  # (0 + 2) / 2 = 1
    run = write_run(exp, "walk__dreamer__s2", [7.0, 2.0])
    with open(run / "metrics.jsonl", "a") as f:  # a resumed run logged step 100 again: the last line counts
        f.write(json.dumps({"step": 100, "charts/episodic_return": 2.0}) + "\n")  # -> (2 + 2) / 2 = 2
    write_run(exp, "walk__dreamer__s3", [3.0, 3.0, 3.0])  # 3
    write_run(exp, "walk__dreamer__s4", [10.0])  # 10
    # task walk, rrama: run averages 4, 5, 9
    write_run(exp, "walk__rrama__s1", [4.0])
    write_run(exp, "walk__rrama__s2", [5.0])
    write_run(exp, "walk__rrama__s3", [8.0, 10.0])  # 9
    # task run: one Dreamer seed (7), no rrama
    write_run(exp, "run__dreamer__s1", [7.0])
    # a folder not named by sweep.py is grouped by its args.json: task dmc/hop, method vrama
    write_run(exp, "dmc_hop__x__vrama__1__123", [6.0], {"env_id": "dmc/hop", "method": "vrama", "seed": 1})
    # a --task-sequence run: one column per task
    write_run(exp, "seq__rrama__s1", [1.0, 3.0], sub="0_walker-stand")  # 2
    write_run(exp, "seq__rrama__s1", [5.0], sub="1_walker-walk")
    return exp


@pytest.mark.slow
def test_mean_se_and_iqm_by_hand():
    # [1, 2, 3, 10]: mean 16 / 4 = 4; deviations -3 -2 -1 6, squares sum 50, sample var 50 / 3,
    # s.e. = sqrt(50 / 3) / sqrt(4) = 4.0825 / 2 = 2.0412
    mean, se = report.mean_se([1, 2, 3, 10])
    assert mean == 4.0 and se == pytest.approx(2.041241, abs=1e-6)
    # IQM: int(4 / 4) = 1 run trimmed at each end -> mean(2, 3) = 2.5; every resample's IQM lies in [1, 10]
    iqm, low, high = report.iqm_ci([1, 2, 3, 10], reps=500, seed=0)
    assert iqm == 2.5 and 1 <= low <= iqm <= high <= 10 and low < high
    assert report.iqm_ci([10, 3, 2, 1], reps=500, seed=0)[0] == 2.5
    # seeded, whatever numpy's global generator holds (rliable draws from it), and that generator is left as it was
    np.random.seed(123)
    state = np.random.get_state()[1].copy()
    assert report.iqm_ci([1, 2, 3, 10], reps=500, seed=0) == (iqm, low, high)
    assert (np.random.get_state()[1] == state).all()
    # 3 runs: int(3 / 4) = 0 trimmed, so IQM = mean = (4 + 5 + 9) / 3 = 6
    assert report.iqm_ci([4, 5, 9], reps=500, seed=0)[0] == pytest.approx(6.0)
    # one run: no s.e.; every resample is that run, so the CI is a point
    assert report.iqm_ci([7.0], reps=100, seed=0) == (7.0, 7.0, 7.0)
    assert report.mean_se([7.0])[0] == 7.0 and report.mean_se([7.0])[1] != report.mean_se([7.0])[1]  # nan


@pytest.mark.slow
def test_probability_of_improvement_by_hand():
    # [3, 5, 7] against [4, 4, 6]: 3 beats none; 5 beats both 4s; 7 beats all three -> 5 of 9 pairs
    p, low, high = report.improvement_ci([3, 5, 7], [4, 4, 6], reps=500, seed=0)
    assert p == pytest.approx(5 / 9) and 0 <= low <= p <= high <= 1
    # ties count half: [1, 2] against [2, 3] -> only 2 vs 2, a tie: 0.5 of 4 pairs
    assert report.improvement_ci([1, 2], [2, 3], reps=500, seed=0)[0] == pytest.approx(0.125)
    assert report.improvement_ci([1, 2], [1, 2], reps=500, seed=0)[0] == 0.5  # the same scores: no difference
    # every run of X above every run of Y: 1, and so is every resample
    assert report.improvement_ci([5, 6], [1, 2, 3], reps=500, seed=0) == (1.0, 1.0, 1.0)


def test_rank_test_by_hand():
    """The exact two-sided Mann-Whitney p: of the C(6, 3) = 20 equally likely splits of 6 ranks into 3 + 3, one puts
    all of X on top (U = 9) and one puts X on top but for one pair (U = 8)."""
    assert report.rank_test([5, 6, 7], [1, 2, 3]) == pytest.approx(2 / 20)  # U = 9 or U = 0: 2 of 20
    assert report.rank_test([2.5, 5, 9], [1, 2, 3]) == pytest.approx(4 / 20)  # U >= 8 or U <= 1: 4 of 20
    assert report.rank_test([5, 6], [1, 2, 3]) == pytest.approx(2 / 10)  # C(5, 2) = 10 splits
    assert report.rank_test([10, 11, 12, 13, 14], [1, 2, 3, 4, 5]) == pytest.approx(2 / 252)  # C(10, 5) = 252
    # ties: by permutation, still exact: [5, 5, 6] above [1, 2, 3] is as extreme as it gets, 2 of 20
    assert report.rank_test([5, 5, 6], [1, 2, 3]) == pytest.approx(2 / 20)
    assert report.rank_test([1, 2, 3], [1, 2, 3]) == pytest.approx(1.0)


@pytest.mark.slow
def test_report_tables_by_hand(results):
    run_script("report.py", str(results.parent), "--reps", "500", "--decimals", "3")  # results/ holds experiments
    text = (results / "report.md").read_text()
    header = next(line for line in text.splitlines() if line.startswith("| method"))
    columns = [c.strip() for c in header.strip("|").split("|")]
    assert columns == ["method"] + [f"{t}: {h}" for t in ("dmc/hop", "run", "seq/0_walker-stand", "seq/1_walker-walk",
                                                            "walk") for h in ("mean ± s.e. (seeds)", "IQM [95% CI]")]
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.strip("|").split("|")[1:]]
            for line in text.splitlines() if line.startswith("| ") and "±" in line}  # the first table's rows
    dreamer, rrama, vrama = rows["Dreamer"], rows["RRAMa"], rows["VRAMa"]
    assert dreamer[8] == "4.000 ± 2.041 (4)" and dreamer[9].startswith("2.500 [")  # walk, as computed above
    assert rrama[8] == "6.000 ± 1.528 (3)" and rrama[9].startswith("6.000 [")  # s.e. = sqrt(14 / 2) / sqrt(3)
    assert dreamer[2:4] == ["7.000 ± – (1)", "7.000 [7.000, 7.000]"]  # run: one seed
    assert rrama[2:4] == ["–", "–"]  # run: no rrama
    assert rrama[4] == "2.000 ± – (1)" and rrama[6] == "5.000 ± – (1)"  # the task sequence's two tasks
    assert vrama[0] == "6.000 ± – (1)"
    # P(RRAMa > Dreamer) on walk: [4, 5, 9] against [1, 2, 3, 10]: each beats 1, 2, 3 and loses to 10 -> 9 of 12
    improvement = next(line for line in text.splitlines() if line.startswith("| RRAMa") and "[0." in line)
    cells = [c.strip() for c in improvement.strip("|").split("|")]
    assert cells[1:5] == ["–"] * 4 and cells[5].startswith("0.75 [")  # only walk has both; no uniform column
    # probabilities in 2 decimals whatever --decimals; p: 9 of 12 pairs, U = 9 of n_x·n_y = 12, the exact test's
    # P(U >= 9) = 7 of the C(7, 3) = 35 splits, two-sided 14 / 35 = 0.4
    assert cells[5].endswith("], p 0.4")
    assert "| walk__dreamer__s2 | walk | 2 | 200 | 2.000 |" in text  # the runs table (the resumed step counted once)
    assert "mixed batches" not in text  # no run logged addressing/ keys: no third table
    assert (results / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "![scores per run](scores.png)" in text and (results / "scores.png").read_bytes()[:4] == b"\x89PNG"
    # the bootstrap is seeded: the same command writes the same report
    run_script("report.py", str(results), "--reps", "500", "--decimals", "3")
    assert (results / "report.md").read_text() == text


def test_diagnostics_table_by_hand(tmp_path):
    exp = tmp_path / "exp"

    def rounds(name, rows, env_id="dmc/walker-walk"):
        run = write_run(exp, name, [1.0], {"env_id": env_id, "method": name.split("__")[1], "seed": 1})
        with open(run / "metrics.jsonl", "a") as f:
            f.write("".join(json.dumps({"step": step, **{f"addressing/{k}": v for k, v in row.items()}}) + "\n"
                            for step, row in rows))

    # rrama seed 1, two rounds -> means: mixed 0.5, walk's share 0.5 (other tasks 0.5), returns 15 / 6, chunk rewards
    # 5 / 2, entropy 1.25 of uniform's 2 = 0.625, bandit gain 4 - 1 = 3
    rounds("walk__rrama__s1", [
        (200, {"mixed_batches": 0.4, "pick_fraction/walker-walk": 0.25, "pick_fraction/walker-stand": 0.75,
               "picked_return": 10, "candidate_return": 6, "picked_chunk_reward": 4, "candidate_chunk_reward": 2,
               "entropy": 1.0, "entropy_uniform": 2.0, "bandit_reward_q": 3, "bandit_reward_uniform": 1}),
        (300, {"mixed_batches": 0.6, "pick_fraction/walker-walk": 0.75, "pick_fraction/walker-stand": 0.25,
               "picked_return": 20, "candidate_return": 6, "picked_chunk_reward": 6, "candidate_chunk_reward": 2,
               "entropy": 1.5, "entropy_uniform": 2.0, "bandit_reward_q": 5, "bandit_reward_uniform": 1})])
    # rrama seed 2, one round logged twice (a resumed run: the last line of a step wins): all picks from its own task
    own = {"pick_fraction/walker-walk": 1.0, "picked_return": 5, "candidate_return": 6, "picked_chunk_reward": 1,
           "candidate_chunk_reward": 2, "entropy": 2.0, "entropy_uniform": 2.0, "bandit_reward_q": 1,
           "bandit_reward_uniform": 1}
    rounds("walk__rrama__s2", [(200, {"mixed_batches": 0.9, **own}), (200, {"mixed_batches": 0.7, **own})])
    # uniform: picks only from walker-stand (no key for its own task: other tasks 1), nothing addressed
    rounds("walk__uniform__s1", [(200, {"mixed_batches": 0.5, "pick_fraction/walker-stand": 1.0, "picked_return": 8,
                                        "candidate_return": 7, "picked_chunk_reward": 3})])
    write_run(exp, "walk__dreamer__s1", [1.0])  # no row
    # a --task-sequence run's second task: its own task is the folder's, walker-walk
    run = write_run(exp, "seq__vrama__s1", [1.0], {"env_id": "dmc/walker-stand", "task_sequence":
                                                   "walker-stand,walker-walk", "method": "vrama", "seed": 1},
                    sub="1_walker-walk")
    with open(run / "1_walker-walk" / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"step": 200, "addressing/mixed_batches": 1.0, "addressing/pick_fraction/walker-stand": 0.4,
                            "addressing/pick_fraction/walker-walk": 0.6}) + "\n")
    runs = report.load_experiment(str(exp), "charts/episodic_return")
    lines = report.diagnostics_table(runs, ["seq/1_walker-walk", "walk"],
                                     report.method_order({r["method"] for r in runs}), 1)
    assert "| seq/1_walker-walk | VRAMa | 1 | 1.00 | 0.40 | – / – | – / – | – | – |" in lines
    rows = [line for line in lines if line.startswith("| walk")]
    # seeds averaged: mixed (0.5 + 0.7) / 2, other tasks (0.5 + 0) / 2, returns (15 + 5) / 2 / 6, chunk rewards
    # (5 + 1) / 2 / 2, entropy (0.625 + 1) / 2 = 0.8125, bandit gain (3 + 0) / 2
    assert rows == ["| walk | No addressing (uniform) | 1 | 0.50 | 1.00 | 8.0 / 7.0 | 3.0 / – | – | – |",
                    "| walk | RRAMa | 2 | 0.60 | 0.25 | 10.0 / 6.0 | 3.0 / 2.0 | 0.81 | 1.5 |"]


def test_stalled_table_by_hand(tmp_path):
    exp = tmp_path / "exp"

    def rounds(name, norms):
        run = write_run(exp, name, [1.0], {"env_id": "dmc/walker-walk", "method": name.split("__")[1], "seed": 1})
        with open(run / "metrics.jsonl", "a") as f:
            f.write("".join(json.dumps({"step": 1000 * (i + 1), "addressing/grad_norm": v}) + "\n"
                            for i, v in enumerate(norms)))

    # seed 1: first round 10, so a round stalls below 0.1: 0.05 and 0.0 do (2 of 5, first at 3,000); 0.1 does not
    rounds("walk__rrama__s1", [10.0, 2.0, 0.05, 0.1, 0.0])
    rounds("walk__rrama__s2", [1.0, 0.5, 0.02])  # below 0.01? no: none of 3 stalls
    rounds("walk__vrama__s1", [4.0, 0.01])  # 0.01 < 0.04: 1 of 2, at 2,000
    write_run(exp, "walk__uniform__s1", [1.0])  # no f_φ: no row
    runs = report.load_experiment(str(exp), "charts/episodic_return")
    assert report.stalled_rounds(runs[0]["metrics_path"]) == (0.4, 3000)
    lines = report.stalled_table(runs, ["walk"], report.method_order({r["method"] for r in runs}))
    rows = [line for line in lines if line.startswith("| walk")]
    assert rows == ["| walk | RRAMa | 2 | 0.20 | 3,000; – |", "| walk | VRAMa | 1 | 0.50 | 2,000 |"]  # (0.4 + 0) / 2
    assert report.stalled_table([r for r in runs if r["method"] == "uniform"], ["walk"], ["uniform"]) == []


def test_pick_source_table_by_hand(tmp_path):
    exp = tmp_path / "exp"
    for name, rows in [("box__rrama__s1", [{"expert": 0.2, "random": 0.8}, {"expert": 0.6, "random": 0.4}]),
                       ("box__rrama__s2", [{"expert": 1.0}]),  # no random pick: a share of 0
                       ("box__uniform__s1", [{"expert": 0.5, "random": 0.5}])]:
        run = write_run(exp, name, [1.0], {"env_id": "kitchen/bluebox", "method": name.split("__")[1], "seed": 1})
        with open(run / "metrics.jsonl", "a") as f:
            f.write("".join(json.dumps({"step": 100 * (i + 2), **{f"addressing/pick_source/{k}": v
                                                                  for k, v in row.items()}}) + "\n"
                            for i, row in enumerate(rows)))
    write_run(exp, "box__dreamer__s1", [1.0])
    runs = report.load_experiment(str(exp), "charts/episodic_return")
    lines = report.pick_source_table(runs, ["box"], report.method_order({r["method"] for r in runs}))
    assert "| task | method | runs | expert | random |" in lines
    # RRAMa: seed 1's means 0.4 / 0.6, seed 2's 1.0 / 0 -> 0.70 / 0.30
    assert [line for line in lines if line.startswith("| box")] == [
        "| box | No addressing (uniform) | 1 | 0.50 | 0.50 |", "| box | RRAMa | 2 | 0.70 | 0.30 |"]
    assert report.pick_source_table([r for r in runs if r["method"] == "dreamer"], ["box"], ["dreamer"]) == []


def test_pick_task_table_by_hand_and_only_for_three_tasks(tmp_path):
    """The picks' tasks, per cell: shown where M holds three tasks (walk -> run: stand, walk and run's own), not
    where it holds two (the diagnostics table's "from other tasks" says that)."""
    exp = tmp_path / "exp"
    for name, rows in [("walk_run__rrama__s1", [{"walker-stand": 0.8, "walker-walk": 0.2},
                                                {"walker-stand": 0.4, "walker-walk": 0.4, "walker-run": 0.2}]),
                       ("walk_run__rrama__s2", [{"walker-stand": 0.5, "walker-walk": 0.5}])]:
        run = write_run(exp, name, [1.0], {"env_id": "dmc/walker-run", "method": "rrama", "seed": 1})
        with open(run / "metrics.jsonl", "a") as f:
            f.write("".join(json.dumps({"step": 100 * (i + 2), **{f"addressing/pick_fraction/{k}": v
                                                                  for k, v in row.items()}}) + "\n"
                            for i, row in enumerate(rows)))
    runs = report.load_experiment(str(exp), "charts/episodic_return")
    lines = report.pick_task_table(runs, ["walk_run"], ["rrama"])
    assert "| task | method | runs | walker-run | walker-stand | walker-walk |" in lines
    # seed 1's means: run 0.2 (one round logged it), stand 0.6, walk 0.3; seed 2's 0, 0.5, 0.5 -> 0.10, 0.55, 0.40
    assert [line for line in lines if line.startswith("| walk_run")] == [
        "| walk_run | RRAMa | 2 | 0.10 | 0.55 | 0.40 |"]
    two = [r for r in runs if r["name"].endswith("s2")]  # two tasks (stand, walk): no table
    assert report.pick_task_table(two, ["walk_run"], ["rrama"]) == []


def test_scores_figure_draws_each_seed_in_the_tables_order(tmp_path):
    """scores.png: per task, the methods in the tables' order (those with runs there), each with its seeds' numbers."""
    scores = {("walk", "dreamer"): [1.0, 2.0], ("walk", "rrama"): [4.0], ("run", "rrama"): [7.0, 9.0, 8.0]}
    methods = report.method_order({m for _, m in scores})
    drawn = report.plot_scores(scores, ["run", "walk"], methods, "t", "charts/episodic_return", tmp_path / "s.png")
    assert drawn == {"run": [("rrama", [7.0, 9.0, 8.0])], "walk": [("dreamer", [1.0, 2.0]), ("rrama", [4.0])]}
    assert (tmp_path / "s.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_report_out_folder_and_errors(results, tmp_path):
    run_script("report.py", str(results), "--out", str(tmp_path / "docs"), "--reps", "100")
    assert sorted(os.listdir(tmp_path / "docs")) == ["curves.png", "report.md", "scores.png"]
    made_by = f"`python report.py {results} --reps 100 --out {tmp_path / 'docs'}`"  # says where it went, too
    assert made_by in (tmp_path / "docs" / "report.md").read_text()
    proc = run_script("report.py", str(tmp_path / "nothing"), check=False)
    assert proc.returncode != 0 and "no such folder" in proc.stderr


def test_runs_curves_write_a_png(tmp_path):  # what plot_curves.py did
    run = write_run(tmp_path, "run", [1.0, 2.0, 3.0, 4.0])
    with open(run / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"step": 400, "eval/episodic_return": 3.5}) + "\n")
    out = tmp_path / "curve.png"
    run_script("report.py", "--runs", str(run), "--out", str(out))
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_runs_curves_draw_a_panel_per_key_and_name_a_missing_one(tmp_path):
    """--runs with --key: one panel per metric (here the KL and the imagined return), a key no run logs named."""
    import matplotlib.image

    run = write_run(tmp_path, "run", [1.0, 2.0, 3.0, 4.0])
    with open(run / "metrics.jsonl", "a") as f:
        for step in (100, 200, 300):
            f.write(json.dumps({"step": step, "losses/kl": step / 50, "charts/imagined_return": step / 10}) + "\n")
    one, two = tmp_path / "one.png", tmp_path / "two.png"
    run_script("report.py", "--runs", str(run), "--key", "losses/kl", "--out", str(one))
    run_script("report.py", "--runs", str(run), "--key", "losses/kl", "charts/imagined_return", "--out", str(two))
    width_one, width_two = (matplotlib.image.imread(str(p)).shape[1] for p in (one, two))
    assert width_two > 1.2 * width_one  # two panels side by side
    proc = run_script("report.py", "--runs", str(run), "--key", "losses/nothing", check=False)
    assert proc.returncode != 0 and "--key losses/nothing" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    proc = run_script("report.py", str(tmp_path), "--key", "a", "b", check=False)
    assert proc.returncode != 0 and "several only with --runs" in proc.stderr


def test_runs_curves_name_a_bad_folder(tmp_path):
    proc = run_script("report.py", "--runs", str(tmp_path), check=False)
    assert proc.returncode != 0 and str(tmp_path) in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_preset_runs_are_their_own_rows_beside_another_experiment(tmp_path):
    """Runs made with --preset P are method@P rows, compared with uniform mixing under the same preset too; --beside
    adds another experiment's runs of the same tasks (here the paper-text rows), and no other task."""
    authors, paper = tmp_path / "results" / "authors", tmp_path / "results" / "paper"
    preset = {"env_id": "dmc/x", "seed": 1, "preset": "authors-code"}
    write_run(authors, "walk__uniform__s1", [1.0], {**preset, "method": "uniform"})
    write_run(authors, "walk__rrama__s1", [3.0], {**preset, "method": "rrama"})
    write_run(paper, "walk__uniform__s1", [2.0], {"env_id": "dmc/x", "method": "uniform", "seed": 1})
    write_run(paper, "run__uniform__s1", [9.0], {"env_id": "dmc/x", "method": "uniform", "seed": 1})  # not in authors
    other = tmp_path / "results" / "other"  # a second --beside folder: its runs join too
    write_run(other, "walk__uniform__s2", [2.5], {"env_id": "dmc/x", "method": "uniform", "seed": 2})
    run_script("report.py", str(authors), "--beside", str(paper), str(other), "--reps", "200", "--decimals", "2")
    text = (authors / "report.md").read_text()
    rows = [line.split("|")[1].strip() for line in text.splitlines()
            if line.startswith("| ") and "±" in line and not line.startswith("| method")]
    assert rows == ["No addressing (uniform)", "No addressing (uniform), authors' code", "RRAMa, authors' code"]
    assert "| run__" not in text and "run: mean" not in text  # walk only
    assert f"`python report.py {authors} --reps 200 --decimals 2 --beside {paper} {other}`" in text  # re-runnable
    assert "| walk__uniform__s1 | walk |" in text and "| paper/walk__uniform__s1 | walk |" in text  # the Runs table
    assert "| other/walk__uniform__s2 | walk |" in text and "| 2.25 ± 0.25 (2) |" in text
    header = next(line for line in text.splitlines() if line.startswith("| method") and "P(>" in line)
    assert header.count("P(>") == 2 and "P(> No addressing (uniform), authors' code)" in header
    rrama = next(line for line in text.splitlines() if line.startswith("| RRAMa, authors' code") and "[" in line
                 and "±" not in line)
    cells = [c.strip() for c in rrama.strip("|").split("|")]
    assert cells[1].startswith("1.00 [") and cells[2].startswith("1.00 [")  # 3 beats 2 and 1
    # 1 run against 2 (2 of C(3, 1) = 3 splits as extreme) and against 1: no evidence either way
    assert cells[1].endswith(", p 0.67") and cells[2].endswith(", p 1")
    # --against adds a column: RRAMa under the preset against itself is "–", uniform against it 0.00 (1 below 3)
    run_script("report.py", str(authors), "--against", "rrama@authors-code", "--reps", "200")
    text = (authors / "report.md").read_text()
    assert f"`python report.py {authors} --reps 200 --against rrama@authors-code`" in text
    header = next(line for line in text.splitlines() if line.startswith("| method") and "P(>" in line)
    assert header.count("P(>") == 2 and header.endswith("walk: P(> RRAMa, authors' code) |")
    uniform = next(line for line in text.splitlines() if line.startswith("| No addressing (uniform), authors' code")
                   and "±" not in line)
    assert [c.strip() for c in uniform.strip("|").split("|")][1:] == ["–", "0.00 [0.00, 0.00], p 1"]
    bad = run_script("report.py", str(authors), "--against", "vrama", check=False)
    assert bad.returncode != 0 and "--against vrama: no such method" in bad.stderr
    for flags in (["--runs", str(authors / "walk__rrama__s1")], [str(tmp_path / "results")]):  # not one experiment
        bad = run_script("report.py", *flags, "--against", "uniform", check=False)
        assert bad.returncode != 0 and "--against" in bad.stderr.strip().splitlines()[-1]
    bad = run_script("report.py", str(authors), "--beside", str(tmp_path / "nope"), check=False)
    assert bad.returncode != 0 and "--beside" in bad.stderr and "no run folders" in bad.stderr
    assert report.method_order({"rrama@authors-code", "dreamer", "uniform@authors-code", "uniform"}) == [
        "dreamer", "uniform", "uniform@authors-code", "rrama@authors-code"]


def test_reference_table_and_band_by_hand(tmp_path):
    """--reference: each run's eval return at its logged step nearest a checkpoint (within 10%) against the
    reference's mean ± 2 std; a task with no reference curve gets no rows; a reference of another key is refused."""
    exp = tmp_path / "results" / "pixels"
    for seed, (at_100k, at_200k) in enumerate([(300.0, 700.0), (100.0, 760.0), (480.0, 0.0)], 1):
        run = exp / f"stand__dreamer__s{seed}"
        run.mkdir(parents=True)
        (run / "args.json").write_text(json.dumps({"env_id": "dmc/walker-stand", "method": "dreamer", "seed": seed}))
        rows = [{"step": 100_000, "eval/episodic_return": at_100k}, {"step": 200_000, "eval/episodic_return": at_200k}]
        if seed == 3:  # stopped early: its second evaluation is at 150k, over 10% from 205k, and is not used
            rows[1]["step"] = 150_000
        (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    write_run(exp, "other__dreamer__s1", [5.0], {"env_id": "dmc/hop", "method": "dreamer", "seed": 1})
    with open(exp / "other__dreamer__s1" / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"step": 100, "eval/episodic_return": 5.0}) + "\n")
    reference = tmp_path / "reference.json"
    reference.write_text(json.dumps({
        "name": "Dreamer v1", "key": "eval/episodic_return", "checkpoints": [105_000, 205_000], "source": "a test",
        "tasks": {"walker-stand": {"steps": [5000, 105_000, 205_000], "mean": [0.0, 315.0, 723.0],
                                   "std": [1.0, 70.0, 90.0], "seeds": [5, 5, 5]}}}))
    run_script("report.py", str(exp), "--key", "eval/episodic_return", "--reference", str(reference), "--reps", "50")
    text = (exp / "report.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| stand |") and "Dreamer" in line and "," in line]
    # 105k: 300, 100, 480 -> mean 293.3, population std sqrt((6.67² + 193.33² + 186.67²) / 3) = sqrt(24088.9) = 155.2;
    # within 315 ± 140 = [175, 455]: 300 only. 205k: 700 and 760 (at 200k) -> 730.0 ± 30.0, both in [543, 903]
    assert rows == ["| stand | Dreamer | 105,000 | 293.3 ± 155.2 (3) | 100,000 | 315.0 ± 70.0 (5) | 1 of 3 |",
                    "| stand | Dreamer | 205,000 | 730.0 ± 30.0 (2) | 200,000 | 723.0 ± 90.0 (5) | 2 of 2 |"]
    assert "| other |" not in text.split("## Against Dreamer v1")[1].split("## Runs")[0]
    assert (exp / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    wrong = run_script("report.py", str(exp), "--reference", str(reference), check=False)  # the default key
    assert wrong.returncode != 0 and "give --key eval/episodic_return" in wrong.stderr
    assert len(wrong.stderr.strip().splitlines()) == 1


def test_reference_table_with_a_binned_reference(tmp_path):
    """A reference binned over windows ("window": Dreamer v1's scores are means over the 100k env steps up to each
    step): each run is averaged over its evaluations in the same window before the seeds are."""
    exp = tmp_path / "results" / "pixels"
    for seed, evals in enumerate([[100.0, 200.0, 300.0, 400.0, 500.0], [50.0, 50.0, 50.0, 50.0, 300.0]], 1):
        run = exp / f"stand__dreamer__s{seed}"
        run.mkdir(parents=True)
        (run / "args.json").write_text(json.dumps({"env_id": "dmc/walker-stand", "method": "dreamer", "seed": seed}))
        rows = [{"step": 20_000 * (i + 1), "eval/episodic_return": v} for i, v in enumerate(evals)]  # 20k..100k
        (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    reference = tmp_path / "reference.json"
    reference.write_text(json.dumps({
        "name": "Dreamer v1", "key": "eval/episodic_return", "checkpoints": [105_000, 205_000], "window": 100_000,
        "source": "a test", "tasks": {"walker-stand": {"steps": [5000, 105_000, 205_000], "mean": [0.0, 315.0, 723.0],
                                                       "std": [1.0, 70.0, 90.0], "seeds": [5, 5, 5]}}}))
    run_script("report.py", str(exp), "--key", "eval/episodic_return", "--reference", str(reference), "--reps", "50")
    text = (exp / "report.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| stand |") and "Dreamer" in line and "," in line]
    # seed 1: (100 + 200 + 300 + 400 + 500) / 5 = 300, in [175, 455]; seed 2: 500 / 5 = 100, not: mean 200 ± 100
    assert rows == ["| stand | Dreamer | 105,000 | 200.0 ± 100.0 (2) | 20,000, 40,000, 60,000, 80,000, 100,000 | "
                    "315.0 ± 70.0 (5) | 1 of 2 |"]  # no evaluation in (105k, 205k]: no row
    assert "in the 100,000 env steps up to each checkpoint" in text


@pytest.mark.slow
def test_levels_table_and_lines_by_hand(tmp_path):
    """--levels: each run's mean over its last 10 values against fixed policies' levels, and the fraction of the way
    from the random policy's level to the expert's; a task without levels gets no rows; a bad file is refused."""
    exp = tmp_path / "results" / "families"
    write_run(exp, "box__dreamer__s1", [100.0] * 5 + [10.0] * 10)  # last 10: 10
    write_run(exp, "box__dreamer__s2", [30.0] * 3)  # fewer than 10 values: all of them, 30
    write_run(exp, "reach__dreamer__s1", [1.0])
    levels = tmp_path / "references.json"
    levels.write_text(json.dumps({"box": {"random": {"return": 0.0, "return_se": 0.0, "episodes": 10},
                                          "expert": {"return": 50.0, "return_se": 0.5, "episodes": 10,
                                                     "success_rate": 1.0}}}))
    run_script("report.py", str(exp), "--levels", str(levels), "--reps", "50")
    text = (exp / "report.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| box | Dreamer |")]
    # mean of 10 and 30 = 20, s.e. = std(ddof 1) / sqrt(2) = 14.142 / 1.414 = 10; (20 - 0) / (50 - 0) = 0.40
    assert rows == ["| box | Dreamer | 20.0 ± 10.0 (2) | 1,500, 300 | random 0.0 ± 0.0 (10), expert 50.0 ± 0.5 (10) | "
                    "0.40 |"]
    assert "| reach |" not in text.split("## Against fixed policies")[1].split("## Runs")[0]
    assert f"--levels {levels}" in text and (exp / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # success_rate: only the expert has that level (no s.e. given: nan), so the random -> expert fraction is absent
    success = report.task_levels(json.loads(levels.read_text()), "box", "charts/success_rate")
    assert list(success) == ["expert"] and success["expert"][::2] == (1.0, 10) and np.isnan(success["expert"][1])
    for wrong in ("[1, 2]", '{"box": {"random": 0.0}}'):  # not task -> policy -> {metric: value}
        levels.write_text(wrong)
        bad = run_script("report.py", str(exp), "--levels", str(levels), check=False)
        assert bad.returncode != 0
        assert bad.stderr.strip() == f"error: --levels {levels}: not a levels file (AssertionError)"


def test_unfinished_runs_are_marked_and_non_finite_ones_left_out(tmp_path):
    """A run whose last step is below its --total-steps counts, marked in both tables; one with a NaN return would
    blank its cells, so it is left out with a warning."""
    exp = tmp_path / "results" / "exp"
    for seed, returns in ((1, [1.0, 3.0]), (2, [5.0])):  # seed 2 stopped at step 100 of 200
        write_run(exp, f"walk__dreamer__s{seed}", returns, {"env_id": "dmc/x", "method": "dreamer",
                                                          "seed": seed, "total_steps": 200})
    first = exp / "walk__dreamer__s1" / "metrics.jsonl"  # its losses/kl as a per-round key: none after the last round
    first.write_text("".join(line + "\n" for line in first.read_text().splitlines() if "losses/kl\": 1.0}" not in line
                             or not line.startswith('{"step": 200')))
    write_run(exp, "walk__dreamer__s3", [float("nan"), 1.0], {"env_id": "dmc/x", "method": "dreamer", "seed": 3})
    out = run_script("report.py", str(exp), "--reps", "100")
    assert "walk__dreamer__s2/metrics.jsonl: stopped at step 100 of --total-steps 200: marked unfinished" in out.stderr
    assert "walk__dreamer__s3/metrics.jsonl: a non-finite charts/episodic_return, left out" in out.stderr
    text = (exp / "report.md").read_text()
    assert "| Dreamer | 3.5 ± 1.5 (2; 1 unfinished) |" in text  # (1 + 3) / 2 = 2 and 5: mean 3.5, s.e. 1.5
    assert "| walk__dreamer__s2 | walk | 1 | 100 (unfinished: stopped at 100 of 200) | 5.0 |" in text
    assert "| walk__dreamer__s1 | walk | 2 | 200 | 2.0 |" in text and "s3" not in text
    # finished is read from the last step of any key: a per-round key ends before the last episode's step
    out = run_script("report.py", str(exp), "--reps", "100", "--key", "losses/kl")
    assert "walk__dreamer__s1/metrics.jsonl: stopped" not in out.stderr and "walk__dreamer__s2" in out.stderr
    text = (exp / "report.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| walk__dreamer__s1 |")]
    assert rows and all("unfinished" not in row for row in rows)
    assert any("unfinished" in line for line in text.splitlines() if line.startswith("| walk__dreamer__s2 |"))


def test_results_root_with_a_run_folder_beside_the_experiments(tmp_path):
    """`report.py results`: every experiment's report, though results/ also keeps a run folder of its own (as
    results/gpu_pixel_cartpole is), which is left out with a line, not taken for the one experiment."""
    root = tmp_path / "results"
    write_run(root / "exp", "walk__dreamer__s1", [1.0, 3.0])
    write_run(root, "single_run", [2.0])
    out = run_script("report.py", str(root), "--reps", "50")
    left_out = f"left out, run folders rather than experiments (report them with --runs): {root / 'single_run'}"
    assert left_out in out.stderr
    assert (root / "exp" / "report.md").exists() and not (root / "report.md").exists()


def test_a_linked_run_folder_counts_in_its_own_cell_and_a_dangling_link_is_not_read(tmp_path):
    """One run in two tables (the walker tables' Dreamer row): a link named for another cell is read as the run it
    names, in that cell; a link to a run not made yet is skipped."""
    exp = tmp_path / "exp"
    write_run(exp, "walk__dreamer__s1", [1.0, 3.0])
    os.symlink("walk__dreamer__s1", exp / "stand_walk__dreamer__s1")
    os.symlink("walk__dreamer__s2", exp / "stand_walk__dreamer__s2")  # not made yet
    runs = report.load_experiment(str(exp), "charts/episodic_return")
    assert sorted((r["task"], r["seed"], list(r["values"])) for r in runs) == [
        ("stand_walk", 1, [1.0, 3.0]), ("walk", 1, [1.0, 3.0])]


def test_tasks_keep_only_the_named_columns_and_name_a_missing_one(results, tmp_path):
    """--tasks: the tables' columns alone (an experiment folder also keeps its pilots' and its Ms' runs), by name or by
    a shell-style pattern; the "Made by" line repeats it, quoted; a pattern matching no task is one line naming it."""
    out = tmp_path / "only"
    run_script("report.py", str(results), "--tasks", "walk", "dmc/*", "--reps", "50", "--out", str(out))
    text = (out / "report.md").read_text()
    header = next(line for line in text.splitlines() if line.startswith("| method |"))
    assert "walk: mean" in header and "dmc/hop: mean" in header
    assert "run: mean" not in header and "seq/" not in header
    dreamer = next(line for line in text.splitlines() if line.startswith("| Dreamer |"))
    assert dreamer.startswith("| Dreamer | – | – | 4.0 ± 2.0 (4) |")  # dmc/hop has none; walk's seeds 1, 2, 3, 10
    assert "run__dreamer__s1" not in text and "seq__rrama__s1" not in text  # nor in the Runs table
    assert f"`python report.py {results} --reps 50 --tasks walk 'dmc/*' --out {out}`" in text
    bad = run_script("report.py", str(results), "--tasks", "wlak", check=False)
    assert bad.returncode != 0 and "--tasks wlak: no such task" in bad.stderr and "walk" in bad.stderr
    other = write_run(tmp_path / "results" / "other", "walk__dreamer__s1", [1.0]).parent
    two = run_script("report.py", str(results), str(other), "--tasks", "walk", check=False)
    assert two.returncode != 0 and "--tasks: give one experiment folder" in two.stderr
    assert not (results / "report.md").exists()  # refused before any report was written


def test_methods_keep_only_the_named_rows_and_name_a_missing_one(results, tmp_path):
    """--methods: the tables' rows and the curves' lines alone (the headline figure's paper rows), in the paper's order
    whatever the order given; a task left with no run is dropped; --title names the curves; the "Made by" line repeats
    both; a method not in the folder is one line naming it, before anything is written."""
    out = tmp_path / "rows"
    run_script("report.py", str(results), "--methods", "rrama", "dreamer", "--title", "two rows", "--reps", "50",
               "--out", str(out))
    text = (out / "report.md").read_text()
    rows = [line.split(" | ")[0] for line in text.splitlines()
            if line.startswith("| ") and "±" in line and not line.startswith("| method")]
    assert rows == ["| Dreamer", "| RRAMa"]  # no vrama row; the paper's order
    header = next(line for line in text.splitlines() if line.startswith("| method |"))
    assert "walk: mean" in header and "run: mean" in header and "dmc/hop" not in header  # dmc/hop: vrama alone
    assert "dmc_hop__x__vrama__1__123" not in text  # nor in the Runs table
    assert f"`python report.py {results} --reps 50 --methods rrama dreamer --title 'two rows' --out {out}`" in text
    assert (out / "curves.png").stat().st_size > 0
    bad = run_script("report.py", str(results), "--methods", "dreamer", "rrma", "--out", str(tmp_path / "bad"),
                     check=False)
    assert bad.returncode != 0 and "--methods rrma: no such method" in bad.stderr and "rrama" in bad.stderr
    assert "Traceback" not in bad.stderr and not (tmp_path / "bad").exists()
    left_out = run_script("report.py", str(results), "--methods", "dreamer", "--against", "rrama", check=False)
    assert left_out.returncode != 0 and "--against rrama: no such method" in left_out.stderr  # not among the rows
    with_runs = run_script("report.py", "--runs", str(results / "walk__dreamer__s1"), "--methods", "dreamer",
                           check=False)
    assert with_runs.returncode != 0 and "--methods" in with_runs.stderr


def test_same_task_puts_a_presets_cell_beside_the_task_it_ran(tmp_path):
    """--same-task walk_authors=walk: a cell of --preset runs (one spec names its cells apart) joins walk's columns, its
    rows kept apart by the preset in their method's name, so they meet walk's Dreamer and uniform in the P(>) table;
    a cell not there yet is a warning; a malformed pair, and a merge that would make two runs one, are each one line."""
    exp = tmp_path / "results" / "exp"
    write_run(exp, "walk__dreamer__s1", [1.0])
    write_run(exp, "walk__uniform__s1", [3.0], {"env_id": "dmc/x", "method": "uniform", "seed": 1})
    write_run(exp, "walk_authors__uniform__s1", [2.0],
              {"env_id": "dmc/x", "method": "uniform", "seed": 1, "preset": "authors-code"})
    run_script("report.py", str(exp), "--same-task", "walk_authors=walk", "--reps", "50")
    text = (exp / "report.md").read_text()
    header = next(line for line in text.splitlines() if line.startswith("| method |"))
    assert "walk: mean" in header and "walk_authors" not in header  # one task, not two
    authors = next(line for line in text.splitlines() if line.startswith("| No addressing (uniform), authors' code")
                   and "±" not in line)
    assert [c.strip() for c in authors.strip("|").split("|")][1:3] == ["1.00 [1.00, 1.00], p 1",
                                                                       "0.00 [0.00, 0.00], p 1"]  # 2 > 1, 2 < 3
    assert "| walk_authors__uniform__s1 | walk |" in text  # the Runs table names the run and its merged task
    assert f"`python report.py {exp} --reps 50 --same-task walk_authors=walk`" in text
    # a cell not run yet (a grid fills in parts, the command stays the same): a warning naming it, the report made
    missing = run_script("report.py", str(exp), "--same-task", "walk_authors=walk", "stand_authors=stand")
    assert "warning: --same-task stand_authors=stand: no task stand_authors" in missing.stderr
    assert "walk_authors" not in next(line for line in (exp / "report.md").read_text().splitlines()
                                      if line.startswith("| method |"))
    malformed = run_script("report.py", str(exp), "--same-task", "walk_authors", check=False)
    assert malformed.returncode != 0 and "--same-task walk_authors: give CELL=TASK" in malformed.stderr
    write_run(exp, "walk_other__uniform__s1", [5.0], {"env_id": "dmc/x", "method": "uniform", "seed": 1})  # no preset
    clash = run_script("report.py", str(exp), "--same-task", "walk_other=walk", check=False)
    assert clash.returncode != 0 and "would be the same run of walk" in clash.stderr
    assert "Traceback" not in missing.stderr + malformed.stderr + clash.stderr
    # a preset's cell in a --beside folder is renamed too, so it joins walk's columns rather than being left out
    other = tmp_path / "results" / "other"
    write_run(other, "walk_authors__rrama__s1", [4.0],
              {"env_id": "dmc/x", "method": "rrama", "seed": 1, "preset": "authors-code"})
    shutil.rmtree(exp / "walk_other__uniform__s1")  # the clashing cell above, out of the way
    run_script("report.py", str(exp), "--same-task", "walk_authors=walk", "--beside", str(other), "--reps", "50")
    assert "| other/walk_authors__rrama__s1 | walk |" in (exp / "report.md").read_text()


def test_welch_interval_by_hand():
    """mean(X) − mean(Y) with its 95% Welch t interval: d ± t(0.975, ν) · se, se² = s_x²/n_x + s_y²/n_y,
    ν = se⁴ / ((s_x²/n_x)² / (n_x − 1) + (s_y²/n_y)² / (n_y − 1))."""
    # [5, 6, 7] against [1, 2, 3]: d = 4; each sample variance 1, se² = 1/3 + 1/3 = 2/3;
    # ν = (4/9) / (2 · (1/9) / 2) = 4; t(0.975, 4) = 2.776445 (a t table), so 4 ± 2.776445 · 0.816497 = 4 ± 2.266958
    assert report.welch_ci([5, 6, 7], [1, 2, 3]) == pytest.approx((4.0, 1.733042, 6.266958), abs=1e-6)
    assert report.welch_ci([1, 2, 3], [5, 6, 7]) == pytest.approx((-4.0, -6.266958, -1.733042), abs=1e-6)
    # unequal variances and sizes: [4, 5, 9] (mean 6, s² = 14 / 2 = 7) against [1, 2, 3, 10] (mean 4, s² = 50 / 3):
    # se² = 7/3 + 50/12 = 6.5; ν = 6.5² / ((7/3)² / 2 + (50/12)² / 3) = 42.25 / 8.509259 = 4.965180, between the t
    # table's ν = 4 (2.7764) and ν = 5 (2.5706): t(0.975, 4.965180) = 2.576014 (scipy.stats.t), 2 ± 2.576014 · 2.549510
    from scipy.stats import t

    assert t.ppf(0.975, 4.965180) == pytest.approx(2.576014, abs=1e-6) and 2.5706 < 2.576014 < 2.7764
    half = 2.576014 * np.sqrt(6.5)
    assert report.welch_ci([4, 5, 9], [1, 2, 3, 10]) == pytest.approx((2.0, 2.0 - half, 2.0 + half), abs=1e-4)
    # one run on a side, or no spread on either: the difference alone
    d, low, high = report.welch_ci([7.0], [1, 2, 3])
    assert d == 5.0 and np.isnan(low) and np.isnan(high)
    assert np.isnan(report.welch_ci([2.0, 2.0], [1.0, 1.0])[1])


@pytest.mark.slow
def test_report_gives_and_prints_the_welch_differences(results, tmp_path):
    """The third table: each row's mean minus Dreamer's (and a preset's row minus the same method's under the paper's
    text), with the Welch interval above; report.py prints each difference as one line."""
    half = 2.576014 * np.sqrt(6.5)  # walk, RRAMa [4, 5, 9] against Dreamer [1, 2, 3, 10]: see the test above
    proc = run_script("report.py", str(results), "--reps", "50", "--decimals", "3")
    text = (results / "report.md").read_text()
    header = next(line for line in text.splitlines() if line.startswith("| method") and "− Dreamer" in line)
    columns = [c.strip() for c in header.strip("|").split("|")]
    rrama = next(line for line in text.splitlines() if line.startswith("| RRAMa |") and "+2.000 [" in line)
    cell = [c.strip() for c in rrama.strip("|").split("|")][columns.index("walk: − Dreamer")]
    assert cell == f"+2.000 [{2 - half:.3f}, {2 + half:.3f}]"
    assert f"walk: RRAMa − Dreamer: +2.000 [{2 - half:.3f}, {2 + half:.3f}] (Welch 95%)" in proc.stdout
    # --preset rows: against uniform mixing and against the same method without the preset ("paper text")
    exp = tmp_path / "presets" / "exp"
    for seed, (paper, authors) in enumerate([(1.0, 5.0), (2.0, 6.0), (3.0, 7.0)], start=1):
        write_run(exp, f"walk__rrama__s{seed}", [paper], {"env_id": "dmc/x", "method": "rrama", "seed": seed})
        write_run(exp, f"walk__uniform__s{seed}", [paper], {"env_id": "dmc/x", "method": "uniform", "seed": seed})
        write_run(exp, f"walk_authors__rrama__s{seed}", [authors],
                  {"env_id": "dmc/x", "method": "rrama", "seed": seed, "preset": "authors-code"})
    proc = run_script("report.py", str(exp), "--same-task", "walk_authors=walk", "--reps", "50")
    assert "walk: RRAMa, authors' code − RRAMa (paper text): +4.0 [1.7, 6.3] (Welch 95%)" in proc.stdout
    text = (exp / "report.md").read_text()
    header = next(line for line in text.splitlines() if line.startswith("| method") and "− paper text" in line)
    row = next(line for line in text.splitlines() if line.startswith("| RRAMa, authors' code |") and "[1.7" in line)
    cells = lambda line: [c.strip() for c in line.strip("|").split("|")]  # noqa: E731
    assert dict(zip(cells(header), cells(row))) == {"method": "RRAMa, authors' code",
                                                    "walk: − No addressing (uniform)": "+4.0 [1.7, 6.3]",
                                                    "walk: − paper text": "+4.0 [1.7, 6.3]"}
    # the P(X > Y) table has the same columns: [5, 6, 7] above [1, 2, 3], p = 2 / C(6, 3) = 0.1
    header = next(line for line in text.splitlines() if line.startswith("| method") and "P(> paper text)" in line)
    row = next(line for line in text.splitlines() if line.startswith("| RRAMa, authors' code |") and "p 0.1" in line)
    assert dict(zip(cells(header), cells(row)))["walk: P(> paper text)"] == "1.00 [1.00, 1.00], p 0.1"


@pytest.mark.slow
def test_bad_command_line_input_is_one_line_and_exit_2(results):
    """A bad value, an unknown flag, a missing value: one `error: --flag: ...` line on stderr, exit code 2, and no
    report written."""
    cases = {("--reps", "abc"): "error: --reps: invalid int value: 'abc'",
             ("--bins", "0"): "error: --bins: must be >= 1 (got 0)",
             ("--decimals", "-1"): "error: --decimals: must be >= 0 (got -1)",
             ("--no-such-flag",): "error: --no-such-flag: unknown flag (known: --out, --runs, ",
             ("--out",): "error: --out: expected one argument",
             ("--same-task", "walk"): "error: --same-task walk: give CELL=TASK"}
    for flags, line in cases.items():
        proc = run_script("report.py", str(results), *flags, check=False)
        assert proc.returncode == 2, (flags, proc.stderr)
        assert proc.stderr.startswith(line) and len(proc.stderr.strip().splitlines()) == 1, (flags, proc.stderr)
        assert not (results / "report.md").exists() and proc.stdout == ""


def test_posture_by_hand(tmp_path):
    """tools/posture.py: per part, the mean return, torso height (state index 14), share of steps above 1.2 and forward
    speed (index 16) over obs[1:] (obs[0] is the reset's); a folder without walker episodes is one line."""
    from tools.posture import posture

    for i, (height, speed) in enumerate([(1.0, 0.5), (1.4, 1.5), (2.0, -1.0)]):
        obs = np.zeros((3, 24), np.float32)  # T = 2 steps after the reset
        obs[0, 14], obs[1:, 14], obs[1:, 16] = 9.0, [height, 1.0], speed  # the reset's height is not counted
        np.savez(tmp_path / f"{i:06d}-2.npz", obs=obs, reward=np.array([0.0, i, 1.0], np.float32))
    files = sorted(str(p) for p in tmp_path.glob("*.npz"))
    rows = posture(files, parts=2)  # [0, 1] and [2]
    assert [(r["first"], r["last"]) for r in rows] == [(0, 1), (2, 2)]
    assert rows[0]["return"] == pytest.approx((1.0 + 2.0) / 2) and rows[1]["return"] == pytest.approx(3.0)
    assert rows[0]["height"] == pytest.approx((1.0 + 1.2) / 2) and rows[1]["height"] == pytest.approx(1.5)
    assert rows[0]["above_1.2"] == pytest.approx(0.25) and rows[1]["above_1.2"] == pytest.approx(0.5)
    assert rows[0]["speed"] == pytest.approx(1.0) and rows[1]["speed"] == pytest.approx(-1.0)
    assert len(posture(files, parts=10)) == 1  # fewer files than parts: one part
    out = run_script("tools/posture.py", str(tmp_path), "--parts", "3").stdout.splitlines()
    assert out[1] == "episodes   1-  1: return    2.0, torso height 1.20 (above 1.2: 50%), forward speed 1.50 m/s"
    bad = run_script("tools/posture.py", str(tmp_path / "none"), check=False)
    assert bad.returncode != 0 and bad.stderr.strip() == f"error: {tmp_path / 'none'}: no episode files (*.npz) there"
    bad = run_script("tools/posture.py", str(tmp_path), "--parts", "0", check=False)
    assert bad.returncode != 0 and bad.stderr.strip() == "error: --parts must be >= 1 (got 0)"
