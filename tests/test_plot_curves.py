import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_plot_curves_writes_a_png(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    rows = [{"step": 1000 * i, "charts/episodic_return": float(i)} for i in range(1, 5)]
    rows.append({"step": 4000, "eval/episodic_return": 3.5})
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = tmp_path / "curve.png"
    subprocess.run([sys.executable, os.path.join(ROOT, "plot_curves.py"), str(run), "--out", str(out)], check=True)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_plot_curves_names_a_bad_folder(tmp_path):
    proc = subprocess.run([sys.executable, os.path.join(ROOT, "plot_curves.py"), str(tmp_path)],
                          capture_output=True, text=True)
    assert proc.returncode != 0 and str(tmp_path) in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
