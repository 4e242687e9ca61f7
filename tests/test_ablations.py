"""experiments.harness.ablations.random_weights: the same architecture, schedule and
constants, parameters that share nothing with the trained ones, and a refusal for other nets."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffplan.denoiser import Denoiser, DenoiserConfig, LoadedDenoiser, ModuleApply, init_params
from diffplan.schedule import cosine_schedule
from experiments.harness.ablations import random_weights


def _loaded(**overrides):
    cfg = DenoiserConfig(vocab_size=6, max_tokens=8, num_cond_channels=2, num_gen_channels=2,
                         widths=(8, 16), attn_levels=(), cross_attn_levels=(1,), groups=4,
                         head_dim=8, text_dim=16, embed_dim=8, **overrides)
    model = Denoiser(cfg)
    params = init_params(model, jax.random.PRNGKey(7), 8, 8)["params"]
    params = jax.tree.map(lambda x: x + 1.0, params)  # "trained": far from any fresh draw
    return LoadedDenoiser(params=params, schedule=cosine_schedule(10),
                          apply_fn=ModuleApply(model), prediction="x0", plan_shape=(8, 8, 2),
                          num_cond_channels=2, model_config=cfg)


def test_random_weights_keep_the_shapes_and_constants_and_change_the_rest():
    trained = _loaded(context_dim=10, cell_context=True)
    table = jnp.arange(60, dtype=jnp.float32).reshape(6, 10)
    trained = trained.replace(params={**trained.params, "frozen_cell_features": table})
    control = random_weights(trained)
    shapes = lambda p: jax.tree.map(jnp.shape, p)
    assert shapes(control.params) == shapes(trained.params)
    np.testing.assert_array_equal(np.asarray(control.params["frozen_cell_features"]), table)
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(control.params),
                            jax.tree.leaves(trained.params)):
        if "frozen" not in jax.tree_util.keystr(path):
            assert float(jnp.abs(a - b).min()) > 0, path
    # The output is not the constant plan of a fresh draw (its last layer is zero) ...
    x = jax.random.normal(jax.random.PRNGKey(1), (2, 8, 8, 4))
    tokens = jax.random.normal(jax.random.PRNGKey(2), (2, 8, 10))
    out = control.apply_fn(control.params, x, jnp.array([1, 5]), tokens)
    assert float(jnp.std(out)) > 1e-3
    # ... and the same seed gives the same weights; the schedule and config are kept.
    again = random_weights(trained)
    for a, b in zip(jax.tree.leaves(control.params), jax.tree.leaves(again.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert control.model_config == trained.model_config
    assert control.prediction == trained.prediction


def test_random_weights_refuse_a_network_that_is_not_a_denoiser():
    trained = _loaded()
    other = trained.replace(apply_fn=lambda p, x, t, tok: x[..., :2])
    with pytest.raises(ValueError, match="need a Denoiser checkpoint"):
        random_weights(other)
