"""Progress a person can see (issue 15): inside a round of C updates the bar ticks per update, and plain-log mode
(no terminal, or --plain-log) prints a line with updates/s and the round's ETA at least every
--log-interval-seconds."""
import glob
import os
import re

import pytest
import torch

import rama_dreamer as rd
from helpers import TINY, run_script


def test_round_line_says_speed_and_time_left():
    assert rd.round_line(1000, 2000, 25, 100, 50.0) == \
        "step 1000/2000 | update 25/100 of this round | 0.5 updates/s | round ETA 02:30"


def test_negative_log_interval_is_refused():
    args = rd.resolve_defaults(rd.Args(env_id="dmc/cartpole-balance", obs_type="state", device="cpu",
                                       log_interval_seconds=-1.0))
    with pytest.raises(rd.UsageError, match="--log-interval-seconds"):
        rd.check_args(args)


@pytest.mark.slow
def test_plain_log_prints_inside_rounds(tmp_path):
    # interval 0: one line after every update, so the count is exact
    proc = run_script("rama_dreamer.py", "--env-id", "dmc/cartpole-balance", "--obs-type", "state", *TINY,
                      "--run-dir", str(tmp_path), "--plain-log", "--log-interval-seconds", "0")
    lines = [line for line in proc.stdout.splitlines() if "of this round" in line]
    pattern = re.compile(r"step \d+/300 \| update ([12])/2 of this round \| \S+ updates/s \| round ETA \d\d:\d\d")
    assert lines and all(pattern.fullmatch(line) for line in lines), lines
    (run_path,) = glob.glob(os.path.join(tmp_path, "*"))
    updates = torch.load(os.path.join(run_path, "checkpoint.pt"), weights_only=False)["state"]["updates"]
    assert len(lines) == updates and [pattern.fullmatch(line)[1] for line in lines] == ["1", "2"] * (updates // 2)
