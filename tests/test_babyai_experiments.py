"""``python -m experiments.babyai``: a tiny end-to-end run (--train of a tiny denoiser and BC
on 6 demonstrations, 8 GoToLocal episodes) whose rows come from minigrid (every executed action
replayed there, no port/minigrid mismatch; a planted replay defect is counted and fails the
run), a run with --demos N that never reads a training layout >= N (a planted read of layout N
is caught), bad input refused in one line, and the sample-efficiency sweep's resumption and
figure (its training and evaluation stubbed)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from envs.babyai import baselines as bb
from envs.babyai import episode as E
from envs.babyai import metrics, seeds, training
from experiments.babyai import baselines, cli, demos as sweep, figures

DEMOS = 6
EPISODES = 8


def _read_beyond(recorded, n: int) -> list[int]:
    """The training layouts >= n among recorded minigrid seeds (other streams ignored)."""
    low, _ = seeds.seed_range(*seeds.STREAMS["training"])
    return sorted({int(s) - low for s in recorded if low <= int(s) < 2 ** 32 and
                   int(s) - low >= n})


def _recording(monkeypatch, recorded: list):
    """Every minigrid seed a layout is reset with, and every layout a batch can draw."""
    def wrap(fn):
        def sampler(layouts):
            recorded.extend(int(s) for s in layouts.seeds)
            return fn(layouts)
        return sampler

    layout = E.layout
    monkeypatch.setattr(E, "layout", lambda env, config, seed: (recorded.append(int(seed)),
                                                                layout(env, config, seed))[1])
    monkeypatch.setattr(training, "layout_sampler", wrap(training.layout_sampler))
    monkeypatch.setattr(bb, "layout_sampler", wrap(bb.layout_sampler))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("babyai_cli")
    recorded = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DIFFPLAN_BABYAI_CACHE", str(root / "cache"))
        _recording(mp, recorded)
        argv = ["--level", "goto_local", "--train", "--model-size", "tiny", "--train-steps", "2",
                "--demos", str(DEMOS), "--bc-steps", "2", "--episodes", str(EPISODES),
                "--modes", "warm_start",
                "--batch-size", "16", "--train-dir", str(root / "run"), "--json",
                str(root / "out.json"), "--no-progress"]
        result = cli.main(argv)
    return root, argv, result, recorded


def test_rows_are_measured_in_minigrid(run):
    root, _, result, _ = run
    methods = [r["method"] for r in result["rows"]]
    assert methods == ["ours, warm start", "BC", "BabyAI bot"]
    for row in result["rows"]:
        assert row["episodes"] == EPISODES
        assert row["SR"] == pytest.approx(100.0 * row["successes"] / EPISODES)
        if row["method"] != "BabyAI bot":
            assert row["mismatches"] == 0
    assert result["rows"][-1]["SR"] == 100.0          # the bot solves GoToLocal
    assert result["demos"] == DEMOS and result["measured_in"] == "minigrid"
    assert json.loads((root / "out.json").read_text())["rows"] == result["rows"]


def test_a_replay_defect_is_counted_and_fails_the_run(run, monkeypatch, capsys):
    """Control: minigrid replays each episode without its last action."""
    root, _, _, _ = run
    replay = metrics.replay

    def short(config, seed_list, actions, *a, **k):
        actions = np.array(actions)
        last = (actions != metrics.NO_ACTION).sum(axis=1) - 1
        actions[np.arange(len(actions)), np.maximum(last, 0)] = metrics.NO_ACTION
        return replay(config, seed_list, actions, *a, **k)

    monkeypatch.setattr(metrics, "replay", short)
    monkeypatch.setenv("DIFFPLAN_BABYAI_CACHE", str(root / "cache"))
    with pytest.raises(SystemExit) as info:
        cli.main(["--level", "goto_local", "--checkpoint", str(root / "run"), "--modes",
                  "warm_start", "--no-bc", "--no-bot", "--episodes", str(EPISODES),
                  "--batch-size", "16", "--json", str(root / "bad.json"), "--no-progress"])
    assert info.value.code == 1
    assert json.loads((root / "bad.json").read_text())["rows"][0]["mismatches"] == EPISODES
    assert "ended differently in the port and in minigrid" in capsys.readouterr().err


def test_demos_never_reads_a_layout_beyond_n(run, tmp_path, monkeypatch):
    _, _, _, recorded = run
    assert recorded and _read_beyond(recorded, DEMOS) == []
    # the control: a run that also reads training layout N is caught
    planted = []
    _recording(monkeypatch, planted)
    layouts = training.cached_layouts("goto_local", DEMOS + 1, cache_dir=tmp_path)
    training.layout_sampler(layouts)
    assert _read_beyond(planted, DEMOS) == [DEMOS]


def test_bc_learns_the_experts_actions_on_the_demonstrations(run):
    """BC's examples: the task's condition after k expert actions, the mission's one-hot colour
    and type, and the expert's action k."""
    import jax

    from envs.babyai.config import make_config
    from envs.babyai.task import BabyAITask

    root, _, _, _ = run
    layouts = training.load_layouts(root / "cache" / f"goto_local_0_{DEMOS}.npz")
    task = BabyAITask(make_config("goto_local"))
    conditions, goals, actions = jax.device_get(jax.jit(bb.bc_batch_fn(task, layouts),
                                                        static_argnums=1)(
        jax.random.PRNGKey(0), 16))
    assert conditions.shape == (16, 8, 8, 8) and goals.shape == (16, bb.GOAL_DIM)
    assert set(np.unique(actions)) <= {0, 1, 2, 5}      # left, right, forward, toggle
    assert (goals.sum(axis=1) == 2).all()
    for mission, ids in zip(layouts.missions, layouts.episodes.tokens):
        colour, kind = mission.split()[-2:]
        goal = np.asarray(bb.goal_vector(ids))
        assert goal[bb.COLOR_IDS.index(bb.grammar.WORDS.index(colour))] == 1
        assert goal[6 + bb.TYPE_IDS.index(bb.grammar.WORDS.index(kind))] == 1


