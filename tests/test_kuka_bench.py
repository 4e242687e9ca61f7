"""The Kuka benchmark end to end on a tiny configuration (its numbers are not checked: speed
lives in the benchmark's output, never in tests)."""
from __future__ import annotations

import json

import pytest

import kuka_fixtures as kf
from experiments.bench import kuka as bench_kuka

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)


def test_bench_kuka_tiny_run_writes_every_row(tmp_path):
    out = tmp_path / "bench.json"
    code = bench_kuka.main(["--batch-sizes", str(kf.BATCH), "--steps", "20", "--c-steps", "50",
                            "--placement-batch", str(kf.BATCH), "--repeats", "1",
                            "--episodes", str(kf.BATCH), "--json", str(out)])
    assert code == 0
    data = json.loads(out.read_text())
    assert data["experiment"] == "bench_kuka"
    kinds = [(r["kind"], r["batch"]) for r in data["rows"]]
    assert kinds == [("mjx", kf.BATCH), ("c", 1), ("pick_and_place", kf.BATCH)]
    for row in data["rows"]:
        assert row["per_second"] > 0 and row["best_per_second"] >= row["per_second"] * 0.999
    assert data["rows"][-1]["seconds_per_placement"] > 0


def test_bench_kuka_rejects_bad_input():
    with pytest.raises(SystemExit):
        bench_kuka.main(["--batch-sizes", "0"])
    with pytest.raises(SystemExit):
        bench_kuka.main(["--steps", "0"])
