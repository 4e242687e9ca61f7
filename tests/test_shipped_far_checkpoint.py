"""The shipped P-MO2G-far checkpoint still loads and still performs: on 64 fresh P-MO2G-far
episodes (seed 4242, used for no choice), warm start re-planning only when refuted, with either
psi, SR and SR_ordered at most one episode below what was measured when shipped and SPL at most
0.03 below, on the executed trajectories; its NOTE.md records how it was made."""
import dataclasses
import os

import numpy as np
import pytest

from envs.gridworld.metrics import trajectory_metrics
from experiments.gridworld import eval as ge
from experiments.harness import core as harness
from experiments.gridworld.spec import FAR_TRAINING_NAME, SPECS
from test_shipped_checkpoint import load_shipped

CHECKPOINT = os.path.join(harness.CHECKPOINT_ROOT, FAR_TRAINING_NAME)
MEASURED = {"search": {"SR": 100.0, "SR_ordered": 100.0, "SPL": 0.946},
            "follow": {"SR": 96.875, "SR_ordered": 96.875, "SPL": 0.911, "fallback": 0.011}}
"""What the shipped model scored on these 64 episodes (warm start, on_refuted), per psi (the
follow psi with its default mark; fallback: the share of fallback moves)."""


@pytest.fixture(scope="module")
def shipped():
    return load_shipped(CHECKPOINT, "p_mo2g_far")


def test_it_is_the_far_settings_default_and_has_its_note(shipped):
    spec = shipped[0]
    assert spec.default_checkpoint() == CHECKPOINT
    assert SPECS["p_mo2g"].default_checkpoint() != CHECKPOINT
    note = open(os.path.join(CHECKPOINT, "NOTE.md")).read()
    for needle in ("compile_p_mo2g_far --train", "seed", "SPL", "p_mo2g_far"):
        assert needle in note


def test_its_config_is_the_far_recipe(shipped):
    spec, denoiser, metadata = shipped
    assert denoiser.model_config == spec.model_config("default")
    assert metadata["extra"] == {**spec.recipe().metadata(), "model_size": "default"}
    train_config = {**spec.train_config().to_dict()}
    assert {k: metadata["train_config"][k] for k in train_config
            if k not in ("checkpoint_every", "log_every", "max_log_every")} == \
        {k: v for k, v in train_config.items()
         if k not in ("checkpoint_every", "log_every", "max_log_every")}


@pytest.mark.parametrize("psi", ["search", "follow"])
def test_warm_start_on_refuted_on_64_far_episodes(shipped, psi):
    spec, denoiser, _ = shipped
    spec = dataclasses.replace(spec, replan="on_refuted", psi=psi)
    episodes = ge.eval_episodes(spec.grid_config(), 64, seed=4242)
    rollout, _ = ge.evaluate_mode(spec, spec.task(denoiser.num_gen_channels), denoiser,
                                  episodes, 4242, "warm_start", 64, progress=False)
    m = trajectory_metrics(rollout.positions, rollout.steps, episodes.target,
                           episodes.expert_path, episodes.reference,
                           expert_length=episodes.expert_length)
    measured = MEASURED[psi]
    assert m["SR"] >= measured["SR"] - 100 / 64 and \
        m["SR_ordered"] >= measured["SR_ordered"] - 100 / 64, m
    assert m["SPL"] >= measured["SPL"] - 0.03, m
    if psi == "follow":
        fallback = np.sum(rollout.fallback_moves) / np.sum(rollout.steps)
        assert fallback <= measured["fallback"] + 0.01, fallback
