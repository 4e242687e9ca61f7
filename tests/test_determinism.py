"""Determinism: the same seed gives the same episodes and results, whatever the batch size or
the number of slots of the evaluation (diffplan.planner.MIN_SUB_BATCH), with the shipped
network (real floating-point plans)."""
import os

import numpy as np
import pytest

from experiments import compile_common as cc

CHECKPOINT = os.path.join(cc.CHECKPOINT_ROOT, cc.TRAINING_NAME)


@pytest.fixture(scope="module")
def shipped():
    spec = cc.SPECS["p_mo2g"]
    denoiser, _ = cc.load_model(CHECKPOINT)
    episodes = cc.eval_episodes(spec.grid_config(), 20, seed=77)
    return spec, spec.task(denoiser.num_gen_channels), denoiser, episodes


@pytest.mark.parametrize("mode", ["on_the_fly", "warm_start", "k_shot"])
def test_per_episode_results_do_not_depend_on_the_batch_size(shipped, mode):
    """20 episodes at once, or 6 slots / 6 per batch (the last call padded): identical
    trajectories, calls and plans; and a second run repeats the first exactly."""
    spec, task, denoiser, episodes = shipped
    runs = [cc.evaluate_mode(spec, task, denoiser, episodes, 77, mode, b, progress=False)[0]
            for b in (20, 6, 20)]
    for other in runs[1:]:
        for name in ("positions", "steps", "denoiser_calls", "num_plans", "first_plan"):
            np.testing.assert_array_equal(getattr(runs[0], name), getattr(other, name),
                                          err_msg=f"{mode} {name}")
