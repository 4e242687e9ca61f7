"""A denoiser that needs no learning: it samples the exact posterior of the episode generator.

Where the instruction's target may lie, given what the agent has seen, follows from how episodes
are generated (``envs.gridworld.episode``): in the instructed compass sector of the reference, at
Chebyshev distance 1 .. ref_target_radius from it (view_radius + 1 .. ref_target_radius in
P-MO2G-far), and unseen so far. :func:`posterior_denoiser` is an "x0 network" that returns a plan
heading for the reference until the agent has stood on it, then for the target if it has been
seen, else for one cell drawn uniformly among those candidates (the argmax of the sampler's noise
over them, so each plan from fresh noise is a fresh draw). Planned with the same planner, psi and
re-planning triggers as a trained denoiser, it is the attribution row of inference: what a
denoiser whose guesses of the hidden target were exact would score (the path channel is left
empty, so it serves the search psi only).

A uniform draw among the candidates is the posterior up to what the generator's rejection of
unreachable layouts and its obstacle draws change; the candidates always hold the target
(tests/test_posterior.py).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffplan.denoiser import LoadedDenoiser
from diffplan.schedule import cosine_schedule
from envs.gridworld.agents import _first_cell, sector_mask
from envs.gridworld.slots import instruction_cells
from envs.gridworld.config import GridConfig
from envs.gridworld.episode import chebyshev
from envs.gridworld.task import NUM_COND_CHANNELS, NUM_GEN_CHANNELS, SUBGOAL_CHANNEL

__all__ = ["target_candidates", "posterior_plan", "posterior_denoiser"]

SCHEDULE_STEPS = 100
"""Training timesteps of the schedule it is sampled with (any plan step count up to this)."""


def target_candidates(config: GridConfig, cells, seen, tokens):
    """bool (H, W): where the instruction's target may lie. cells int32 (H, W) the condition's
    cell tokens, seen bool (H, W), tokens int32 (L,) the instruction. The target's cell once it
    has been seen; else the unseen cells the generator could have put it in (see the module
    docstring), or every unseen cell in a setting without a reference."""
    reference, target, direction = instruction_cells(cells, tokens)
    target = target & seen
    unseen = ~seen
    if config.has_reference:
        reference = reference & seen
        ref_cell = _first_cell(reference)
        rows, cols = jnp.meshgrid(jnp.arange(config.size), jnp.arange(config.size),
                                  indexing="ij")
        d_ref = chebyshev(jnp.stack([rows, cols], -1), ref_cell)
        nearest = config.view_radius + 1 if config.target_beyond_reference_view else 1
        allowed = (sector_mask(ref_cell, direction, config.size)
                   & (d_ref >= nearest) & (d_ref <= config.ref_target_radius)
                   & jnp.any(reference))
        guess = jnp.where(jnp.any(unseen & allowed), unseen & allowed, unseen)
    else:
        guess = unseen
    return jnp.where(jnp.any(target), target, guess)


def posterior_plan(config: GridConfig, x_t, tokens):
    """float32 (H, W, 3): the plan of one episode from the sampler's input x_t (H, W, C + 3)
    (the condition channels in-painted, noise in the others): path empty (-1), goal the target
    or a drawn candidate, sub-goal the reference until visited, then the same as the goal."""
    cells = jnp.round(x_t[..., 0]).astype(jnp.int32)
    visited, seen = x_t[..., 3] > 0.5, x_t[..., 4] > 0.5
    candidates = target_candidates(config, cells, seen, tokens)
    noise = x_t[..., SUBGOAL_CHANNEL]
    pick = jnp.argmax(jnp.where(candidates, noise, -jnp.inf).ravel())
    goal = (jnp.arange(cells.size) == pick).reshape(cells.shape)
    if config.has_reference:
        reference = instruction_cells(cells, tokens)[0] & seen
        subgoal = jnp.where(jnp.any(reference & visited), goal, reference)
    else:
        subgoal = goal
    signed = lambda m: m.astype(jnp.float32) * 2 - 1  # noqa: E731
    return jnp.stack([-jnp.ones(cells.shape, jnp.float32), signed(goal), signed(subgoal)], -1)


def posterior_denoiser(config: GridConfig) -> LoadedDenoiser:
    """A LoadedDenoiser (x0 prediction, no parameters) planning ``config``'s world with
    :func:`posterior_plan`."""

    def apply_fn(params, x_t, t, tokens):
        del params, t
        return jax.vmap(lambda x, tok: posterior_plan(config, x, tok))(x_t, tokens)

    return LoadedDenoiser(params=None, schedule=cosine_schedule(SCHEDULE_STEPS),
                          apply_fn=apply_fn, prediction="x0",
                          plan_shape=(config.size, config.size, NUM_GEN_CHANNELS),
                          num_cond_channels=NUM_COND_CHANNELS)
