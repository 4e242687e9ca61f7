"""Language controls: the same episodes with one word of the instruction changed, so that a
planner that reads the word must act differently and one that ignores it cannot.

- ``names``: the reference's name (in a setting with no reference, MO1G, the goal's)
  replaced by that of a distractor the agent sees at t = 0 (an object that is neither the
  target nor the reference; drawn uniformly among them with the control's key). The world is
  unchanged; only the tokens name another object. Measured by :func:`named_first`: the agent
  stands on the named distractor before it stands on the true reference (MO1G: the true
  target). A planner that reads the name does so in nearly every episode; one that ignores it
  (heading for the true object, or for any object) rarely does.
- ``direction``: the direction word reversed (sector d -> d + 4), everything else unchanged:
  where the direction is the only clue to a hidden target (P-MO2G-far), a planner that reads
  it searches the wrong side first and its SPL drops.

Every function is pure over one episode (vmap for a batch); the metric is plain numpy over
executed trajectories. The control changes the instruction only, never what the world
records (``Episode.target``, ``reference``) or how success is measured.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs.gridworld import grammar
from envs.gridworld.episode import Episode

CONTROLS = ("names", "direction")
CONTROL_STREAM = 0xC0A7
"""Folded into an episode's key to draw the control's choices (never the planner's key)."""


def visible_distractors(episode: Episode, visible0):
    """bool (H, W): cells holding an object that is neither the target nor the reference,
    seen at t = 0 (visible0 bool (H, W))."""
    grid = episode.grid
    objects = grid > 0
    other = (grid != episode.target_class) & (grid != episode.reference_class)
    return objects & other & visible0


def name_a_distractor(key, episode: Episode, visible0, setting: str):
    """(episode with the reference (no reference: the goal) named as a visible distractor, the
    distractor's cell int32 (2,), valid bool ()): valid is False (and the episode unchanged)
    where no distractor is visible at t = 0."""
    cells = visible_distractors(episode, visible0)
    size = cells.shape[1]
    scores = jnp.where(cells.ravel(), jax.random.uniform(key, (cells.size,)), -1.0)
    flat = jnp.argmax(scores)
    cell = jnp.stack([flat // size, flat % size]).astype(jnp.int32)
    valid = cells.any()
    named = episode.grid[cell[0], cell[1]].astype(jnp.int32)
    has_reference = episode.reference_class > 0
    tokens = grammar.fill_template(
        jnp.asarray(grammar.compile_templates(setting))[grammar.token_template(
            episode.template)], jnp.where(has_reference, named, episode.reference_class),
        jnp.where(has_reference, episode.target_class, named),
        jnp.maximum(episode.direction, 0)).astype(episode.tokens.dtype)
    tokens = jnp.where(valid, tokens, episode.tokens)
    return episode.replace(tokens=tokens), cell, valid


def reverse_direction(episode: Episode, setting: str) -> Episode:
    """The episode with its instruction's direction word reversed (sector d -> (d + 4) % 8);
    unchanged where the setting has no direction."""
    direction = jnp.maximum(episode.direction, 0)
    tokens = grammar.fill_template(
        jnp.asarray(grammar.compile_templates(setting))[grammar.token_template(
            episode.template)], episode.reference_class, episode.target_class,
        (direction + 4) % 8)
    tokens = jnp.where(episode.direction >= 0, tokens.astype(episode.tokens.dtype),
                       episode.tokens)
    return episode.replace(tokens=tokens)


def first_visit(positions: np.ndarray, steps: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """int (N,): the first move index t (0 = the start) at which episode i stands on cells[i]
    within its steps[i] moves (positions int (N, T + 1, 2)); T + 1 where it never does."""
    positions, cells = np.asarray(positions), np.asarray(cells)
    on = np.all(positions == cells[:, None, :], axis=-1)
    on &= np.arange(positions.shape[1])[None, :] <= np.asarray(steps)[:, None]
    return np.where(on.any(1), on.argmax(1), positions.shape[1])


def named_first(positions, steps, named, reference) -> np.ndarray:
    """bool (N,): the agent stood on the named cell before it stood on the true reference
    (or stood on the named cell and never on the reference); for the goal's name (MO1G) pass
    the true target as ``reference``."""
    t_named = first_visit(positions, steps, named)
    t_reference = first_visit(positions, steps, reference)
    return (t_named < np.asarray(positions).shape[1]) & (t_named < t_reference)
