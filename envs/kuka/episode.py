"""Episodes of the Kuka tasks (the columns of :mod:`envs.kuka.config`).

Following Diffuser and Decision Diffuser, a task is a set of "X on Y" relations the arm must
build, and success is the share of instructed relations that hold at the end:

* stacking, multi-constraint: one tower of all four blocks in a fully instructed order, 3
  instructed relations ("Stack the green block on top of the red block. Stack the blue block
  on top of the green block. Stack the yellow block on top of the blue block.");
* stacking, single constraint: one tower of all four blocks, one instructed relation ("Build a
  tower of all four blocks. Stack the green block on top of the red block."); the order of the
  rest is free (the expert draws one), the episode ends when the relation holds and the four
  blocks stand in one tower;
* rearrangement, single constraint: one relation "X on Y", the other blocks stay where they are;
* rearrangement, multi-constraint: two relations, drawn uniformly from the 36 valid pairs (two
  towers of two, or a tower of three), in either instruction order.

Initial layout: the four blocks flat, axis-aligned, centres 0.6 m from the base in uniformly
drawn directions (Diffuser's), redrawn until every pair is separated by at least MIN_GAP in x
or y (their footprints neither overlap nor touch).

An episode is a pytree of arrays (:class:`Episode`) generated in JAX from a key
(:func:`generate`); everything is jit/vmap-able.
"""
from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.kuka import grammar, scene
from envs.kuka.config import COLUMNS, MAX_RELATIONS, NO_BLOCK, TaskSpec

MIN_GAP = 0.03
"""Minimum clearance (m) between two blocks' footprints at reset."""


@struct.dataclass
class Episode:
    """One episode (leading batch axes allowed when vmapped).

    block_xy: float32 (4, 2) the blocks' initial centres (m);
    constraints: int32 (3, 2) the instructed relations (top, bottom) in instruction order,
      rows of -1 padding;
    goal: int32 (3, 2) the relations the scripted expert builds, in build order (bottom up);
      stacking: the whole tower; rearrangement: the instructed relations;
    tower: bool () the episode also needs all four blocks in one tower (stacking);
    max_steps: int32 () placements allowed (TaskSpec.max_steps);
    tokens: int32 (grammar.MAX_TOKENS,) the instruction (for a natural-language one, its
      canonical phrasing's: the natural words are outside the vocabulary);
    phrasing: int32 (1 + MAX_RELATIONS,) the phrasing of each sentence
      (``grammar.draw_phrasings``): the tower sentence's (``grammar.tower_phrasings``), then
      each relation's (``grammar.relation_phrasings``), the natural set's after the grammar's;
      drawn for every sentence, present or not. None in an Episode built by hand.
    features: None, or float32 (L, D) the instruction's pretrained text features
      (``diffplan.instruction``), filled on the host before a rollout of a denoiser that reads
      them (``envs.kuka.sentences.with_features``; ``KukaTask(text="features")`` hands them to
      the planner). Never generated inside jit.

    Everything task-specific is data here, so that one compiled step serves every task.
    """

    block_xy: jax.Array
    constraints: jax.Array
    goal: jax.Array
    tower: jax.Array
    max_steps: jax.Array
    tokens: jax.Array
    phrasing: jax.Array | None = None
    features: jax.Array | None = None

    @property
    def num_constraints(self) -> jax.Array:
        return (self.constraints[..., 0] >= 0).sum(-1)


def _pair_table() -> np.ndarray:
    """int32 (36, 2, 2): every valid set of two relations (distinct tops, distinct bottoms, not
    each on the other), each in build order (the lower relation first)."""
    relations = [(t, b) for t, b in itertools.permutations(range(scene.NUM_BLOCKS), 2)]
    sets = []
    for r1, r2 in itertools.combinations(relations, 2):
        if r1[0] == r2[0] or r1[1] == r2[1] or (r1[0] == r2[1] and r1[1] == r2[0]):
            continue
        # r2 under r1 (r1's bottom is r2's top): build r2 first.
        sets.append((r2, r1) if r1[1] == r2[0] else (r1, r2))
    return np.array(sets, np.int32)


