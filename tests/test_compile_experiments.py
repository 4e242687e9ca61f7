"""End-to-end runs of the CompILE experiments on a tiny configuration (train a few steps,
evaluate a few episodes), the JSON / trajectories contracts, and the seed discipline."""
import json
import os

import jax
import numpy as np
import pytest

from envs.gridworld import grammar, metrics
from experiments.gridworld import cli as gridworld_cli, spec as gridworld_spec
from experiments.harness import core as harness

EXPECTED_ROW_FIELDS = {"method", "SR", "GD", "path_precision", "path_recall", "path_f1",
                       "denoiser_calls_per_episode", "seconds"}


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """`compile_p_mo2g --train` with a tiny model: 4 steps, 6 episodes, every mode."""
    out = tmp_path_factory.mktemp("p_mo2g")
    argv = ["--train", "--train-steps", "4", "--model-size", "tiny", "--train-dir",
            str(out / "train"), "--episodes", "6", "--batch-size", "4", "--num-steps", "2",
            "--warm-num-steps", "2", "--warm-start-step", "1", "--json", str(out / "r.json"),
            "--trajectories", str(out / "t.npz"), "--no-progress"]
    result = gridworld_cli.main("p_mo2g", argv)
    return out, result


def test_json_contract(tiny_run):
    out, result = tiny_run
    with open(out / "r.json") as f:
        data = json.load(f)
    assert data == json.loads(json.dumps(result))
    assert data["experiment"] == "compile_p_mo2g"
    assert data["episodes"] == 6 and data["seed"] == harness.DEFAULT_EVAL_SEED
    methods = [row["method"] for row in data["rows"]]
    assert methods == ["one-shot", "two-shot", "on-the-fly", "warm-start on-the-fly", "oracle",
                       "searcher"]
    assert data["trajectories_method"] == "on-the-fly"
    # Each re-planning row's trigger: paper-style on-the-fly before every move, warm start on
    # change (the cheap default).
    assert data["replan"] == {"on_the_fly": "always", "warm_start": "on_change"}
    for row in data["rows"]:
        assert EXPECTED_ROW_FIELDS <= set(row), EXPECTED_ROW_FIELDS - set(row)
        # Rates over the 6 episodes: whole episodes, and the ordered ones among the successes.
        for key in ("SR", "SR_ordered"):
            assert row[key] * 6 / 100 == pytest.approx(round(row[key] * 6 / 100)), key
        assert row["SR_ordered"] <= row["SR"]
    calls = {row["method"]: row["denoiser_calls_per_episode"] for row in data["rows"]}
    assert calls["one-shot"] == 2.0
    assert calls["warm-start on-the-fly"] < calls["on-the-fly"]
    assert calls["oracle"] == calls["searcher"] == 0.0
    oracle = data["rows"][-2]
    assert oracle["SR_ordered"] == 100.0 and oracle["SPL"] == 1.0


def check_trajectories(traj, result, n: int):
    """A run's trajectories file (n episodes) holds contract 2's arrays, recomputes the main
    row's metrics, and its moves are 4-connected, inside the grid, never into an obstacle."""
    for key in ("grid", "agent", "target", "reference", "expert_path", "expert_length",
                "visible0", "instruction", "object_names", "positions", "steps", "success"):
        assert key in traj.files, key
    assert traj["positions"].shape == (n, 101, 2) and traj["positions"].dtype == np.int32
    assert traj["grid"].dtype == np.int8 and traj["grid"].shape == (n, 16, 16)
    # Anyone can recompute the metrics of the main row from what the agent did.
    recomputed = metrics.trajectory_metrics(traj["positions"], traj["steps"], traj["target"],
                                            traj["expert_path"], traj["reference"],
                                            traj["expert_length"])
    row = next(r for r in result["rows"] if r["method"] == result["trajectories_method"])
    for key in ("SR", "SR_ordered", "GD", "path_precision", "path_recall", "path_f1", "SPL"):
        assert recomputed[key] == pytest.approx(row[key]), key
    # Executed moves are 4-connected, inside the grid, never into an obstacle.
    pos = traj["positions"]
    assert np.all(np.abs(np.diff(pos, axis=1)).sum(-1) <= 1)
    rows = np.arange(n)[:, None]
    assert np.all(traj["grid"][rows, pos[..., 0], pos[..., 1]] != -1)
    np.testing.assert_array_equal(traj["success"], np.all(pos[np.arange(n), traj["steps"]] ==
                                                          traj["target"], axis=-1))


