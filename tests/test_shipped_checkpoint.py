"""The shipped grid-world checkpoint still loads and still performs: on-the-fly SR and
SR_ordered >= 95% on 64 fresh P-MO2G episodes (seed 4242, used for no choice; measured 100 / 100
when shipped), on the executed trajectories."""
import os

import jax
import numpy as np
import pytest

from diffplan.metrics import trajectory_metrics
from experiments import compile_common as cc

CHECKPOINT = os.path.join(cc.CHECKPOINT_ROOT, cc.TRAINING_NAME)


@pytest.fixture(scope="module")
def shipped():
    if not os.path.isdir(CHECKPOINT):
        pytest.fail(f"the shipped checkpoint {CHECKPOINT} is missing")
    spec = cc.SPECS["p_mo2g"]
    denoiser, metadata = cc.load_model(CHECKPOINT)
    return spec, denoiser, metadata


def test_checkpoint_has_a_note_with_its_provenance():
    note = open(os.path.join(CHECKPOINT, "NOTE.md")).read()
    for needle in ("--train", "seed", "SR"):
        assert needle in note


def test_checkpoint_config_matches_the_default_model(shipped):
    spec, denoiser, metadata = shipped
    assert denoiser.model_config == spec.model_config("default")
    assert metadata["extra"] == {**spec.recipe().metadata(), "model_size": "default"}
    assert metadata["train_config"] == spec.train_config().to_dict()


def test_on_the_fly_sr_on_64_p_mo2g_episodes(shipped):
    spec, denoiser, _ = shipped
    task = spec.task(denoiser.num_gen_channels)
    # Episodes from a seed used by no shipped number (README uses 1000).
    episodes = cc.eval_episodes(spec.grid_config(), 64, seed=4242)
    rollout, _ = cc.evaluate_mode(spec, task, denoiser, episodes, 4242, "on_the_fly", 64,
                                  progress=False)
    m = trajectory_metrics(rollout.positions, rollout.steps, episodes.target,
                           episodes.expert_path, episodes.reference)
    assert m["SR"] >= 95.0 and m["SR_ordered"] >= 95.0, m
    # Success is what the agent executed: standing on the target at the end.
    final = rollout.positions[np.arange(64), rollout.steps]
    np.testing.assert_array_equal(np.all(final == np.asarray(episodes.target), -1),
                                  np.asarray(rollout.final_state.success))