REARRANGEMENT_PAIRS = _pair_table()


def sample_layout(key) -> jax.Array:
    """float32 (4, 2) block centres 0.6 m from the base in uniform directions, redrawn until no
    two footprints come within MIN_GAP of each other (axis-aligned squares)."""
    n = scene.NUM_BLOCKS
    width = 2 * float(scene.BLOCK_HALF_SIZE[0])

    def draw(k):
        angles = jax.random.uniform(k, (n,), minval=-jnp.pi, maxval=jnp.pi)
        return scene.BLOCK_RADIUS * jnp.stack([jnp.cos(angles), jnp.sin(angles)], axis=-1)

    def overlaps(xy):
        sep = jnp.max(jnp.abs(xy[:, None] - xy[None]), axis=-1) + 10.0 * jnp.eye(n)
        return jnp.min(sep) < width + MIN_GAP

    def body(carry):
        k, _ = carry
        k, sub = jax.random.split(k)
        return k, draw(sub)

    k0, k1 = jax.random.split(key)
    _, xy = jax.lax.while_loop(lambda c: overlaps(c[1]), body, (k0, draw(k1)))
    return xy.astype(jnp.float32)


def _pad(rows, total: int = MAX_RELATIONS):
    rows = jnp.asarray(rows, jnp.int32).reshape(-1, 2)
    return jnp.concatenate([rows, jnp.full((total - rows.shape[0], 2), NO_BLOCK, jnp.int32)])


def sample_relations(key, spec: TaskSpec):
    """(constraints int32 (3, 2) instruction order, goal int32 (3, 2) build order) of a task."""
    k_perm, k_pick, k_order = jax.random.split(key, 3)
    if spec.kind == "stacking":
        order = jax.random.permutation(k_perm, scene.NUM_BLOCKS)  # bottom to top
        goal = jnp.stack([order[1:], order[:-1]], axis=-1)  # (3, 2) (top, bottom) bottom up
        if spec.multi:
            return goal, goal
        j = jax.random.randint(k_pick, (), 0, 3)
        return _pad(goal[j]), goal
    if not spec.multi:
        order = jax.random.permutation(k_perm, scene.NUM_BLOCKS)
        pair = _pad(order[:2])
        return pair, pair
    pairs = jnp.asarray(REARRANGEMENT_PAIRS)[jax.random.randint(k_pick, (), 0,
                                                                len(REARRANGEMENT_PAIRS))]
    swap = jax.random.bernoulli(k_order)
    instructed = jnp.where(swap, pairs[::-1], pairs)
    return _pad(instructed), _pad(pairs)


def generate(key, spec: TaskSpec) -> Episode:
    """An episode of the task from a key: the layout from the key's first split (every task
    shares the layouts of a seed), the relations from a split folded with the task's column
    (each column draws its own) and the phrasings from the third (the same tokens in every
    language but "natural", whose tokens are the canonical phrasing's)."""
    k_layout, k_rel, k_lang = jax.random.split(key, 3)
    column = list(COLUMNS).index(dataclasses.replace(spec, language="canonical").name)
    constraints, goal = sample_relations(jax.random.fold_in(k_rel, column), spec)
    tower = spec.kind == "stacking"
    phrasing = grammar.draw_phrasings(k_lang, spec.language)
    tokens = grammar.phrasing_tokens(phrasing, constraints, tower and not spec.multi)
    return Episode(block_xy=sample_layout(k_layout), constraints=constraints, goal=goal,
                   tower=jnp.asarray(tower), max_steps=jnp.asarray(spec.max_steps, jnp.int32),
                   tokens=tokens, phrasing=phrasing)


def episode_keys(seed: int, num: int, start: int = 0) -> jax.Array:
    """Keys of episodes start..start+num-1 of a seed: episode i is fold_in(PRNGKey(seed), i)."""
    root = jax.random.PRNGKey(seed)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.arange(start, start + num))
