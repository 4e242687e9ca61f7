"""Shortest paths on a 4-connected grid in jax.numpy: one relaxation serves BFS and Dijkstra.

A "field" is the cost-to-go to a source cell: ``field[c]`` is the cheapest total cost of the
cells entered on a 4-connected path from c to the source (the source itself costs 0). With unit
costs it is the BFS distance in moves. It is computed by iterated Bellman-Ford relaxation under
``lax.while_loop`` (until nothing changes), which vmaps over a batch of grids.

Moves are indexed 0..3 = north, east, south, west; row 0 is north.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

MOVES = jnp.array([[-1, 0], [0, 1], [1, 0], [0, -1]], jnp.int32)
"""(4, 2) row/col deltas of the actions north, east, south, west."""
INF = 1e9
"""Cost-to-go of cells that cannot reach the source."""


def _neighbour_min(values, fill):
    """min over the four neighbours of each cell of values (..., H, W); ``fill`` off the grid.

    Written as shifted concatenations and an elementwise minimum chain so that XLA fuses it
    into one loop (a pad + stack version was about 2x slower on CPU)."""
    row = jnp.full_like(values[..., :1, :], fill)
    col = jnp.full_like(values[..., :1], fill)
    north = jnp.concatenate([row, values[..., :-1, :]], axis=-2)
    south = jnp.concatenate([values[..., 1:, :], row], axis=-2)
    west = jnp.concatenate([col, values[..., :-1]], axis=-1)
    east = jnp.concatenate([values[..., 1:], col], axis=-1)
    return jnp.minimum(jnp.minimum(north, south), jnp.minimum(west, east))


UNIT_INF = 10_000
"""Unreachable marker of unit-cost (int16) fields; larger than any path on a grid of <= 100x100."""


def cost_to_go(passable, source, enter_cost=None):
    """Cost-to-go field towards ``source`` over passable cells.

    Args:
      passable: bool (H, W); impassable cells are never entered.
      source: int32 (2,) (row, col); its cost is 0 even if impassable.
      enter_cost: float32 (H, W) positive cost of entering each cell; None = 1 per move (BFS,
        computed in int16, returned as float32).
    Returns:
      float32 (H, W): ``field[c] = min over neighbours n of enter_cost[n] + field[n]`` (the
      cheapest cost from c to the source); INF where the source is unreachable.
    """
    h, w = passable.shape
    unit = enter_cost is None
    dtype, inf = (jnp.int16, UNIT_INF) if unit else (jnp.float32, INF)
    rows = jnp.arange(h)[:, None]
    cols = jnp.arange(w)[None, :]
    is_source = (rows == source[0]) & (cols == source[1])
    start = jnp.where(is_source, 0, inf).astype(dtype)
    # Cost of entering a cell (inf if impassable); a path's cost sums those of the cells entered.
    via_cost = jnp.where(passable, 1 if unit else enter_cost, inf).astype(dtype)

    def body(carry):
        field, _, it = carry
        through = _neighbour_min(jnp.minimum(via_cost + field, inf), inf)
        new = jnp.where(is_source, 0, jnp.minimum(field, jnp.where(passable, through, inf)))
        new = new.astype(dtype)
        return new, jnp.any(new != field), it + 1

    field, _, _ = jax.lax.while_loop(lambda c: c[1] & (c[2] < h * w), body,
                                     (start, jnp.array(True), jnp.array(0)))
    return jnp.where(field >= inf, INF, field).astype(jnp.float32)


def bfs_distance(passable, source):
    """BFS distance in moves (int32 (H, W)) towards ``source``; -1 where unreachable."""
    field = cost_to_go(passable, source)
    return jnp.where(field >= INF, -1, field).astype(jnp.int32)


def neighbours(pos, shape):
    """(4, 2) neighbour cells of pos (N, E, S, W) and bool (4,) whether each is on a grid of
    the given (H, W) shape."""
    cells = pos[None, :] + MOVES
    inside = jnp.all((cells >= 0) & (cells < jnp.array(shape[:2])), axis=-1)
    return cells, inside


def best_move(field, passable, pos, enter_cost=None):
    """The move (0..3) from pos into the passable neighbour n minimising enter_cost[n] + field[n].

    Ties go to the lowest move index (N, E, S, W). Always returns a move; if no neighbour is
    passable it returns 0 (the move will collide). Returns int32 ().
    """
    h, w = field.shape
    cells, inside = neighbours(pos, (h, w))
    clipped = jnp.clip(cells, 0, jnp.array([h - 1, w - 1]))
    value = field[clipped[:, 0], clipped[:, 1]]
    if enter_cost is not None:
        value = value + enter_cost[clipped[:, 0], clipped[:, 1]]
    ok = inside & passable[clipped[:, 0], clipped[:, 1]]
    return jnp.argmin(jnp.where(ok, value, 2 * INF)).astype(jnp.int32)


def descend(field, passable, start, num_steps):
    """Follows a unit-cost field downhill from start for num_steps moves (staying at the source).

    Returns int32 (num_steps + 1, 2) positions, the first being start.
    """

    def step(pos, _):
        at_source = field[pos[0], pos[1]] <= 0
        nxt = pos + MOVES[best_move(field, passable, pos)]
        nxt = jnp.where(at_source, pos, nxt)
        return nxt, nxt

    _, positions = jax.lax.scan(step, start, None, length=num_steps)
    return jnp.concatenate([start[None], positions], axis=0)


def positions_to_mask(positions, size, valid=None):
    """bool (size, size) mask of the cells in positions (P, 2); rows where valid is False ignored."""
    valid = jnp.ones(positions.shape[0], bool) if valid is None else valid
    mask = jnp.zeros((size, size), jnp.int32)
    mask = mask.at[positions[:, 0], positions[:, 1]].add(valid.astype(jnp.int32))
    return mask > 0
