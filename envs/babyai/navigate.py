"""Shortest routes on a map and the BabyAI action that follows one: the search behind both
psi (over the agent's map, to the plan's goal estimate) and the expert (over the true grid, to
the instructed objects).

A map here is what is passable and at what cost: ``enter`` float32 (H, W) the actions it takes
to move into each cell from a neighbour facing it (1 for a free cell, 2 for a closed door: a
toggle, then forward; ``inf`` for a cell that cannot be entered). Turns are not in the field;
:func:`act` adds them when it picks the next cell.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

from envs.babyai import objects as O

INF = jnp.inf
TURN_COST = 1.0
"""Actions per quarter turn (:func:`act` weighs the next cell's turns with it)."""


def neighbours(field, fill):
    """(4, H, W): field shifted so that [d, r, c] is field at (r, c) + DIR_DELTA[d] (fill off
    the map)."""
    h, w = field.shape
    padded = jnp.pad(field, 1, constant_values=fill)
    return jnp.stack([padded[1 + dr:1 + dr + h, 1 + dc:1 + dc + w]
                      for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0))])


def adjacent(mask):
    """bool (H, W): cells with a 4-neighbour in mask (bool (H, W))."""
    return jnp.any(neighbours(mask, False), axis=0)


@custom_vmap
def cost_to_go(enter, start):
    """float32 (H, W): the least cost from each cell to a goal, moving between 4-neighbours and
    paying ``enter`` of each cell entered; start float32 (H, W) the cost of ending at each cell
    (``inf`` where it is no goal). Bellman-Ford relaxation until nothing changes (at most H * W
    rounds). A cell's own enter cost does not count for leaving it (the agent's cell).

    Under ``vmap`` (psi over a batch of episodes) the relaxation runs on the batch laid out
    last, (H, W, B) (:func:`_cost_to_go_batched`): the same values, bit for bit, about three
    times faster on the CPU than vmap's (B, H, W) layout, whose 22-wide rows vectorise poorly
    (docs/DESIGN.md, the BabyAI paragraph)."""
    return _relax(enter[..., None], start[..., None])[..., 0]


@cost_to_go.def_vmap
def _cost_to_go_batched(axis_size, in_batched, enter, start):
    """cost_to_go's batching rule: the batch moved to the last axis, relaxed, moved back."""
    enter, start = (x if batched else jnp.broadcast_to(x, (axis_size,) + x.shape)
                    for x, batched in zip((enter, start), in_batched))
    field = _relax(jnp.moveaxis(enter, 0, -1), jnp.moveaxis(start, 0, -1))
    return jnp.moveaxis(field, -1, 0), True


def _neighbour_min(field):
    """(H, W, B): the least of each cell's 4-neighbours in field (H, W, B) (inf off the map)."""
    h, w, b = field.shape
    col = jnp.full((h, 1, b), INF, field.dtype)
    row = jnp.full((1, w, b), INF, field.dtype)
    east = jnp.concatenate([field[:, 1:], col], 1)
    west = jnp.concatenate([col, field[:, :-1]], 1)
    south = jnp.concatenate([field[1:], row], 0)
    north = jnp.concatenate([row, field[:-1]], 0)
    return jnp.minimum(jnp.minimum(east, south), jnp.minimum(west, north))


def _relax(enter, start):
    """cost_to_go of B maps laid out (H, W, B): Jacobi relaxation until no cell of any map
    changes (a converged map stays as it is), at most H * W rounds."""
    h, w = enter.shape[:2]

    def cond(carry):
        i, field, changed = carry
        return changed & (i < h * w)

    def body(carry):
        i, field, _ = carry
        new = jnp.minimum(field, jnp.minimum(start, _neighbour_min(enter + field)))
        return i + 1, new, jnp.any(new < field)

    _, field, _ = jax.lax.while_loop(cond, body, (0, start, jnp.array(True)))
    return field


def _turn_towards(direction, wanted):
    """The turn action towards heading ``wanted``: right for a quarter turn clockwise, else
    left (a half turn goes left)."""
    return jnp.where(wanted == (direction + 1) % 4, O.RIGHT, O.LEFT).astype(jnp.int32)


def act(field, enter, goal, stand, closed_door, pos, direction):
    """The next BabyAI action along the field (int32 ()).

    field float32 (H, W) from :func:`cost_to_go` to the stand cells; enter float32 (H, W);
    goal bool (H, W) the cells to face at the end; stand bool (H, W) the cells to end on;
    closed_door bool (H, W) cells to toggle before entering; pos int32 (2,), direction int32 ().
    On a stand cell: face a goal cell beside it (done when facing one: the world then checks
    the mission). Elsewhere: the neighbour with the least enter + field + turns; face it, then
    toggle it if it is a closed door, else forward. With no finite neighbour: turn left (look
    around)."""
    h, w = field.shape
    cells = pos[None, :] + O.DIR_DELTA                     # (4, 2)
    inside = (cells[:, 0] >= 0) & (cells[:, 0] < h) & (cells[:, 1] >= 0) & (cells[:, 1] < w)
    r = jnp.clip(cells[:, 0], 0, h - 1)
    c = jnp.clip(cells[:, 1], 0, w - 1)
    turns = jnp.array([0.0, 1.0, 2.0, 1.0])[(jnp.arange(4) - direction) % 4]
    # at a stand cell: face the goal (ahead first, then a quarter turn, then behind)
    faces_goal = inside & goal[r, c]
    face = jnp.argmin(jnp.where(faces_goal, turns, INF))
    at_goal = jnp.where(face == direction, O.DONE, _turn_towards(direction, face))
    # elsewhere: the next cell of the route
    q = jnp.where(inside, enter[r, c] + field[r, c] + TURN_COST * turns, INF)
    best = jnp.argmin(q)
    ahead = jnp.where(closed_door[r[best], c[best]], O.TOGGLE, O.FORWARD)
    move = jnp.where(best == direction, ahead, _turn_towards(direction, best))
    move = jnp.where(jnp.isfinite(q[best]), move, O.LEFT)
    on_stand = stand[pos[0], pos[1]] & jnp.any(faces_goal)
    return jnp.where(on_stand, at_goal, move).astype(jnp.int32)


def route(field, enter, start, pos, max_len: int):
    """(cells bool (H, W), end int32 (2,)): the route from pos down the field (the least
    enter + field neighbour each time, ties to the lowest direction index) to a cell where the
    field is its own start cost (``start`` as given to :func:`cost_to_go`), pos included, and
    the cell it ends on; at most max_len cells (static)."""
    h, w = field.shape
    through = neighbours(enter + field, INF)               # (4, H, W)

    def body(_, carry):
        cell, mask = carry
        mask = mask.at[cell[0], cell[1]].set(True)
        options = through[:, cell[0], cell[1]]
        d = jnp.argmin(options)
        moves_on = field[cell[0], cell[1]] < start[cell[0], cell[1]]  # else it ends here
        nxt = jnp.where(moves_on, cell + O.DIR_DELTA[d], cell)
        return nxt.astype(jnp.int32), mask

    end, mask = jax.lax.fori_loop(0, max_len, body,
                                  (pos.astype(jnp.int32), jnp.zeros((h, w), bool)))
    return mask, end
