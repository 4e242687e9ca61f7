"""The shipped BabyAI GoToLocal checkpoints (ours and BC) still load and still perform: on 64
minigrid episodes of seed 1777 (used for no choice), every action replayed in minigrid, ours
(warm start) at most one episode below what was measured when shipped and BC within three
episodes of it, and far shorter walks than the same planner with random weights; their NOTE.md
files record how they were made."""
from __future__ import annotations

import os

import pytest

from experiments.babyai import cli
from experiments.babyai.spec import SPECS

CHECKPOINT = SPECS["goto_local"].default_checkpoint()
EPISODES = 64
MEASURED = {"ours, warm start": 100.0, "BC": 26.5625, "random weights, warm start": 98.4375}
"""SR on these 64 episodes when shipped (`python -m experiments.babyai --level goto_local
--episodes 64 --seed 1777 --modes warm_start --no-bot --random-weights`): 64, 17 and 63 of 64.
Mean reward: ours 0.896, random weights 0.639."""


@pytest.fixture(scope="module")
def result():
    return cli.main(["--level", "goto_local", "--episodes", str(EPISODES), "--seed", "1777",
                     "--modes", "warm_start", "--no-bot", "--random-weights", "--no-progress"])


def test_the_level_defaults_to_the_shipped_checkpoints_with_notes(result):
    assert result["checkpoint"] == os.path.join("checkpoints", "babyai_goto_local")
    assert result["bc_checkpoint"] == os.path.join("checkpoints", "babyai_goto_local_bc")
    assert result["demos"] == 2000
    for name, needle in (("babyai_goto_local", "--level goto_local --train"),
                         ("babyai_goto_local_bc", "BC baseline")):
        note = open(os.path.join(os.path.dirname(CHECKPOINT), name, "NOTE.md")).read()
        assert needle in note and "--seeds 2001,2002,2003" in note


def test_ours_and_bc_perform_as_measured_in_minigrid(result):
    rows = {row["method"]: row for row in result["rows"]}
    assert set(rows) == set(MEASURED)
    del rows["random weights, warm start"]  # the next test
    assert result["measured_in"] == "minigrid"
    for method, row in rows.items():
        assert row["mismatches"] == 0, method
    assert rows["ours, warm start"]["SR"] >= MEASURED["ours, warm start"] - 100 / EPISODES
    assert abs(rows["BC"]["SR"] - MEASURED["BC"]) <= 3 * 100 / EPISODES
    # The learned planner is far ahead of BC on the same demonstrations.
    assert rows["ours, warm start"]["SR"] - rows["BC"]["SR"] > 50


def test_what_the_learned_denoiser_adds_is_the_short_walk(result):
    """In one 6 x 6 room, walking the known map to random goals faces the named object within
    64 actions almost always: the same planner with random weights succeeds about as often,
    but takes over three times the actions; the learned denoiser's reward is far above it."""
    rows = {row["method"]: row for row in result["rows"]}
    ours, control = rows["ours, warm start"], rows["random weights, warm start"]
    assert abs(control["SR"] - MEASURED["random weights, warm start"]) <= 3 * 100 / EPISODES
    assert ours["mean_steps"] * 2.5 < control["mean_steps"]
    assert ours["mean_reward"] - control["mean_reward"] > 0.15
