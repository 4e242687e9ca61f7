"""Success checkers on physical block poses: the strict one of contract 4 and Diffuser's.

Strict (docs/DESIGN.md, contract 4): "X on Y" holds when their centres' xy distance is under half a
block width (0.1 m), X's bottom rests on Y's top within a quarter of a block's height
(|(z_X - h) - (z_Y + h)| < h / 2 with h the half height 0.03 m, so 0.015 m), and neither is
held. Bottom and top are those of the block's nominal flat pose about its centre, so a block
leaning on another at an angle (its centre higher than a flat block's would be) is not on it.

Diffuser's looser check: xy distance under 0.2 m, X's centre higher than Y's by more than
0.05 m, neither held.

All functions but :func:`per_phrasing_metrics` (plain Python over a batch of episodes) are pure
jnp (jit/vmap-able) and accept numpy arrays too; shapes are for one episode: pos float (4, 3)
block centres, held bool (4,).
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from envs.kuka.scene import BLOCK_HALF_SIZE

HALF_WIDTH = float(BLOCK_HALF_SIZE[0])
HALF_HEIGHT = float(BLOCK_HALF_SIZE[2])
XY_TOLERANCE = HALF_WIDTH
"""Strict: centres closer than half a block width in xy."""
Z_TOLERANCE = HALF_HEIGHT / 2
"""Strict: X's bottom within a quarter of a block's height of Y's top."""
DIFFUSER_XY = 0.2
DIFFUSER_DZ = 0.05


def _pairs(pos, held):
    pos = jnp.asarray(pos)
    held = jnp.asarray(held, bool)
    xy = jnp.linalg.norm(pos[:, None, :2] - pos[None, :, :2], axis=-1)
    dz = pos[:, None, 2] - pos[None, :, 2]  # [i, j] = z_i - z_j
    free = ~held[:, None] & ~held[None, :] & ~jnp.eye(pos.shape[0], dtype=bool)
    return xy, dz, free


def on_matrix(pos, held) -> jnp.ndarray:
    """bool (4, 4): [i, j] = block i is on block j (strict)."""
    xy, dz, free = _pairs(pos, held)
    gap = dz - 2 * HALF_HEIGHT  # bottom of i minus top of j
    return free & (xy < XY_TOLERANCE) & (jnp.abs(gap) < Z_TOLERANCE)


def diffuser_on_matrix(pos, held) -> jnp.ndarray:
    """bool (4, 4): [i, j] = block i is on block j by Diffuser's check."""
    xy, dz, free = _pairs(pos, held)
    return free & (xy < DIFFUSER_XY) & (dz > DIFFUSER_DZ)


def satisfied(on, constraints) -> jnp.ndarray:
    """bool (K,): constraint k (int (K, 2) rows (top, bottom), -1 padding) holds in on (4, 4);
    padding rows are False."""
    constraints = jnp.asarray(constraints)
    valid = constraints[:, 0] >= 0
    c = jnp.maximum(constraints, 0)
    return valid & on[c[:, 0], c[:, 1]]


def on_floor(pos, held) -> jnp.ndarray:
    """bool (4,): the block rests on the floor (its bottom within a quarter height of z = 0)."""
    pos = jnp.asarray(pos)
    return ~jnp.asarray(held, bool) & (jnp.abs(pos[:, 2] - HALF_HEIGHT) < Z_TOLERANCE)


def single_tower(pos, held) -> jnp.ndarray:
    """bool (): the four blocks form one tower: one block on the floor, every other block on a
    block (strict), no block carrying two."""
    on = on_matrix(pos, held)
    return ((on_floor(pos, held).sum() == 1) & (on.any(1).sum() == pos.shape[0] - 1)
            & (on.sum(0) <= 1).all())


def per_phrasing_metrics(tokens, constraints, strict) -> list[dict]:
    """Strict SR over the instructed constraints whose sentence is in each relation phrasing,
    so that one phrasing the planner misreads shows instead of being averaged away.

    Args (numpy, a batch of N episodes): tokens int (N, L) the instructions; constraints int
    (N, 3, 2) (top, bottom) in instruction order, -1 rows absent; strict bool (N, 3) each
    constraint holds. Returns [{"template": int (envs.kuka.grammar.RELATION_TEMPLATES), "phrasing":
    str, "constraints": int, "SR": float}] by template index.
    """
    from envs.kuka import grammar

    counts: dict[int, tuple[int, int]] = {}
    sentences = grammar.sentence_templates_batch(tokens)
    for found, rows, ok in zip(sentences, np.asarray(constraints), np.asarray(strict)):
        relations = [k for kind, k in filter(None, found) if kind == "relation"]
        present = [j for j in range(len(rows)) if rows[j, 0] >= 0]
        if len(relations) != len(present):
            raise ValueError(f"an instruction has {len(relations)} relation sentences for "
                             f"{len(present)} constraints")
        for k, j in zip(relations, present):
            hits, n = counts.get(int(k), (0, 0))
            counts[int(k)] = (hits + int(ok[j]), n + 1)
    return [{"template": k, "phrasing": grammar.RELATION_TEMPLATES[k], "constraints": n,
             "SR": 100.0 * hits / n} for k, (hits, n) in sorted(counts.items())]
