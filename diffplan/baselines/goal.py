"""The learned-goal baseline: the denoiser's own network, trained to predict the next sub-goal
cell (and the goal) directly, as a classification over cells, instead of in-painting a plan.

It answers "does in-painting beat predicting the goal directly?" on equal footing: the same
network (:class:`diffplan.denoiser.Denoiser` of the same :class:`DenoiserConfig`, so the same
size), the same training batches (the world's ``Recipe``), the same optimiser, steps and
checkpoints (``diffplan.train.train`` with ``TrainConfig.objective = "goal"``,
:func:`diffplan.losses.goal_loss`), and at evaluation the same planner, triggers and psi:
:class:`GoalClassifier` is a ``Denoiser`` whose call returns a plan, so ``load_denoiser``,
``Planner`` and every CLI take it unchanged (one denoiser call per plan: ``--num-steps 1``).

The plan it returns (an "x0" prediction; B, H, W, G): the path channel -1 everywhere (no
route: the world's psi finds its own way), and each other channel the network's logits over
cells rescaled to [-1, 1] with their order kept (the argmax cell at +1, the least likely at
-1), so that a psi that takes the argmax among the cells it may still head for takes the
network's most likely such cell. The network never sees the sampler's noise: the generated
channels of its input are set to 0 and its timestep to 0, in training and in planning.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffplan import models
from diffplan.denoiser import Denoiser, DenoiserConfig

__all__ = ["GoalClassifier", "cell_logits_input", "rescale_cells"]


def cell_logits_input(x_t: jax.Array, num_cond_channels: int):
    """(x, t): x_t (B, H, W, C+G) with its generated channels set to 0, and t int32 (B,) of
    zeros: what the classifier reads (the conditions alone)."""
    x = x_t.astype(jnp.float32).at[..., num_cond_channels:].set(0.0)
    return x, jnp.zeros(x_t.shape[:1], jnp.int32)


def rescale_cells(logits: jax.Array) -> jax.Array:
    """float32 (B, H, W) logits -> (B, H, W) in [-1, 1]: each map's max at +1, min at -1,
    the order of the cells kept (a constant map is all +1)."""
    lo = logits.min(axis=(1, 2), keepdims=True)
    hi = logits.max(axis=(1, 2), keepdims=True)
    span = jnp.maximum(hi - lo, 1e-12)
    return jnp.where(hi > lo, 2.0 * (logits - lo) / span - 1.0, 1.0)


class GoalClassifier(Denoiser):
    """The Denoiser's network read as a classifier over cells (see the module docstring).

    ``logits(x_t, t, tokens) -> (B, H, W, G)``: the network's raw outputs on the conditions
    alone (channel g > 0: logits over cells of the g-th generated channel's +1 cell; the path
    channel's are unused). Call: ``(x_t, t, tokens) -> plan (B, H, W, G)`` in [-1, 1].
    """

    def logits(self, x_t: jax.Array, t: jax.Array, tokens: jax.Array) -> jax.Array:
        x, t0 = cell_logits_input(x_t, self.config.num_cond_channels)
        return Denoiser.__call__(self, x, t0, tokens)

    def __call__(self, x_t: jax.Array, t: jax.Array, tokens: jax.Array) -> jax.Array:
        out = self.logits(x_t, t, tokens)
        path = -jnp.ones(out.shape[:-1] + (1,), jnp.float32)
        cells = [rescale_cells(out[..., g])[..., None] for g in range(1, out.shape[-1])]
        return jnp.concatenate([path] + cells, axis=-1)


models.register_model(models.class_path(GoalClassifier), GoalClassifier, DenoiserConfig)
