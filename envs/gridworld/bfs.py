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


def _shift(values, axis, offset, fill):
    """values shifted by one cell along axis: ``out[i] = values[i + offset]`` (offset -1 or 1),
    ``fill`` where i + offset is off the grid. Same shape as values."""
    n = values.shape[axis]
    edge = jnp.full_like(jax.lax.slice_in_dim(values, 0, 1, axis=axis), fill)
    if offset < 0:
        return jnp.concatenate([edge, jax.lax.slice_in_dim(values, 0, n - 1, axis=axis)], axis)
    return jnp.concatenate([jax.lax.slice_in_dim(values, 1, n, axis=axis), edge], axis)


def _neighbour_min(values, fill, axes=(-2, -1)):
    """min over the four neighbours of each cell of values, whose grid axes (rows, cols) are
    ``axes`` (default: the last two, (..., H, W)); ``fill`` off the grid.

    Written as shifted concatenations and an elementwise minimum chain so that XLA fuses it
    into one loop (a pad + stack version was about 2x slower on CPU)."""
    rows, cols = axes
    return jnp.minimum(
        jnp.minimum(_shift(values, rows, -1, fill), _shift(values, rows, 1, fill)),
        jnp.minimum(_shift(values, cols, -1, fill), _shift(values, cols, 1, fill)))


UNIT_INF = 10_000
"""Unreachable marker of unit-cost int16 fields; larger than any path on a grid of <= 100x100
(small grids use uint8 fields, see :func:`_unit_dtype`)."""


def _unit_dtype(h, w):
    """(dtype, unreachable marker) of a unit-cost field on an (h, w) grid.

    A shortest path visiting every cell would need every cell passable (an impassable source is
    never reached), and then it has at most h + w - 2 moves; any other has at most h * w - 2.
    uint8 (marker 255) holds both bounds on grids up to 16 x 16; larger grids use int16."""
    if max(h * w - 2, h + w - 2) < 255:
        return jnp.uint8, 255
    return jnp.int16, UNIT_INF


def _unit_field_batch_last(passable, source):
    """BFS distances towards each grid's source, grids stacked on the LAST axis.

    Args:
      passable: bool (H, W, B); source: int32 (2, B) (row, col).
    Returns:
      float32 (H, W, B): moves from each cell to its grid's source (0 at the source even if
      impassable), INF where unreachable; equal to the enter_cost=None field of cost_to_go.

    The batch is the minor axis so that XLA vectorises each relaxation over the grids (a
    batch-first layout, which plain vmap produces, runs along 16-wide rows and is several times
    slower). One relaxation: ``field = min(field, max(min over neighbours n of (field[n] + 1,
    or inf if n is impassable), wall))`` with wall 0 on passable cells and inf elsewhere; the
    source starts at 0 and a minimum never raises it. All grids relax until none changes.
    """
    h, w = passable.shape[:2]
    dtype, inf = _unit_dtype(h, w)
    rows = jnp.arange(h)[:, None, None]
    cols = jnp.arange(w)[None, :, None]
    is_source = (rows == source[0]) & (cols == source[1])
    start = jnp.where(is_source, 0, inf).astype(dtype)
    wall = jnp.where(passable, 0, inf).astype(dtype)

    def body(carry):
        field, _, it = carry
        via = jnp.minimum(jnp.maximum(field, wall), inf - 1) + 1  # inf through impassable cells
        new = jnp.minimum(field, jnp.maximum(_neighbour_min(via, inf, axes=(0, 1)), wall))
        return new, jnp.any(new != field), it + 1

    field, _, _ = jax.lax.while_loop(lambda c: c[1] & (c[2] < h * w), body,
                                     (start, jnp.array(True), jnp.array(0)))
    return jnp.where(field >= inf, INF, field).astype(jnp.float32)


def cost_to_go(passable, source, enter_cost=None):
    """Cost-to-go field towards ``source`` over passable cells.

    Args:
      passable: bool (H, W); impassable cells are never entered.
      source: int32 (2,) (row, col); its cost is 0 even if impassable.
      enter_cost: float32 (H, W) positive cost of entering each cell; None = 1 per move (BFS,
        computed in uint8/int16 with the grids of a vmapped batch on the minor axis, returned
        as float32).
    Returns:
      float32 (H, W): ``field[c] = min over neighbours n of enter_cost[n] + field[n]`` (the
      cheapest cost from c to the source); INF where the source is unreachable.
    """
    if enter_cost is None:
        return _unit_field(passable, jnp.asarray(source, jnp.int32))
    return _cost_field(passable, jnp.asarray(source, jnp.int32),
                       jnp.asarray(enter_cost, jnp.float32))