def test_trajectories_file_recomputes_the_main_row(tiny_run):
    out, result = tiny_run
    check_trajectories(np.load(out / "t.npz"), result, 6)


def test_p_mo2g_far_runs_from_its_entry_point(tiny_run, tmp_path, monkeypatch):
    """`python -m experiments.compile_p_mo2g_far` evaluates a checkpoint of the paper's settings
    on the far setting: the ordered success in its row, trajectories of far episodes (the
    target 4-9 cells from the reference, unseen at t=0), re-planning when refuted with the best
    of 2 plans, and the exact-posterior denoiser's row (it solves the 4 episodes)."""
    import runpy
    import sys

    out, _ = tiny_run
    monkeypatch.setattr(sys, "argv", [
        "compile_p_mo2g_far", "--checkpoint", str(out / "train"), "--episodes", "4",
        "--batch-size", "4", "--num-steps", "2", "--modes", "on_the_fly", "--json",
        str(tmp_path / "r.json"), "--trajectories", str(tmp_path / "t.npz"), "--no-progress",
        "--replan", "on_refuted", "--samples", "2", "--posterior-denoiser"])
    runpy.run_module("experiments.compile_p_mo2g_far", run_name="__main__")
    result = json.loads((tmp_path / "r.json").read_text())
    assert (result["experiment"], result["setting"]) == ("compile_p_mo2g_far", "p_mo2g_far")
    assert [r["method"] for r in result["rows"]] == [
        "on-the-fly", "on-the-fly, exact posterior", "oracle", "searcher"]
    assert result["samples"] == 2 and result["replan"] == {"on_the_fly": "on_refuted"}
    assert result["rows"][1]["SR_ordered"] == 100.0
    assert result["rows"][2]["SR_ordered"] == 100.0 and result["rows"][2]["SPL"] == 1.0
    assert "SR_ordered" in result["rows"][0]
    traj = np.load(tmp_path / "t.npz")
    check_trajectories(traj, result, 4)
    far = np.abs(traj["target"] - traj["reference"]).max(-1)
    assert ((far >= 4) & (far <= 9)).all()
    target = traj["target"]
    assert not traj["visible0"][np.arange(4), target[:, 0], target[:, 1]].any()


def test_other_settings_evaluate_a_checkpoint(tiny_run, tmp_path):
    out, _ = tiny_run
    for setting in ("mo1g", "1o1g"):
        result = gridworld_cli.main(setting, ["--checkpoint", str(out / "train"), "--episodes", "3",
                                   "--batch-size", "3", "--num-steps", "2",
                                   "--warm-start-step", "1", "--modes", "on_the_fly",
                                   "--json", str(tmp_path / f"{setting}.json"), "--no-progress",
                                   "--no-reference-agents"])
        assert result["experiment"] == f"compile_{setting}"
        assert [r["method"] for r in result["rows"]] == ["on-the-fly"]
        assert "SR_ordered" not in result["rows"][0]


def test_baseline_rows_beside_the_planner(tiny_run, tmp_path):
    """--baselines adds BC's and CQL's rows, and the reference agents theirs, measured on the
    planner's episodes: equal to baselines_eval's rows for the same seeds (the table is the
    same measurement)."""
    from experiments.gridworld.baselines import baseline_rows, reference_rows

    out, _ = tiny_run
    result = gridworld_cli.main("1o1g", ["--checkpoint", str(out / "train"), "--episodes", "4",
                              "--seeds", "7,8", "--batch-size", "4", "--num-steps", "2",
                              "--modes", "one_shot", "--baselines", "bc,cql", "--no-progress"])
    rows = result["rows"]
    assert [r["method"] for r in rows] == ["one-shot", "BC", "CQL", "oracle", "searcher"]
    expected = baseline_rows("1o1g", (7, 8), 4, 4, False, methods=("bc", "cql")) + \
        reference_rows("1o1g", (7, 8), 4, 4, False)
    for row, want in zip(rows[1:], expected):
        assert row["SR"] == want["SR"] and row["path_f1"] == want["path_f1"]
        assert {s: v["SR"] for s, v in row["per_seed"].items()} == {
            s: v["SR"] for s, v in want["per_seed"].items()}
        assert len(row["SR_ci95"]) == 2


