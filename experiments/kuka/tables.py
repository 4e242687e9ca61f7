"""The Kuka world's printed table: the columns of a result row and the legend printed under it
(the columns, and what the row names say: who acts, as ``--policy`` and ``--modes`` spell it,
the Table 2 column, the phrasing)."""
from __future__ import annotations

from experiments.harness.tables import format_table as _table
from experiments.kuka.spec import LANGUAGE_CHOICES, METHOD_NAMES

TABLE_COLUMNS = (("method", "{:<46}", "method"), ("episodes", "{:>6d}", "eps"),
                 ("SR", "{:>7.2f}", "SR"), ("SR_diffuser", "{:>8.2f}", "SR_Diff"),
                 ("all_constraints", "{:>7.2f}", "all"), ("tower", "{:>7.2f}", "tower"),
                 ("placements_per_episode", "{:>6.2f}", "moves"), ("SPL", "{:>6.3f}", "SPL"),
                 ("denoiser_calls_per_episode", "{:>6.1f}", "calls"),
                 ("seconds", "{:>7.1f}", "sec"))

LEGEND = (
    ("eps", "episodes, all seeds"),
    ("SR", "strict success: % of instructed constraints that hold on the final physical poses "
           "at rest"),
    ("SR_Diff", "the same by Diffuser's looser check"),
    ("all", "% of episodes with every constraint held"),
    ("tower", "% of stacking episodes ending in one tower of four"),
    ("moves", "placements (pick-and-place actions) per episode"),
    ("SPL", "success x placements needed / placements made, 0-1"),
    ("calls", "denoiser calls per episode"),
    ("sec", "wall seconds of the row over all its seeds, physics and settling included; the "
            "planner's programs are compiled before timing (not counted), but the first column "
            "the process runs also compiles the settling step, and a baseline's or the "
            "expert's first column its own program"))
"""The columns' legend. `sec`: experiments.kuka.cli compiles every planning mode's program
(harness.compiling.compiled_planners) before its timers start; env.settle_batch, the reader's
restate_jit, harness.core.policy_runner and expert.run_expert compile on their first call."""

ROWS = {
    **{f"planner {name}": f"--policy planner --modes {mode}" for mode, name in
       METHOD_NAMES.items()},
    "single constraint / multi-constraint": "the Table 2 column (the first row: both pooled)",
    "read": "restated canonically by --reader first",
    "expert": "the scripted expert (--policy expert)",
    "BC / CQL / DD-style": "the baselines (--policy or --baselines bc, cql, dd)"}
"""What the parts of a row's name say."""


def rows_legend(rows) -> list[tuple[str, str]]:
    """(name, meaning) of the parts of the row names the rows use."""
    parts = {p for r in rows for p in str(r.get("method", "")).split(", ")}
    phrasings = sorted(parts & set(LANGUAGE_CHOICES))
    return [(name, meaning) for name, meaning in ROWS.items()
            if parts & set(name.split(" / "))] + (
        [(" / ".join(phrasings), "the phrasing (--language; none named: canonical)")]
        if phrasings else [])


UNREAD_COLUMN = ("unread_episodes", "{:>6d}", "unread",
                 "episodes whose instruction the reader could not restate (envs.kuka.reader: "
                 "not acted on, counted failed)")
"""Shown only when a reader refused some instruction."""


def format_table(rows) -> str:
    """A plain-text table of result rows (missing values shown as '-'), then its legend."""
    unread = (UNREAD_COLUMN,) if any(r.get("unread_episodes") for r in rows) else ()
    return _table(rows, TABLE_COLUMNS[:-1] + unread + TABLE_COLUMNS[-1:], LEGEND,
                  rows_legend(rows))
