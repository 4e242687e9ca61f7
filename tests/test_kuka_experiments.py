"""Tiny end-to-end runs of the Kuka experiment CLIs (contracts 2 and 4), recomputing the
main row's SR from the written states with a plain-numpy check: the scripted expert, and the
planner after `--train` of a few steps of the tiny model (its on-the-fly rollout at batch
kf.BATCH is the program test_bench_train's Kuka run evaluates with: compiled once)."""
from __future__ import annotations

import json

import numpy as np
import pytest

import kuka_fixtures as kf
from envs.kuka import grammar, render
from experiments.harness import intervals
from experiments.kuka import cli as kuka_cli, spec as kuka_spec

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)

STATE_FIELDS = {"block_pos", "block_quat", "held", "block_half_size", "constraints",
                "instruction"}


def _recomputed_sr(states, rows=None):
    """Percent of instructed constraints holding in the states (rows: a subset of episodes)."""
    rows = range(len(states["constraints"])) if rows is None else rows
    held, total = 0, 0
    for i in rows:
        for top, bottom in states["constraints"][i]:
            if top < 0:
                continue
            total += 1
            held += kf.numpy_on(states["block_pos"][i], states["held"][i], top, bottom)
    return 100.0 * held / total


def _load_states(path):
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


@pytest.mark.parametrize("kind", ["stacking", "rearrangement"])
def test_cli_end_to_end(kind, tmp_path):
    out_json, out_npz, figs = tmp_path / "r.json", tmp_path / "s.npz", tmp_path / "figs"
    result = kuka_cli.main(kind, [
        "--policy", "expert", "--episodes", "4", "--seed", "5", "--batch-size", str(kf.BATCH),
        "--json", str(out_json),
        "--states", str(out_npz), "--figures", str(figs), "--num-figures", "1", "--no-progress"])
    data = json.loads(out_json.read_text())
    assert data == json.loads(json.dumps(result))
    assert data["experiment"] == f"kuka_{kind}" and data["episodes"] == 4 and data["seed"] == 5
    main, single, multi = data["rows"]
    assert data["states_method"] == main["method"] == "expert"
    assert [single["column"], multi["column"]] == ["single", "multi"]
    states = _load_states(out_npz)
    assert set(states) == STATE_FIELDS
    n = 8
    assert states["block_pos"].shape == (n, 4, 3) and states["block_pos"].dtype == np.float32
    assert states["block_quat"].shape == (n, 4, 4) and states["block_quat"].dtype == np.float32
    assert states["held"].shape == (n, 4) and states["held"].dtype == bool
    assert states["constraints"].shape == (n, 3, 2) and states["constraints"].dtype == np.int32
    np.testing.assert_allclose(states["block_half_size"], [0.1, 0.1, 0.03])
    np.testing.assert_allclose(np.linalg.norm(states["block_quat"], axis=-1), 1, atol=1e-4)
    # Contract 4: the main row's SR is the share of instructed constraints holding.
    assert main["SR"] == pytest.approx(_recomputed_sr(states), abs=1e-9)
    counts = (states["constraints"][..., 0] >= 0).sum(-1)
    multi_count = 3 if kind == "stacking" else 2
    np.testing.assert_array_equal(counts, [1] * 4 + [multi_count] * 4)
    assert single["SR"] == pytest.approx(_recomputed_sr(states, range(4)), abs=1e-9)
    assert multi["SR"] == pytest.approx(_recomputed_sr(states, range(4, 8)), abs=1e-9)
    assert main["SR"] == 100.0 and main["SR_diffuser"] == 100.0
    # Scored after 1 s at rest; the expert's blocks stay put and it never moves a block twice.
    assert data["settle_seconds"] == 1.0
    assert main["settle_changed"] == single["settle_changed"] == multi["settle_changed"] == 0
    assert main["SPL"] == single["SPL"] == multi["SPL"] == 1.0
    # The instructions are the episodes' constraints in words.
    for c, text in zip(states["constraints"], states["instruction"]):
        tower_sentence = kind == "stacking" and (c[:, 0] >= 0).sum() == 1
        assert str(text) == grammar.render(c, tower_sentence)
    assert len(list(figs.glob("*.png"))) == 2