def test_reference_agents_in_the_table_and_json_unless_left_out(tiny_run, tmp_path, capsys):
    """The oracle's and the searcher's rows are in every grid-world table and its JSON by
    default; --no-reference-agents (documented in --help) leaves them out, and nothing else."""
    out, _ = tiny_run
    argv = ["--checkpoint", str(out / "train"), "--episodes", "4", "--batch-size", "4",
            "--num-steps", "2", "--modes", "one_shot", "--no-progress"]
    capsys.readouterr()
    planner_rows = []
    for flags, methods in (([], ["one-shot", "oracle", "searcher"]),
                           (["--no-reference-agents"], ["one-shot"])):
        json_path = tmp_path / f"r{len(flags)}.json"
        gridworld_cli.main("mo1g", argv + flags + ["--json", str(json_path)])
        table = capsys.readouterr().out
        with open(json_path) as f:
            rows = json.load(f)["rows"]
        assert [r["method"] for r in rows] == methods
        for name in ("oracle", "searcher"):
            assert any(line.startswith(name) for line in table.splitlines()) == (not flags)
        planner_rows.append({k: v for k, v in rows[0].items() if k != "seconds"})
    assert planner_rows[0] == planner_rows[1]
    with pytest.raises(SystemExit):
        gridworld_cli.main("mo1g", ["--help"])
    assert "--no-reference-agents" in capsys.readouterr().out


def test_language_all_makes_a_row_per_phrasing(tiny_run):
    """--language all: a row per phrasing and mode on the same worlds; the canonical rows are
    those of --language canonical, the others say their phrasing in the method and JSON."""
    out, _ = tiny_run
    argv = ["--checkpoint", str(out / "train"), "--episodes", "4", "--batch-size", "4",
            "--num-steps", "2", "--modes", "one_shot", "--no-progress"]
    both = gridworld_cli.main("p_mo2g", argv + ["--language", "all"])
    assert [r["method"] for r in both["rows"]] == [
        f"{method}{suffix}" for suffix in ("", ", paraphrased", ", unseen")
        for method in ("one-shot", "oracle", "searcher")]
    assert [r["language"] for r in both["rows"]] == [
        language for language in ("canonical", "paraphrased", "unseen") for _ in range(3)]
    assert both["language"] == "all"
    assert "per_phrasing" not in both["rows"][0]  # one phrasing: nothing to split
    for row in both["rows"][3:]:  # each phrasing's own rates, on its own episodes
        split = row.get("per_phrasing", [{"template": None, "episodes": 4}])
        assert sum(p["episodes"] for p in split) == 4
        pool = set(grammar.template_pool("p_mo2g", row["language"]).tolist()) | {None}
        assert {p["template"] for p in split} <= pool
    canonical = gridworld_cli.main("p_mo2g", argv)
    for key in ("SR", "SR_ordered", "GD", "path_f1"):
        assert both["rows"][0][key] == canonical["rows"][0][key]


def test_profile_writes_a_trace(tiny_run, tmp_path):
    out, _ = tiny_run
    gridworld_cli.main("p_mo2g", ["--checkpoint", str(out / "train"), "--episodes", "2", "--batch-size",
                       "2", "--num-steps", "2", "--warm-num-steps", "2", "--modes",
                       "one_shot", "--profile", str(tmp_path / "prof"), "--no-progress",
                       "--no-reference-agents"])
    traces = [f for _, _, files in os.walk(tmp_path / "prof") for f in files]
    assert any(f.endswith((".xplane.pb", ".trace.json.gz")) for f in traces), traces


def test_missing_checkpoint_says_how_to_get_one(tmp_path, capsys):
    with pytest.raises(SystemExit) as err:
        gridworld_cli.main("p_mo2g", ["--checkpoint", str(tmp_path / "nothing"), "--episodes", "2"])
    assert err.value.code == 2
    msg = capsys.readouterr().err.strip()
    assert "--train" in msg and len(msg.splitlines()) == 1


