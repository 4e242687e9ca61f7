"""experiments.cli: the output checks and the atomic JSON writer every CLI shares."""
from __future__ import annotations

import argparse
import json
import os

import pytest

from experiments.harness import cli


def _parser():
    return argparse.ArgumentParser(prog="x")


def test_write_json_writes_and_leaves_no_temporary_file(tmp_path, capsys):
    path = tmp_path / "sub" / "r.json"
    cli.write_json(str(path), {"a": [1, 2]})
    assert json.loads(path.read_text()) == {"a": [1, 2]}
    assert os.listdir(path.parent) == ["r.json"]
    assert capsys.readouterr().out.strip() == f"wrote {path}"


def test_write_json_failure_keeps_the_old_file(tmp_path):
    path = tmp_path / "r.json"
    path.write_text('{"old": 1}')
    with pytest.raises(TypeError):  # not serialisable: fails mid-write (a bug, not a user error)
        cli.write_json(str(path), {"bad": object()})
    assert json.loads(path.read_text()) == {"old": 1}
    assert os.listdir(tmp_path) == ["r.json"]


def test_write_json_unwritable_directory(tmp_path, capsys):
    """The directory cannot be made (a file stands where it should be): one line, exit 3."""
    (tmp_path / "file").write_text("x")
    with pytest.raises(SystemExit) as info:
        cli.write_json(str(tmp_path / "file" / "r.json"), {})
    assert info.value.code == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: cannot write")


@pytest.mark.parametrize("path, message", [("{tmp}", "is a directory"),
                                           ("{tmp}/f.txt", "must end in .npz"),
                                           ("", "needs a file path")])
def test_check_output_file(path, message, tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.check_output_file(_parser(), "--out", path.replace("{tmp}", str(tmp_path)), ".npz")
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--train-steps", "3"], "--train-steps only makes sense with --train"),
    (["--train", "--checkpoint", "c"], "exclude each other"),
    (["--train", "--train-steps", "1"], "--train-steps must be >= 2"),
    (["--train", "--checkpoint-every", "0"], "--checkpoint-every must be >= 1"),
])
def test_training_flags_are_checked_together(argv, message, capsys):
    parser = _parser()
    cli.add_training_flags(parser, training_name="x", served="y", train_steps=10,
                           checkpoint_every=5, model_sizes={"tiny": {}})
    args = parser.parse_args(argv)
    with pytest.raises(SystemExit):
        cli.check_training_flags(parser, args, {"train_steps": "--train-steps",
                                                "checkpoint_every": "--checkpoint-every"})
    assert message in capsys.readouterr().err.strip().splitlines()[-1]


def test_harness_intervals_tables_and_keys():
    """The shared harness: Wilson intervals of rates, the table layout (missing values as
    '-'), and the seed convention of episode and planner keys."""
    import jax
    import numpy as np

    from experiments.harness import core as harness, intervals, tables

    assert intervals.wilson_interval(0, 0) == [0.0, 100.0]
    lo, hi = intervals.wilson_interval(3000, 3000)
    assert hi == pytest.approx(100.0) and lo == pytest.approx(99.872, abs=1e-3)  # [99.87, 100]
    assert intervals.rate_interval(31.3, 3000) == intervals.wilson_interval(939, 3000)
    table = tables.format_table([{"method": "a", "SR": 50.0}, {"method": "bb", "SR": None}],
                                (("method", "{:<4}", "m"), ("SR", "{:>6.1f}", "SR")))
    assert table.splitlines() == ["m        SR", "-----------", "a      50.0", "bb        -"]
    root = jax.random.PRNGKey(9)
    np.testing.assert_array_equal(harness.episode_keys(9, 2, 4),
                                  [jax.random.fold_in(root, i) for i in (2, 3)])
    stream = jax.random.fold_in(root, harness.ROLLOUT_STREAM)
    np.testing.assert_array_equal(harness.planner_keys(9, np.array([5, 1])),
                                  [jax.random.fold_in(stream, i) for i in (5, 1)])


def test_compile_together_gives_the_jitted_programs(monkeypatch):
    """compiling.compile_together: one compiled program per argument set (compiled in
    threads), each computing what the jitted function computes on arguments of its shapes."""
    import jax
    import numpy as np

    from experiments.harness import compiling

    monkeypatch.setenv(compiling.THREADS_VARIABLE, "2")  # the suite's conftest sets 1
    assert compiling.compile_threads() == 2
    fn = jax.jit(lambda x, k: x * k + 1)
    small, large = compiling.compile_together(fn, [(np.ones(3, np.float32), 2.0),
                                                 (np.ones((2, 4), np.float32), 2.0)])
    x = np.arange(8, dtype=np.float32).reshape(2, 4)
    np.testing.assert_array_equal(large(x, 3.0), fn(x, 3.0))
    np.testing.assert_array_equal(small(x[0, :3], 0.5), fn(x[0, :3], 0.5))
    with pytest.raises(TypeError):
        small(x, 2.0)  # a compiled program refuses other shapes
    assert compiling.compile_together(fn, []) == []
    (one,) = compiling.compile_together(fn, [(x, 1.0)], min_memory_gb=1e9)  # one at a time
    np.testing.assert_array_equal(one(x, 4.0), fn(x, 4.0))


@pytest.mark.parametrize("value", ["0", "-1", "two", ""])
def test_compile_threads_refuses_what_is_not_a_positive_count(monkeypatch, value):
    from experiments.harness import compiling

    monkeypatch.setenv(compiling.THREADS_VARIABLE, value)
    with pytest.raises(ValueError, match="DIFFPLAN_COMPILE_THREADS must be a positive integer"):
        compiling.compile_threads()
    monkeypatch.delenv(compiling.THREADS_VARIABLE)
    assert compiling.compile_threads() == (__import__("os").cpu_count() or 1)
