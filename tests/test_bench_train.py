"""experiments.bench_train end to end on tiny configurations (its numbers are not checked: speed
lives in the benchmark's output, never in tests): training to a target in either world, the time
split of a step, and one-line errors."""
from __future__ import annotations

import json

import pytest

import kuka_fixtures as kf
from experiments.bench import train as bench_train

TINY = ["--model-size", "tiny", "--no-progress"]
SPLIT = ["--split-seconds", "2", "--split-window", "1", "--split-repeats", "2"]


def test_bench_train_tiny_run(tmp_path):
    """bench_train pauses the training at each evaluation and resumes it: 4 steps, evaluated
    after 2 and 4."""
    result = bench_train.main(["--train-dir", str(tmp_path / "t"), "--eval-every", "2",
                               "--max-steps", "4", "--episodes", "2", "--model-size", "tiny",
                               "--json", str(tmp_path / "b.json"), "--no-progress"])
    assert [r["step"] for r in result["rows"]] == [2, 4]
    assert result["steps_per_second"] > 0
    data = json.loads((tmp_path / "b.json").read_text())
    assert data["experiment"] == "bench_train" and data["world"] == "gridworld"
    for key in ("episodes", "seed", "mode", "target_SR", "target_metric", "steps_per_second",
                "reached", "rows", "final_metadata_step"):
        assert key in data
    assert data["seed"] == 1000 and data["mode"] == "warm_start" and "split" not in data
    for row in data["rows"]:  # rates over 2 episodes; ordered successes are successes
        assert row["SR"] in (0.0, 50.0, 100.0) and row["SR_ordered"] in (0.0, 50.0, 100.0)
        assert row["SR_ordered"] <= row["SR"]


def test_bench_train_stops_at_target(tmp_path):
    """--stop-at-target ends the run at the first evaluation that reaches --target (0 is
    reached by any model), and reports that evaluation as the one that reached it."""
    result = bench_train.main(["--train-dir", str(tmp_path / "t"), "--eval-every", "2",
                               "--max-steps", "6", "--episodes", "2", "--model-size", "tiny",
                               "--target", "0", "--target-metric", "SR_ordered",
                               "--stop-at-target", "--no-progress"])
    assert [r["step"] for r in result["rows"]] == [2]
    assert result["reached"]["step"] == 2 and result["target_metric"] == "SR_ordered"


def test_every_target_metric_must_reach_the_target():
    """--target-metric SR,SR_ordered asks both; Kuka's SR asks it in every column."""
    from experiments.bench import train_worlds as bw

    grid, kuka = bw.WORLDS["gridworld"], bw.WORLDS["kuka"]
    row = {"SR": 100.0, "SR_ordered": 98.0}
    assert bw.reached(grid, row, ["SR"], 99) and bw.reached(grid, row, ["SR"], 100)
    assert not bw.reached(grid, row, ["SR", "SR_ordered"], 99)
    assert bw.reached(grid, row, ["SR", "SR_ordered"], 98)
    kuka_row = {"SR": 99.5, "SR_min": 98.0,
                "SR_columns": {"a": 100.0, "b": 100.0, "c": 100.0, "d": 98.0}}
    assert not bw.reached(kuka, kuka_row, ["SR"], 99) and bw.reached(kuka, kuka_row, ["SR"], 98)


def test_train_dir_of_other_settings_is_refused_in_one_line(tmp_path, capsys):
    """A --train-dir holding a training of other settings (here another batch size) ends in
    one line naming the clash, not a traceback."""
    from experiments.bench import train_worlds as bw

    class Stop(Exception):
        pass

    def stop(step, record):
        raise Stop()  # after the first checkpoint, step 2

    with pytest.raises(Stop):
        bw.run_training(bw.WORLDS["gridworld"], str(tmp_path / "t"), model_size="tiny",
                        checkpoint_every=2, progress=False, callback=stop)
    with pytest.raises(SystemExit) as exc:
        bench_train.main(["--train-dir", str(tmp_path / "t"), "--eval-every", "2",
                          "--max-steps", "2", "--episodes", "2", "--batch-size", "128", *TINY])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "batch_size" in err[0]


@pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)
def test_bench_train_kuka_tiny_run(tmp_path):
    """Kuka: the time split of a step, then 2 steps of a tiny model (batch 16, one example per
    share of the default mixture), evaluated on kf.BATCH validation episodes per Table 2
    column with on-the-fly planning under physics (the tiny model's rollout at batch kf.BATCH,
    the program of test_kuka_experiments' planner runs)."""
    from envs.kuka.config import COLUMNS

    result = bench_train.main(["--world", "kuka", "--train-dir", str(tmp_path / "t"),
                               "--eval-every", "2", "--max-steps", "2",
                               "--episodes", str(kf.BATCH), "--batch-size", "16", "--target",
                               "0", *TINY, "--split", *SPLIT, "--json", str(tmp_path / "k.json")])
    _check_split(result["split"], 16)
    data = json.loads((tmp_path / "k.json").read_text())
    assert data == json.loads(json.dumps(result))
    assert data["world"] == "kuka" and data["mode"] == "on_the_fly"
    assert data["batch_size"] == 16 and data["seed"] == 1000
    assert data["final_metadata_step"] == 2 and [r["step"] for r in data["rows"]] == [2]
    row = data["rows"][0]
    assert set(row["SR_columns"]) == set(COLUMNS)
    assert row["SR_min"] == min(row["SR_columns"].values())
    assert row["SR_min"] <= row["SR"] <= max(row["SR_columns"].values())  # a mean of columns
    assert data["reached"]["step"] == 2  # target 0: reached at the first evaluation


def test_bench_train_split_only(tmp_path):
    """--split-only: the split alone, nothing trained into --train-dir (the Kuka world's split
    runs in test_bench_train_kuka_tiny_run, with --split)."""
    result = bench_train.main(["--world", "gridworld", "--split-only", "--batch-size", "64",
                               *SPLIT, "--train-dir", str(tmp_path / "t"), *TINY,
                               "--json", str(tmp_path / "s.json")])
    split = json.loads((tmp_path / "s.json").read_text())["split"]
    assert result["split_only"] and "rows" not in result
    assert not (tmp_path / "t").exists()
    _check_split(split, 64)


def _check_split(split, batch):
    """Every part takes time, the shares are of the full step, and the sustained training loop
    reports its windows. (No bound on one part's time against another's: timings of a loaded
    CPU vary, and a unit test never asserts a speed; benchmarks print ratios.)"""
    parts = {p["part"]: p for p in split["parts"]}
    assert list(parts) == ["generation", "forward", "forward+backward", "full step"]
    full = parts["full step"]["ms"]
    assert all(p["ms"] > 0 for p in parts.values())
    for p in parts.values():
        assert p["share"] == pytest.approx(100.0 * p["ms"] / full)
    assert parts["full step"]["share"] == pytest.approx(100.0)
    assert split["steps_per_second"] == pytest.approx(1000.0 / full)
    assert split["examples_per_second"] == pytest.approx(1000.0 * batch / full)
    sustained = split["sustained"]
    assert sustained["seconds"] >= 2 and sustained["steps"] > 0
    assert sustained["windows"] and all(w["steps_per_second"] > 0 for w in sustained["windows"])
    assert sum(w["steps"] for w in sustained["windows"]) == sustained["steps"]