BAD_INVOCATIONS = [
    (["--episodes", "0"], "--episodes"),
    (["--modes", "two_shot"], "--modes"),
    (["--num-steps", "4", "--warm-start-step", "4"], "--warm-start-step"),
    (["--json", "{tmp}"], "is a directory"),
    (["--json", "{tmp}/ckpt_file/r.json"], "cannot be created"),
    (["--num-steps", "500"], "exceeds the denoiser's schedule"),
    (["--figures", "{tmp}/f", "--num-figures", "0"], "--num-figures"),
    (["--num-figures", "3"], "only makes sense with --figures"),
    (["--trajectories", "{tmp}/x"], "must end in .npz"),
    (["--train", "--checkpoint", "{tmp}"], "exclude each other"),
    (["--train-steps", "10"], "only makes sense with --train"),
    (["--train-seed", "1", "--model-size", "tiny"], "only make sense with --train"),
    (["--seeds", "1,x"], "--seeds"),
    (["--seeds", "1,1"], "distinct"),
    (["--checkpoint", "{tmp}/nothing"], "no checkpoint in"),
    (["--checkpoint", "{tmp}/ckpt_file"], "no checkpoint in"),
    (["--baselines", "bc,ppo"], "--baselines must be distinct names"),
    (["--baselines", "bc,bc"], "--baselines must be distinct names"),
    (["--samples", "0"], "--samples"),
    (["--posterior-denoiser", "--psi", "follow"], "--psi search only"),
    (["--psi", "follow", "--follow-mark", "1"], "--follow-mark must be in [-1, 1)"),
    (["--psi", "follow", "--follow-mark", "nan"], "--follow-mark must be in [-1, 1)"),
    (["--follow-mark", "-0.5"], "it needs --psi follow"),
]


@pytest.mark.parametrize("argv, message", BAD_INVOCATIONS)
def test_bad_arguments_are_rejected_in_one_line(argv, message, tmp_path, capsys):
    """Every user error ends before any work with one line on stderr and exit code 2."""
    (tmp_path / "ckpt_file").write_text("not a checkpoint")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    with pytest.raises(SystemExit) as err:
        gridworld_cli.main("p_mo2g", argv + ["--episodes" if "--episodes" not in argv else "--seed",
                                  "1" if "--episodes" not in argv else "3", "--no-progress"])
    assert err.value.code == 2
    lines = [l for l in capsys.readouterr().err.strip().splitlines() if l.startswith(
        ("error", "python -m", "usage"))]
    assert message in lines[-1], lines
    assert not any("Traceback" in l for l in lines)


def test_same_seed_same_results(tiny_run, tmp_path):
    out, _ = tiny_run
    argv = ["--checkpoint", str(out / "train"), "--episodes", "4", "--batch-size", "4",
            "--num-steps", "2", "--warm-start-step", "1", "--modes", "on_the_fly",
            "--no-progress", "--no-reference-agents"]
    a = gridworld_cli.main("p_mo2g", argv + ["--trajectories", str(tmp_path / "a.npz")])
    b = gridworld_cli.main("p_mo2g", argv + ["--trajectories", str(tmp_path / "b.npz"),
                                  "--batch-size", "3"])
    np.testing.assert_array_equal(np.load(tmp_path / "a.npz")["positions"],
                                  np.load(tmp_path / "b.npz")["positions"])
    assert a["rows"][0]["SR"] == b["rows"][0]["SR"]


def test_ship_checkpoint_writes_a_loadable_export_with_its_note(tiny_run, tmp_path):
    from experiments.shipping import denoiser as ship_checkpoint

    out, _ = tiny_run
    dest = tmp_path / "shipped"
    ship_checkpoint.main(["--train-dir", str(out / "train"), "--out", str(dest),
                          "--results", str(out / "r.json")])
    note = (dest / "NOTE.md").read_text()
    assert "--train" in note and "seed" in note and "on-the-fly" in note
    denoiser, _ = harness.load_model(str(dest))
    assert denoiser.model_config == gridworld_spec.SPECS["p_mo2g"].model_config("tiny")
    assert jax.tree.leaves(denoiser.params)


def test_a_follow_results_command_names_its_mark():
    """The NOTE's command of a follow-psi result repeats the mark it ran with, so the command
    reproduces it whatever the default; a search result names neither."""
    from experiments.shipping.denoiser import _result_command

    base = {"experiment": "compile_p_mo2g", "episodes": 10, "seed": 1000}
    assert _result_command({**base, "psi": "follow", "follow_mark": -0.8}).endswith(
        "--seed 1000 --psi follow --follow-mark -0.8")
    assert _result_command({**base, "psi": "search", "follow_mark": 0.0}).endswith("--seed 1000")