@pytest.mark.parametrize("argv, needle", [
    (["--level", "nowhere"], "unknown BabyAI level 'nowhere'"),
    (["--level", "putnext"], "not one the Task can plan"),
    (["--level", "BabyAI-PutNextLocal-v0"], "not one the Task can plan"),
    (["--level", "goto", "--mission", "go to the pink ball"], "outside the GoTo grammar"),
    (["--level", "goto", "--mission", "put the red ball next to the blue box"],
     "outside the GoTo grammar"),
    (["--level", "goto", "--demos", "10"], "--demos and --detour-prob set what --train"),
    (["--level", "goto", "--demos-sweep", "100,x"], "comma-separated integers"),
    (["--level", "goto", "--modes", "one_shot"], "--modes must be"),
    (["--level", "goto", "--seed", "4242"], "must be below 2048"),
    (["--level", "goto", "--seeds", "2001,2048"], "must be below 2048"),
])
def test_bad_input_is_one_line(argv, needle, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert info.value.code == 2 and needle in err[-1]
    assert sum(needle in line for line in err) == 1


def test_a_missing_checkpoint_names_the_train_command(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(["--level", "goto", "--checkpoint", str(tmp_path / "none")])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "python -m experiments.babyai --level goto --train" in err[0]


def test_the_sweep_resumes_and_reports_the_fewest_reaching_99(tmp_path, monkeypatch, capsys):
    """Training and evaluation stubbed: each N's validation row is written once (a rerun reads
    it), only the fewest N reaching 99% is evaluated on the evaluation seeds, and the figure's
    labels overlap nothing."""
    calls = []
    rates = {100: 80.0, 300: 99.2, 1000: 99.9}
    monkeypatch.setattr(sweep, "train", lambda spec, run_dir, **k: calls.append(("train", k[
        "demos"])))
    monkeypatch.setattr(sweep.harness, "load_checked", lambda *a: None)
    monkeypatch.setattr(baselines, "denoiser_minutes", lambda d: 1.0)
    monkeypatch.setattr(sweep, "_evaluate", lambda spec, den, mode, seeds, n, b, p: calls.append(
        ("eval", tuple(seeds))) or {"SR": rates[calls[-2][1]], "SR_ci95": [70.0, 100.0],
                                    "episodes": n, "mismatches": 0})
    argv = ["--level", "goto_local", "--demos-sweep", "1000,100,300", "--sweep-dir",
            str(tmp_path), "--seeds", "2001,2002", "--episodes", "50", "--no-progress"]
    first = cli.main(argv)
    assert first["fewest_demos"] == 300 and first["evaluation"]["seeds"] == [2001, 2002]
    assert [c for c in calls if c[0] == "eval"] == [("eval", (1000,))] * 3 + [
        ("eval", (2001, 2002))]
    assert (tmp_path / "demos_100" / "validation.json").exists()
    assert (tmp_path / "demos_300" / "evaluation.json").exists()
    assert (tmp_path / "success_vs_demos.png").exists()
    calls.clear()
    assert cli.main(argv)["rows"] == first["rows"] and calls == []     # resumed from files
    fig = figures.draw("goto_local", first["rows"], first["evaluation"], [], 99.0)
    renderer = fig.canvas.get_renderer()
    boxes = [t.get_window_extent(renderer) for t in fig.axes[0].texts]
    assert len(boxes) == 3 and not any(a.overlaps(b) for i, a in enumerate(boxes)
                                       for b in boxes[i + 1:])


def test_published_entries_are_complete():
    """Every published number names its paper, table, level, source and a demos count the code
    can plot; a 99% threshold entry carries success 99 and its interval's high end."""
    from experiments.babyai.spec import PUBLISHED, SPECS, published

    keys = {"paper", "table", "level", "demos", "success", "what", "source"}
    for p in PUBLISHED:
        assert keys <= set(p) and p["level"] in SPECS, p
        assert isinstance(p["demos"], int) and p["demos"] > 0, p
        assert all(p[k] for k in ("paper", "table", "source")), p
        if p["what"] == "demos to reach 99%":
            assert p["success"] == 99.0 and p.get("demos_high", p["demos"]) >= p["demos"], p
        else:
            assert p["what"] == f"success with {p['demos']} demos", p
    assert sum(len(published(level)) for level in SPECS) == len(PUBLISHED)
    # The transcribed values, pinned: changing one is a deliberate edit of this list too.
    assert [(p["level"], p["table"], p["demos"], p.get("demos_high"), p["success"])
            for p in PUBLISHED] == [
        ("goto_local", "Table 3 (second-hand)", 148_500, 193_200, 99.0),
        ("goto", "Table 3 (second-hand)", 341_100, 408_500, 99.0),
        ("goto", "Table 3 (second-hand)", 10_000, None, 96.1),
        ("goto_local", "Table 4 (second-hand)", 1_000_000, None, 100.0),
        ("goto", "Table 4 (second-hand)", 1_000_000, None, 100.0)]


def test_published_numbers_print_with_their_interval_and_table():
    from experiments.babyai import tables as bt
    from experiments.babyai.spec import published

    text = bt.format_published(published("goto_local"))
    for p in published("goto_local"):
        assert f"{p['paper']}, {p['table']}: {p['what']}" in text
        if "demos_high" in p:
            assert f"{p['demos']}-{p['demos_high']} demos" in text
    assert "none found" in bt.format_published([])
