"""experiments.goal_probe on the shipped token checkpoint: at the last timestep (pure noise)
its one-step estimate puts MO1G's goal and P-MO2G's reference on the expert's cell (it reads
the names: measured 100 and 100 on 256 examples), the table and JSON are written, and bad input
is one line."""
from __future__ import annotations

import json
import os

import pytest

from experiments.gridworld.goal_probe import main
from experiments.harness import core as harness

SHIPPED = os.path.join(harness.CHECKPOINT_ROOT, "compile_gridworld")


def test_the_shipped_token_model_reads_the_names(tmp_path, capsys):
    out = tmp_path / "probe.json"
    result = main(["--checkpoint", SHIPPED, "--timesteps", "99", "--batch-size", "64",
                   "--json", str(out)])
    row = result["checkpoints"][SHIPPED]["rows"][0]
    assert result["checkpoints"][SHIPPED]["text"] == "tokens" and row["t"] == 99
    assert row["goal mo1g"] >= 90 and row["reference p_mo2g"] >= 90, row
    assert row["goal 1o1g"] == 100.0, row
    assert json.loads(out.read_text())["checkpoints"][SHIPPED]["rows"] == [row]
    printed = capsys.readouterr().out
    assert "reference p_mo2g" in printed and "legend:" in printed


@pytest.mark.parametrize("argv, needle", [
    (["--checkpoint", SHIPPED, "--timesteps", "99,x"], "comma-separated integers"),
    (["--checkpoint", SHIPPED, "--batch-size", "100"], "multiple of 64"),
    (["--checkpoint", SHIPPED, "--timesteps", "100"], "outside the schedule's 0..99"),
])
def test_bad_input_is_one_line(argv, needle, capsys):
    with pytest.raises(SystemExit):
        main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert needle in err[-1], err