def _cost_field_batch_last(passable, source, enter_cost):
    """Dijkstra-style cost-to-go towards each grid's source, grids stacked on the LAST axis
    (as :func:`_unit_field_batch_last`, for which see the layout's rationale).

    Args: passable bool (H, W, B); source int32 (2, B); enter_cost float32 (H, W, B).
    Returns float32 (H, W, B), INF where unreachable; equal to cost_to_go with enter_cost.
    """
    h, w = passable.shape[:2]
    rows = jnp.arange(h)[:, None, None]
    cols = jnp.arange(w)[None, :, None]
    is_source = (rows == source[0]) & (cols == source[1])
    start = jnp.where(is_source, 0.0, INF).astype(jnp.float32)
    # Cost of entering a cell (inf if impassable); a path's cost sums those of the cells entered.
    via_cost = jnp.where(passable, enter_cost, INF).astype(jnp.float32)

    def body(carry):
        field, _, it = carry
        through = _neighbour_min(jnp.minimum(via_cost + field, INF), INF, axes=(0, 1))
        new = jnp.where(is_source, 0.0, jnp.minimum(field, jnp.where(passable, through, INF)))
        return new, jnp.any(new != field), it + 1

    field, _, _ = jax.lax.while_loop(lambda c: c[1] & (c[2] < h * w), body,
                                     (start, jnp.array(True), jnp.array(0)))
    return jnp.where(field >= INF, INF, field).astype(jnp.float32)


def _batched_args(axis_size, in_batched, args):
    """args with a leading batch axis of axis_size each (broadcast where not batched)."""
    return [x if batched else jnp.broadcast_to(x, (axis_size,) + x.shape)
            for x, batched in zip(args, in_batched)]


def _one_grid(batch_last_fn):
    """The one-grid function of a batch-last one (every argument and the result carry the
    grids on their last axis). Under vmap the grids are moved to the last axis and computed
    together, so XLA vectorises across grids (a custom_vmap rule; nested vmaps nest)."""

    @jax.custom_batching.custom_vmap
    def one(*args):
        return batch_last_fn(*(x[..., None] for x in args))[..., 0]

    @one.def_vmap
    def rule(axis_size, in_batched, *args):
        args = _batched_args(axis_size, in_batched, args)
        out = batch_last_fn(*(jnp.moveaxis(x, 0, -1) for x in args))
        return jnp.moveaxis(out, -1, 0), True

    return one


_unit_field = _one_grid(_unit_field_batch_last)
"""Unit-cost cost_to_go of one grid: (bool (H, W), int32 (2,)) -> float32 (H, W)."""
_cost_field = _one_grid(_cost_field_batch_last)
"""cost_to_go of one grid with enter_cost: (bool (H, W), int32 (2,), float32 (H, W))."""


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


def _best_neighbour(value, pos):
    """The move (0..3) from pos into the neighbour n of least value[n] (float32 (H, W), 2 * INF
    where n may not be entered); off-grid neighbours count as 2 * INF; ties go to the lowest
    move index. Returns int32 ()."""
    h, w = value.shape
    cells, inside = neighbours(pos, (h, w))
    clipped = jnp.clip(cells, 0, jnp.array([h - 1, w - 1]))
    return jnp.argmin(jnp.where(inside, value[clipped[:, 0], clipped[:, 1]], 2 * INF)).astype(
        jnp.int32)


def best_move(field, passable, pos, enter_cost=None):
    """The move (0..3) from pos into the passable neighbour n minimising enter_cost[n] + field[n].

    Ties go to the lowest move index (N, E, S, W). Always returns a move; if no neighbour is
    passable it returns 0 (the move will collide). Returns int32 ().
    """
    value = field if enter_cost is None else field + enter_cost
    return _best_neighbour(jnp.where(passable, value, 2 * INF), pos)


def descend(field, passable, start, num_steps):
    """Follows a unit-cost field downhill from start for num_steps moves (staying at the source).

    Returns int32 (num_steps + 1, 2) positions, the first being start.
    """
    value = jnp.where(passable, field, 2 * INF)  # best_move's values, masked once for all steps

    def step(pos, _):
        at_source = field[pos[0], pos[1]] <= 0
        nxt = pos + MOVES[_best_neighbour(value, pos)]
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
