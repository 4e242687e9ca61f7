"""The grid world's printed tables: the columns of a result row (contract 2), the legend printed
under every grid-world table (the CompILE CLIs, ``baselines_eval``, ``ablation_compile``) with
each row's planning mode as the ``--modes`` flag spells it, and the per-seed intervals."""
from __future__ import annotations

from experiments.gridworld.spec import METHOD_NAMES
from experiments.harness.tables import format_intervals as _intervals, format_table as _table

TABLE_COLUMNS = (("method", "{:<22}", "method"), ("SR", "{:>7.2f}", "SR"),
                 ("SR_ordered", "{:>7.2f}", "SR_ord"), ("GD", "{:>6.3f}", "GD"),
                 ("path_precision", "{:>7.2f}", "Prec"), ("path_recall", "{:>7.2f}", "Rec"),
                 ("path_f1", "{:>7.2f}", "F1"), ("SPL", "{:>6.3f}", "SPL"),
                 ("plan_f1", "{:>7.2f}", "planF1"),
                 ("denoiser_calls_per_episode", "{:>8.1f}", "calls"),
                 ("fallback_percent", "{:>6.2f}", "fb%"), ("seconds", "{:>8.1f}", "sec"))

LEGEND = (
    ("SR", "% of episodes on the target within 100 moves"),
    ("SR_ord", "% that stood on the reference first, as told"),
    ("GD", "mean final distance to the target, cells"),
    ("Prec/Rec/F1", "executed cells against the expert path's, pooled, %"),
    ("SPL", "success x expert's moves / agent's moves, 0-1"),
    ("planF1", "path F1 of the first plan, %"),
    ("calls", "denoiser calls per episode"),
    ("fb%", "% of moves psi made without the plan's marks (--psi follow)"),
    ("sec", "wall seconds of the row over all its seeds, including compiling its program (a "
            "load when the compilation cache holds it): a planner row's once per seed, another "
            "row's the first time the process runs it"))
"""The columns' legend. `sec`: each seed's planner evaluation builds its jitted rollout afresh
(harness.core.rollout_fn), a policy's is cached per process (harness.core.policy_runner), and
the timer starts before the first call."""

MODE_MEANINGS = {"one_shot": "one plan at t = 0", "k_shot": "a second plan at the first's goal",
                 "on_the_fly": "a plan from noise before every move, or as --replan says",
                 "warm_start": "re-plans warm-started from the last plan when new cells were "
                               "seen, or as --replan says"}
"""Each planning mode's row in a few words (its name is METHOD_NAMES[mode])."""

OTHER_ROWS = {"exact posterior": "a denoiser that learns nothing, exact guesses",
              "BC": "behaviour cloning", "CQL": "conservative Q-learning",
              "DD-style": "diffusion over states + inverse dynamics",
              "searcher": "no learning: reference, then target or unseen cells where told",
              "oracle": "the expert's shortest path, whole map known"}
"""The other rows (attribution rows, baselines, reference agents) in a few words."""


def _mode(method: str) -> str | None:
    """The planning mode a row's method names ("warm-start on-the-fly, unseen": warm_start;
    an ablation's "p_mo2g + on the fly": none), or None."""
    base = method.split(",")[0]
    for mode, name in sorted(METHOD_NAMES.items(), key=lambda kv: -len(kv[1])):
        if base == name or base.endswith(" " + name):
            return mode
    return None


def rows_legend(rows) -> list[tuple[str, str]]:
    """(name, meaning) of the row names the rows use: each planning mode with its ``--modes``
    value ("two-shot = k_shot (...)"), then the baselines and reference agents."""
    methods = [str(r.get("method", "")) for r in rows]
    modes = {_mode(m) for m in methods}
    return ([(name, f"{mode} ({MODE_MEANINGS[mode]})") for mode, name in METHOD_NAMES.items()
             if mode in modes]
            + [(name, meaning) for name, meaning in OTHER_ROWS.items()
               if any(name in m.split(", ") or m.split(", ")[0].endswith(" " + name)
                      for m in methods)])


def format_table(rows, extra_rows=()) -> str:
    """A plain-text table of result rows (missing values shown as '-'), then its legend: the
    columns, and a "rows:" line (the planning modes as ``--modes`` names them, the other rows,
    extra_rows' (name, meaning) pairs)."""
    return _table(rows, TABLE_COLUMNS, LEGEND, rows_legend(rows) + list(extra_rows))


def format_intervals(rows, seeds) -> str:
    """Per-seed SR and the pooled 95% intervals, one line per row."""
    return _intervals(rows, seeds, 22)
