"""The shipped grid-world denoiser on pretrained text features (checkpoints/
compile_gridworld_pretrained) still loads and still performs: the warm-start row (the CLI's
default) on 64 fresh episodes of seed 4242 (used for no choice), P-MO2G with canonical and
with paraphrased instructions and MO1G canonical, each at most one episode below all 64 (its
rows on 3 x 1000 evaluation episodes read SR 100.0, P-MO2G ordered 100.0 / 99.97), on the
executed trajectories; and its
recorded text encoder is the shipped one, hashes checked. The sealed natural-language set is
not used here: it is measured once, by the CLI (docs/results.md)."""
import dataclasses
import os

import numpy as np
import pytest

from envs.gridworld.metrics import trajectory_metrics
from experiments.gridworld import eval as ge
from experiments.gridworld.spec import SPECS, TRAINING_NAME
from experiments.harness import core as harness

CHECKPOINT = os.path.join(harness.CHECKPOINT_ROOT, f"{TRAINING_NAME}_pretrained")
MIN_SR = 100.0 * 63 / 64


@pytest.fixture(scope="module")
def shipped():
    from experiments.harness.text import checkpoint_encoder

    if not os.path.isdir(CHECKPOINT):
        pytest.fail(f"the shipped checkpoint {CHECKPOINT} is missing")
    denoiser, metadata = harness.load_model(CHECKPOINT)
    return denoiser, metadata, checkpoint_encoder(CHECKPOINT, denoiser)


def test_note_and_config_are_the_features_recipe(shipped):
    denoiser, metadata, encoder = shipped
    note = open(os.path.join(CHECKPOINT, "NOTE.md")).read()
    for needle in ("--train --text pretrained", "seed", "SR"):
        assert needle in note
    spec = dataclasses.replace(SPECS["p_mo2g"], text="pretrained")
    assert denoiser.model_config == spec.model_config("default")
    assert denoiser.model_config.cell_lookup and denoiser.model_config.context_dim == 384
    assert metadata["extra"]["text"] == "pretrained"
    assert metadata["extra"]["text_encoder"]["directory"] is None  # the shipped encoder
    assert metadata["train_config"] == spec.train_config().to_dict()
    assert encoder is not None and encoder.dim == 384


@pytest.mark.parametrize("setting,language", [("p_mo2g", "canonical"),
                                              ("p_mo2g", "paraphrased"),
                                              ("mo1g", "canonical")])
def test_warm_start_on_64_episodes(shipped, setting, language):
    from experiments.gridworld.text import with_features

    denoiser, _, encoder = shipped
    spec = dataclasses.replace(SPECS[setting], text="pretrained", language=language)
    task = spec.task(denoiser.num_gen_channels, features=True)
    episodes = with_features(ge.eval_episodes(spec.grid_config(), 64, seed=4242), setting,
                             encoder)
    rollout, _ = ge.evaluate_mode(spec, task, denoiser, episodes, 4242, "warm_start", 64,
                                  progress=False)
    m = trajectory_metrics(rollout.positions, rollout.steps, episodes.target,
                           episodes.expert_path, episodes.reference)
    assert m["SR"] >= MIN_SR, (setting, language, m)
    if setting == "p_mo2g":
        assert m["SR_ordered"] >= MIN_SR, (language, m)
    final = rollout.positions[np.arange(64), rollout.steps]
    np.testing.assert_array_equal(np.all(final == np.asarray(episodes.target), -1),
                                  np.asarray(rollout.final_state.success))
