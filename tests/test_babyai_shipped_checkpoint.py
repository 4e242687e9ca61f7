"""The shipped BabyAI checkpoints (ours and BC, per level) still load and still perform: on
fresh minigrid episodes of seed 1777 (used for no choice), every action replayed in minigrid,
ours (warm start) at most one episode below what was measured when shipped and BC within three
episodes of it, and far shorter walks than the same planner with random weights; their NOTE.md
files record how they were made."""
from __future__ import annotations

import os

import pytest

from experiments.babyai import cli
from experiments.babyai.spec import SPECS

SEED = 1777
SHIPPED = {
    # `python -m experiments.babyai --level goto_local --episodes 64 --seed 1777 --modes
    # warm_start --no-bot --random-weights`: 64, 17 and 63 of 64; mean reward: ours 0.900,
    # random weights 0.692; actions 7.1 and 21.8.
    "goto_local": dict(episodes=64, measured={"ours, warm start": 100.0, "BC": 26.5625,
                                              "random weights, warm start": 98.4375},
                       steps_ratio=2.5, reward_gap=0.15),
    # `python -m experiments.babyai --level goto --episodes 32 --seed 1777 --modes warm_start
    # --no-bot --random-weights`: 32, 2 and 31 of 32; mean reward: ours 0.834, random weights
    # 0.612; actions 106.4 and 246.0.
    "goto": dict(episodes=32, measured={"ours, warm start": 100.0, "BC": 6.25,
                                        "random weights, warm start": 96.875},
                 steps_ratio=2.0, reward_gap=0.15),
}
"""Per level: the episodes of seed 1777 and the SR of each row on them when shipped, and how
far ahead of the random-weights control ours must stay (fewer actions by at least
steps_ratio, mean reward above it by at least reward_gap)."""


@pytest.fixture(scope="module", params=sorted(SHIPPED))
def shipped(request):
    level = request.param
    result = cli.main(["--level", level, "--episodes", str(SHIPPED[level]["episodes"]),
                       "--seed", str(SEED), "--modes", "warm_start", "--no-bot",
                       "--random-weights", "--no-progress"])
    return level, SHIPPED[level], result


def test_the_level_defaults_to_the_shipped_checkpoints_with_notes(shipped):
    level, _, result = shipped
    name = SPECS[level].name
    assert result["checkpoint"] == os.path.join("checkpoints", name)
    assert result["bc_checkpoint"] == os.path.join("checkpoints", name + "_bc")
    assert result["demos"] == 2000
    for folder, needle in ((name, f"--level {level} --train"), (name + "_bc", "BC baseline")):
        note = open(os.path.join(os.path.dirname(SPECS[level].default_checkpoint()), folder,
                                 "NOTE.md")).read()
        assert needle in note and "--seeds 2001,2002,2003" in note


def test_ours_and_bc_perform_as_measured_in_minigrid(shipped):
    _, expected, result = shipped
    measured, episodes = expected["measured"], expected["episodes"]
    rows = {row["method"]: row for row in result["rows"]}
    assert set(rows) == set(measured)
    del rows["random weights, warm start"]  # the next test
    assert result["measured_in"] == "minigrid"
    for method, row in rows.items():
        assert row["mismatches"] == 0, method
    assert rows["ours, warm start"]["SR"] >= measured["ours, warm start"] - 100 / episodes
    assert abs(rows["BC"]["SR"] - measured["BC"]) <= 3 * 100 / episodes
    # The learned planner is far ahead of BC on the same demonstrations.
    assert rows["ours, warm start"]["SR"] - rows["BC"]["SR"] > 50


def test_what_the_learned_denoiser_adds_over_random_weights(shipped):
    """The same planner, triggers and psi with random weights: walking the known map to random
    goals faces the named object before the step limit almost always (GoToLocal's one room,
    64 actions; GoTo's nine rooms, 576), so what the learned denoiser adds is the short walk
    (about 3 and 2.3 times fewer actions here, a far higher reward)."""
    _, expected, result = shipped
    rows = {row["method"]: row for row in result["rows"]}
    ours, control = rows["ours, warm start"], rows["random weights, warm start"]
    measured = expected["measured"]["random weights, warm start"]
    assert abs(control["SR"] - measured) <= 3 * 100 / expected["episodes"]
    assert ours["mean_steps"] * expected["steps_ratio"] < control["mean_steps"]
    assert ours["mean_reward"] - control["mean_reward"] > expected["reward_gap"]