def test_x0_prediction_trains_and_evaluates(tmp_path):
    """--prediction x0: the checkpoint records it and evaluation converts x0 to noise."""
    result = gridworld_cli.main("p_mo2g", ["--train", "--prediction", "x0", "--train-steps", "2",
                                "--model-size", "tiny", "--train-dir", str(tmp_path / "x0"),
                                "--episodes", "2", "--batch-size", "2", "--num-steps", "2",
                                "--warm-start-step", "1", "--modes", "on_the_fly",
                                "--no-progress", "--no-reference-agents"])
    assert result["rows"][0]["denoiser_calls_per_episode"] > 0
    denoiser, _ = harness.load_model(str(tmp_path / "x0"))
    assert denoiser.prediction == "x0"


def test_ablation_runs_every_row_on_a_tiny_configuration(tiny_run, tmp_path):
    from experiments.gridworld import ablation as ablation_compile

    out, _ = tiny_run
    result = ablation_compile.main([
        "--train", "--train-steps", "2", "--model-size", "tiny", "--main-checkpoint",
        str(out / "train"), "--checkpoint-root", str(tmp_path), "--settings", "mo1g",
        "--episodes", "2", "--batch-size", "2", "--num-steps", "2", "--no-progress",
        "--json", str(tmp_path / "ablation.json")])
    methods = [row["method"] for row in result["rows"]]
    assert methods == ["mo1g baseline", "mo1g + grid repr", "mo1g + g", "mo1g + on the fly",
                       "mo1g oracle", "mo1g searcher"]
    for row in result["rows"]:
        assert EXPECTED_ROW_FIELDS <= set(row)
    with open(tmp_path / "ablation.json") as f:
        assert json.load(f)["experiment"] == "ablation_compile"
    # The no-g models were trained without the goal loss, with their own grid representation.
    denoiser, meta = harness.load_model(str(tmp_path / "compile_gridworld_class_id_no_goal"))
    assert denoiser.model_config.grid_repr == "class_id"
    assert meta["extra"]["goal_channel"] is False


def test_psi_follow_reports_its_fallback_moves(tiny_run):
    """--psi follow: the paper's psi; every planner row says what share of its moves were
    fallback moves (in the JSON and per seed), and the JSON records the psi."""
    out, _ = tiny_run
    result = gridworld_cli.main("p_mo2g", [
        "--checkpoint", str(out / "train"), "--episodes", "3", "--seeds", "7,8",
        "--batch-size", "3", "--num-steps", "2", "--modes", "on_the_fly", "--psi", "follow",
        "--follow-mark", "-0.5", "--no-progress"])
    assert result["psi"] == "follow" and result["follow_mark"] == -0.5
    row = result["rows"][0]
    assert set(row["per_seed"]) == {"7", "8"} and "fallback_percent" in row["per_seed"]["7"]
    # The share recomputed through the library, on the documented episodes and planner keys.
    assert row["fallback_percent"] == pytest.approx(_library_fallback_percent(out / "train"))


def _library_fallback_percent(checkpoint) -> float:
    """100 x fallback moves / moves of seeds 7 and 8 (3 episodes each) planned with
    diffplan.rollout (not the CLI's slot pool), the follow psi marking above -0.5."""
    import jax

    from diffplan import Planner, PlannerConfig, load_denoiser, rollout
    from envs.gridworld.config import make_config
    from envs.gridworld.episode import generate_batch
    from envs.gridworld.task import GridTask

    den = load_denoiser(str(checkpoint))
    task = GridTask(make_config("p_mo2g"), psi_kind="follow", follow_mark=-0.5)
    planner = Planner(den, PlannerConfig(mode="on_the_fly", num_steps=2))
    fallback = moves = 0
    for seed in (7, 8):
        episodes = generate_batch(jax.random.PRNGKey(seed), make_config("p_mo2g"), 3)
        out = rollout(task, planner, harness.planner_keys(seed, jax.numpy.arange(3)), episodes)
        fallback += int(out.fallback_moves.sum())
        moves += int(out.steps.sum())
    return 100.0 * fallback / moves
