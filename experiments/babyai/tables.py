"""The BabyAI tables: the rows measured in minigrid with their legend, the published
imitation-learning numbers shown beside them, and the demonstrations sweep's table."""
from __future__ import annotations

from experiments.babyai.spec import METHOD_NAMES
from experiments.harness import tables

COLUMNS = (
    ("method", "{:<18}", "method"),
    ("SR", "{:>7.2f}", "SR", "% of episodes with minigrid's reward > 0 (minigrid's own success)"),
    ("mean_reward", "{:>6.3f}", "reward", "minigrid's mean return, 1 - 0.9 x steps / "
                                           "max_steps on success, 0 otherwise"),
    ("mean_steps", "{:>7.1f}", "steps", "actions per episode (a failure runs to max_steps)"),
    ("denoiser_calls_per_episode", "{:>7.1f}", "calls", "denoiser calls per episode"),
    ("mismatches", "{:>5d}", "mism", "episodes whose end (step, reward, termination, pose) "
                                     "differs between the port and minigrid: must be 0"),
    ("seconds", "{:>7.1f}", "sec", "wall seconds of the row over its seeds: its program's "
                                   "compilation (a load when cached), acting, and the replay "
                                   "in minigrid"))

RANDOM_ROW = "random weights, warm start"
OTHER_ROWS = {RANDOM_ROW: "the same planner, psi and triggers with a denoiser "
                                           "of random weights (--random-weights): nothing "
                                           "learned",
              "BC": "behaviour cloning of the same demonstrations, on the same condition "
                    "channels (one-hot colour and type of the mission)",
              "BabyAI bot": "minigrid.utils.baby_ai_bot.BabyAIBot, run in minigrid"}


def rows_legend(rows) -> list[tuple[str, str]]:
    """(name, meaning) of the rows present."""
    meanings = {"ours, on-the-fly": "on_the_fly (a plan from noise before every action)",
                "ours, warm start": "warm_start (the last plan re-noised and denoised in one "
                                    "call when a cell looks different or the plan's goal is "
                                    "reached)", **OTHER_ROWS}
    assert set(METHOD_NAMES.values()) <= set(meanings)
    present = {r["method"] for r in rows}
    return [(name, meaning) for name, meaning in meanings.items() if name in present]


def format_table(rows) -> str:
    return tables.format_table(rows, COLUMNS, row_names=rows_legend(rows))


def format_intervals(rows, seeds) -> str:
    return tables.format_intervals(rows, seeds, 18)


def format_published(entries) -> str:
    """The published imitation-learning numbers of the level (spec.PUBLISHED; a 99% interval of
    demonstrations as low-high), or a line saying none was found for it."""
    if not entries:
        return ("published imitation learning (BabyAI papers): none found for this level "
                "(experiments/babyai/spec.py, PUBLISHED, says what was looked for)")
    lines = ["published imitation learning (not measured here; a table marked 'second-hand' "
             "was read in a write-up of the paper, not in the paper):"]
    for p in entries:
        demos = (f"{p['demos']}-{p['demos_high']}" if p.get("demos_high", p["demos"])
                 != p["demos"] else f"{p['demos']}")
        lines.append(f"  {p['paper']}, {p['table']}: {p['what']}: {demos} demos, "
                     f"{p['success']}% success")
    return "\n".join(lines)


SWEEP_COLUMNS = (("run", "{:<12}", "demos", "training episodes (expert demonstrations, "
                                            "layouts 0..N-1)"),
                 ("SR", "{:>7.2f}", "SR", "validation SR in minigrid, %"),
                 ("SR_low", "{:>7.2f}", "low", "lower end of its 95% Wilson interval"),
                 ("mismatches", "{:>5d}", "mism", "port/minigrid mismatches (must be 0)"),
                 ("train_minutes", "{:>7.1f}", "train", "minutes of optimisation"))


def format_sweep(rows) -> str:
    return tables.format_table([{**r, "run": str(r["demos"])} for r in rows], SWEEP_COLUMNS)
