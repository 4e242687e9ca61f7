"""Every printed results table ends with a legend of its columns (units; whether `sec` counts
compilation) and of its row names in the flags' spelling; progress bars say "compiling" until
the program runs and time their ETA from then on."""
from __future__ import annotations

import io
import re

import pytest

from experiments.harness import tables


def _legend_names(text: str) -> set[str]:
    """The names a table's legend explains ("a / b" and "a/b/c" count for each part)."""
    body = text.split("legend: ", 1)[1]
    names = set()
    for entry in re.split(r"; (?=[^;]*? = )", " ".join(body.split())):
        name = entry.split(" = ", 1)[0].strip()
        names.update(n.strip() for n in re.split(r" / |/|, ", name))
    return names


def _headers(text: str) -> list[str]:
    return text.splitlines()[0].split()


GRID_ROWS = [{"method": m, "SR": 100.0, "seconds": 3.0} for m in (
    "one-shot", "two-shot", "on-the-fly", "warm-start on-the-fly", "on-the-fly, unseen",
    "on-the-fly, exact posterior", "BC", "searcher", "oracle")]


def test_grid_world_table_explains_every_column_and_the_mode_of_every_row():
    from experiments.gridworld import eval as ge
    from experiments.gridworld.spec import METHOD_NAMES

    text = ge.format_table(GRID_ROWS)
    explained = _legend_names(text)
    for header in _headers(text)[1:]:
        assert header in explained, header
    sec = text.split("sec = ", 1)[1]
    assert "including compiling" in " ".join(sec.split())
    rows = " ".join(text.split("rows: ", 1)[1].split())
    for mode, name in METHOD_NAMES.items():  # e.g. "two-shot = k_shot (...)"
        assert f"{name} = {mode} (" in rows
    for name in ("exact posterior", "BC", "searcher", "oracle"):
        assert f"{name} = " in rows
    # Only the names the table uses.
    assert "CQL" not in ge.format_table(GRID_ROWS[:1]) and "two-shot" not in \
        ge.format_table(GRID_ROWS[:1])


def test_ablation_rows_are_explained():
    from experiments.gridworld import eval as ge
    from experiments.gridworld.ablation import VARIANT_LEGEND, VARIANTS

    assert [name for name, _, _ in VARIANTS] == [name for name, _ in VARIANT_LEGEND]
    text = ge.format_table([{"method": "mo1g + on the fly"}], VARIANT_LEGEND)
    assert "+ on the fly = " in " ".join(text.split())


def test_kuka_table_explains_every_column_and_row_name():
    from experiments.kuka.tables import format_table

    text = format_table([{"method": "planner on-the-fly"},
                         {"method": "planner one-shot, single constraint, paraphrased, read"},
                         {"method": "BC, multi-constraint"}])
    explained = _legend_names(text)
    for header in _headers(text)[1:]:
        assert header in explained, header
    flat = " ".join(text.split())
    assert "compiled before timing (not counted)" in flat
    for part in ("planner on-the-fly = --policy planner --modes on_the_fly",
                 "planner one-shot = --policy planner --modes one_shot", "read = ",
                 "paraphrased = ", "BC / CQL / DD-style = "):
        assert part in flat, part


def test_sweep_and_benchmark_tables_end_with_their_legends():
    from experiments.bench import common as bc, gridworld as bg, unet as bu
    from experiments.sweeping.output import format_rows

    sweep = format_rows([dict(task="gridworld/p_mo2g", modes="warm_start", num_steps=10,
                              warm_num_steps=2, warm_start_step=1, replan="on_change", eta=0.0,
                              seed=2001, episodes=8, SR=100.0, denoiser_calls_per_episode=11.0,
                              seconds=1.0, compile_seconds=2.0)])
    explained = _legend_names(sweep)
    for header in _headers(sweep)[1:]:
        assert header in explained or header == "seed", header
    assert "compilation not included" in " ".join(sweep.split())
    grid = bg.format_table([dict(kind="generation", setting="p_mo2g", batch=4, per_second=1.0,
                                 best_per_second=2.0, target=None, ratio=None,
                                 compile_seconds=1.0)])
    assert "compile s = " in grid and grid.splitlines()[3].startswith("legend: ")
    unet = bu.format_table([dict(method="m", params=None, ms=1.0, best_ms=1.0, gflop=None,
                                 gflops=None, percent_of_peak=None, compile_seconds=1.0)])
    assert "% peak = " in unet
    for name, entries in bc.LEGENDS.items():
        assert tables.legend(entries).startswith("legend: "), name


def test_a_legend_wraps_and_a_table_without_meanings_has_none():
    text = tables.legend([("x", "word " * 40)])
    assert all(len(line) <= tables.LEGEND_WIDTH for line in text.splitlines())
    assert text.splitlines()[1].startswith("  ")
    plain = tables.format_table([{"method": "a"}], (("method", "{:<4}", "m"),))
    assert plain.splitlines() == ["m   ", "----", "a   "]
    with_meaning = tables.format_table([{"method": "a", "SR": 1.0}], (
        ("method", "{:<4}", "m"), ("SR", "{:>5.1f}", "SR", "success, %")), [("z", "zz")],
        [("a", "a row")])
    assert with_meaning.splitlines()[-2:] == ["legend: SR = success, %; z = zz", "rows: a = a row"]


def test_progress_bar_says_compiling_then_times_from_the_first_result(monkeypatch):
    """No ETA and "compiling" until the first update (or a report from inside the program);
    the rate, hence the ETA, counts only what ran after that (here: 10 units in 1 s after 60 s
    of compiling: 10/s, not 20 units / 61 s); compiling() says it again mid-bar."""
    from diffplan import progress
    from experiments.harness.progress import PARTS, RELAY

    now = [1000.0]
    monkeypatch.setattr(progress.time, "time", lambda: now[0])
    bar = progress.bar(total=100, file=io.StringIO(), mininterval=0)
    assert "compiling" in str(bar) and "<?" in str(bar)
    now[0] += 60.0
    bar.update(10)  # the first batch: compiling ended with it
    assert "compiling" not in str(bar) and "<?" in str(bar)
    now[0] += 1.0
    bar.update(10)
    assert bar.format_dict["rate"] == pytest.approx(10.0)
    assert "<00:08" in str(bar)  # 80 left at 10/s
    bar.compiling("compiling BC")
    assert "compiling BC" in str(bar) and "<?" in str(bar)
    bar.close()
    # A report from inside a jitted program (count 0: nothing finished yet) ends compiling.
    relayed = progress.bar(total=10, file=io.StringIO())
    token = RELAY.attach(relayed)
    RELAY(token * PARTS, 0)
    assert "compiling" not in str(relayed) and relayed.n == 0
    RELAY.detach(token)
    relayed.close()