@pytest.mark.parametrize("argv, message", [
    (["--world", "mars"], "--world"),
    (["--target", "101"], "--target"),
    (["--target-metric", "SR,GD"], "--target-metric"),
    (["--target-metric", "SR,SR"], "--target-metric"),
    (["--world", "kuka", "--target-metric", "SR_ordered"], "--target-metric"),
    (["--world", "kuka", "--mode", "warm_start"], "--mode"),
    (["--mode", "one_shot"], "--mode"),
    (["--batch-size", "32"], "--batch-size"),
    (["--world", "kuka", "--batch-size", "12"], "--batch-size"),
    (["--eval-every", "3", "--max-steps", "4"], "--max-steps"),
    (["--episodes", "0"], "--episodes"),
    (["--split-only", "--split-seconds", "0"], "--split-seconds"),
    (["--split-only", "--split-seconds", "5", "--split-window", "10"], "--split-window"),
    (["--split-repeats", "0"], "--split-repeats"),
    (["--set", "colour=red"], "--set colour"),
    (["--set", "lr"], "FIELD=VALUE"),
    (["--set", "lr=-1"], "lr"),
    (["--set", "cross_attn_levels=[7]"], "cross_attn_levels"),
])
def test_bench_train_rejects_bad_input_in_one_line(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        bench_train.main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert message in err[-1] and err[-1].startswith("python -m experiments.bench_train: error")


def test_settings_reach_the_training_and_the_model():
    """--set FIELD=VALUE changes the TrainConfig or the DenoiserConfig of the world's recipe
    (JSON values, lists as tuples); a shorter run keeps its warm-up within a tenth."""
    from experiments.bench import train_worlds as bw

    model, config, _ = bw.training(bw.WORLDS["gridworld"], "default", 1,
                                   ["steps=1000", "lr=0.002", "cross_attn_levels=[1, 2]",
                                    "ema_decay=0.99", "seed=3"])
    assert (config.steps, config.lr, config.ema_decay, config.seed) == (1000, 0.002, 0.99, 3)
    assert config.warmup_steps <= 100 and model.cross_attn_levels == (1, 2)


def test_batch_size_follows_the_recipe_mixture():
    """A smaller mixture allows a smaller batch: the check is the recipe's, not a constant."""
    from envs.gridworld.training import Recipe as GridRecipe
    from envs.kuka.training import Recipe as KukaRecipe

    assert GridRecipe().batch_multiple == 64 and KukaRecipe().batch_multiple == 16
    parser = bench_train.build_parser()
    args = parser.parse_args(["--batch-size", "32", "--set",
                              'mixture=[["p_mo2g", 18], ["mo1g", 9], ["1o1g", 5]]'])
    world, *_ = bench_train.check_args(parser, args)
    assert world.name == "gridworld"


def test_kuka_specs_can_be_set_as_lists():
    """--set specs=[[kind, multi, language], ...] gives the Kuka recipe those task specs (a
    spec listed twice has twice the share); a malformed spec is refused, naming it."""
    from envs.kuka.config import TaskSpec
    from envs.kuka.training import Recipe
    from experiments.bench import train_worlds as bw

    _, _, recipe = bw.training(bw.WORLDS["kuka"], "default", 1, [
        'specs=[["rearrangement", true, "canonical"], ["rearrangement", true, "canonical"], '
        '["stacking", false, "paraphrased"]]'])
    assert recipe.specs == (TaskSpec("rearrangement", True),) * 2 + (
        TaskSpec("stacking", False, "paraphrased"),)
    assert recipe.batch_multiple == 3
    assert recipe.metadata()["specs"][0] == ["rearrangement", True, "canonical"]
    for bad in ([["stacking", "yes", "canonical"]], [["stacking", False]], []):
        with pytest.raises(ValueError, match="spec"):
            Recipe(specs=bad)
    with pytest.raises(ValueError, match="held-out"):  # "unseen": the development phrasings
        Recipe(specs=[["stacking", False, "unseen"]])


def test_checkpoints_fall_on_every_evaluation_and_stay_frequent():
    """bench_train checkpoints at least as often as the world's --train, and on every
    evaluation step (the evaluation reads that checkpoint)."""
    from experiments.bench.train_worlds import WORLDS

    for world in WORLDS.values():
        for eval_every in (1, 7, 250, 1000, 12000, 12345):
            every = world.checkpoint_interval(eval_every)
            assert 1 <= every <= world.checkpoint_every and eval_every % every == 0
    assert WORLDS["kuka"].checkpoint_interval(12000) == WORLDS["kuka"].checkpoint_every