def test_intervals_over_seeds_count_episodes_not_constraints(capsys):
    """With several seeds every row has a 95% interval whose trials are the episodes (a
    multi-constraint episode is one cluster), and per-seed SR and SPL."""
    result = kuka_cli.main("stacking", [
        "--policy", "expert", "--episodes", "2", "--seeds", "5,6", "--batch-size", str(kf.BATCH),
        "--no-progress"])
    main, single, multi = result["rows"]
    assert single["SR_ci95"] == pytest.approx(intervals.wilson_interval(4, 4))
    assert multi["constraints"] == 12 and multi["SR_ci95"] == pytest.approx(
        intervals.wilson_interval(4, 4))
    assert main["SR_ci95"] == pytest.approx(intervals.wilson_interval(8, 8))
    assert set(multi["per_seed"]) == {"5", "6"} and multi["per_seed"]["6"]["SPL"] == 1.0
    assert "95% interval" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["--episodes", "0"], "--episodes must be >= 1"),
    (["--states", "out.txt"], "must end in .npz"),
    (["--policy", "expert", "--train"], "only make sense with --policy planner"),
    (["--train", "--checkpoint", "x"], "exclude each other"),
    (["--train-steps", "5"], "only makes sense with --train"),
    (["--modes", "two_shot"], "--modes must be distinct modes"),
    (["--seeds", "1,1"], "--seeds must be distinct"),
    (["--settle", "-1"], "--settle must be between 0 and 10"),
])
def test_cli_rejects_bad_input(argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        kuka_cli.main("stacking", argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()  # argparse's usage (wrapped), then one error line
    assert message in lines[-1] and "Traceback" not in err


def test_missing_checkpoint_says_how_to_get_one(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        kuka_cli.main("rearrangement", ["--checkpoint", str(tmp_path / "none"),
                                           "--no-progress"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "kuka_rearrangement --train" in err and len(err.splitlines()) == 1


# ------------------------------------------------------------------------------ planner

@pytest.fixture(scope="module")
def train_dir(tmp_path_factory):
    """One tiny training (3 steps of the tiny model) shared by both experiments: the
    second `--train` finds it finished and evaluates it."""
    return tmp_path_factory.mktemp("kuka_train") / "run"


def _planner_run(kind, train_dir, out, extra):
    argv = ["--train", "--train-steps", "3", "--model-size", "tiny", "--train-dir",
            str(train_dir), "--episodes", "4",
            "--seed", "6", "--batch-size", str(kf.BATCH), "--json", str(out / "r.json"),
            "--states", str(out / "s.npz"), "--no-progress", *extra]
    return kuka_cli.main(kind, argv)


def _check_planner_result(result, out, kind, modes, languages):
    data = json.loads((out / "r.json").read_text())
    assert data == json.loads(json.dumps(result))
    assert data["policy"] == "planner" and data["modes"] == list(modes)
    assert data["checkpoint"] is not None and data["train_seconds"] is not None
    main, rows = data["rows"][0], data["rows"][1:]
    assert data["states_method"] == main["method"]
    assert main["method"] == "planner on-the-fly" + (", read" if data["reader"] else "")
    assert len(rows) == 2 * len(modes) * len(languages)
    for row in rows:
        # Both are counts of the row's instructed constraints, in percent.
        for key in ("SR", "SR_diffuser"):
            count = row[key] * row["constraints"] / 100.0
            assert 0 <= round(count) <= row["constraints"]
            assert count == pytest.approx(round(count), abs=1e-6), (key, row)
        assert row["constraints"] >= row["episodes"] == 4
        calls = row["denoiser_calls_per_episode"]
        if row["mode"] == "one_shot":
            assert calls == 10.0 and row["plans_per_episode"] == 1.0
        else:  # one 10-step plan per placement
            assert calls == pytest.approx(10.0 * row["placements_per_episode"])
    states = _load_states(out / "s.npz")
    assert set(states) == STATE_FIELDS and states["block_pos"].shape == (8, 4, 3)
    # Contract 4: the main row's SR is the share of instructed constraints holding.
    assert main["SR"] == pytest.approx(_recomputed_sr(states), abs=1e-9)
    single, multi = [r for r in rows if r["mode"] == "on_the_fly"
                     and r["language"] == languages[0]]
    assert single["SR"] == pytest.approx(_recomputed_sr(states, range(4)), abs=1e-9)
    assert multi["SR"] == pytest.approx(_recomputed_sr(states, range(4, 8)), abs=1e-9)
    multi_count = 3 if kind == "stacking" else 2
    counts = (states["constraints"][..., 0] >= 0).sum(-1)
    np.testing.assert_array_equal(counts, [1] * 4 + [multi_count] * 4)


def test_stacking_planner_end_to_end(train_dir, tmp_path):
    figs = tmp_path / "figs"
    result = _planner_run("stacking", train_dir, tmp_path,
                          ["--figures", str(figs), "--num-figures", "1"])
    _check_planner_result(result, tmp_path, "stacking", ("on_the_fly", "one_shot"),
                          ("canonical",))
    names = sorted(p.name for p in figs.glob("*.png"))
    assert names == ["stacking_multi_canonical_000.png", "stacking_single_canonical_000.png"]


def test_rearrangement_planner_end_to_end_with_paraphrases(train_dir, tmp_path):
    """With a (tiny) reader: its rows say so and the run records it."""
    from diffplan.reader import save_reader, train_reader
    from envs.kuka import reader

    config = reader.reader_config(dim=16, num_layers=1, num_heads=2)
    save_reader(str(tmp_path / "reader"), config,
                train_reader(config, reader.role_batch, [0], 2))
    result = _planner_run("rearrangement", train_dir, tmp_path,
                          ["--modes", "on_the_fly", "--language", "both",
                           "--reader", str(tmp_path / "reader")])
    assert result["reader"] == str(tmp_path / "reader")
    assert all(r["method"].endswith(", read") for r in result["rows"][1:])
    _check_planner_result(result, tmp_path, "rearrangement", ("on_the_fly",),
                          ("canonical", "paraphrased"))
    rows = result["rows"][1:]
    assert [r["language"] for r in rows] == ["canonical"] * 2 + ["paraphrased"] * 2
    assert all("paraphrased" in r["method"] for r in rows[2:])
    assert not any("per_phrasing" in r for r in rows[:2])  # canonical: one phrasing
    for row in rows[2:]:  # each paraphrase's constraints counted under it, the rest nowhere
        split = row.get("per_phrasing", [{"template": 1, "constraints": row["constraints"]}])
        assert sum(p["constraints"] for p in split) == row["constraints"]
        assert all(1 <= p["template"] <= 7 for p in split)
    # The states are those of the main (canonical) row's episodes.
    states = _load_states(tmp_path / "s.npz")
    for c, text in zip(states["constraints"], states["instruction"]):
        assert str(text) == grammar.render(c, False)


def test_videos_render_or_say_why(tmp_path, monkeypatch, capsys):
    final, frames = kf.expert_run("rearrangement_single", 11)
    videos = {"ep": frames[0, 0, ::6]}
    written = kuka_cli.write_videos(str(tmp_path / "v"), videos)
    if written:  # a GL backend exists here
        from PIL import Image

        with Image.open(written[0]) as gif:
            assert gif.n_frames == len(videos["ep"])
    monkeypatch.setattr(render, "GL_BACKENDS", ("no-such-backend",))
    assert kuka_cli.write_videos(str(tmp_path / "w"), videos) == []
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "no GL backend" in ln]
    assert len(lines) == 1


def test_ship_kuka_checkpoint_with_its_note(train_dir, tmp_path):
    """ship_checkpoint --world kuka exports the (tiny) run with a NOTE.md holding the training
    command, the task specs and the Kuka results table; the export loads as the Kuka denoiser."""
    from experiments.shipping import denoiser as ship_checkpoint

    out = tmp_path / "res"
    out.mkdir()
    _planner_run("rearrangement", train_dir, out, ["--modes", "on_the_fly"])
    dest = tmp_path / "shipped"
    ship_checkpoint.main(["--world", "kuka", "--train-dir", str(train_dir), "--out", str(dest),
                          "--results", str(out / "r.json")])
    note = (dest / "NOTE.md").read_text()
    assert "kuka_stacking --train" in note and "task specs" in note and "SR_Diff" in note
    assert ("python -m experiments.kuka_rearrangement --episodes 4 --seed 6 --modes on_the_fly"
            in note)
    assert "timestep_power" in note
    denoiser = kuka_spec.load_checked(str(dest), kuka_spec.NUM_STEPS, "stacking")
    assert denoiser.plan_shape == (24, 24, 3)


def test_note_commands_carry_the_kuka_flags_a_result_departs_in():
    """A NOTE's command reproduces its table: --modes, --carry and --reader when not the
    defaults, nothing added when they are."""
    from experiments.shipping.denoiser import _result_command

    base = {"experiment": "kuka_stacking", "episodes": 70, "seeds": [2001, 2002, 2003],
            "language": "all", "modes": ["on_the_fly", "one_shot"], "carry": "path",
            "reader": None}
    assert _result_command(base) == ("python -m experiments.kuka_stacking --episodes 70 "
                                     "--seeds 2001,2002,2003 --language all")
    read = dict(base, modes=["on_the_fly"], carry="arc", reader="checkpoints/kuka_reader")
    assert _result_command(read).endswith(
        "--language all --modes on_the_fly --carry arc --reader checkpoints/kuka_reader")
