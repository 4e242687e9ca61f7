"""The agent's egocentric view, as minigrid computes it (``gen_obs_grid`` / ``process_vis``
with ``see_through_walls=False``, BabyAI's setting), in jax.numpy.

Coordinates: a grid is indexed [row, col] = minigrid's (y, x); row 0 is the top. Directions
0..3 = east, south, west, north (minigrid's ``DIR_TO_VEC``). The view is the 7 x 7 square ahead
of the agent; view cell (vx, vy) (minigrid's image index: ``image[vx, vy]``) lies
``VIEW - 1 - vy`` cells ahead of the agent and ``vx - VIEW // 2`` cells to its right, so the
agent is at (3, 6) looking towards vy = 0. Cells off the grid are seen as walls.

Occlusion: a cell is visible if a run of see-through cells (not a wall, not a closed or locked
door) connects it to the agent, propagated row by row away from the agent: within a row to the
left and to the right, and from each see-through visible cell to the row beyond (straight and
diagonally outwards).
"""
from __future__ import annotations

import jax.numpy as jnp

from envs.babyai import objects as O

VIEW = 7
"""The side of the egocentric view (minigrid's ``agent_view_size``, 7 in BabyAI)."""
AGENT_VX, AGENT_VY = VIEW // 2, VIEW - 1


def view_cells(pos, direction):
    """int32 (VIEW, VIEW, 2): the world cell (row, col) of each view cell (vx, vy) of an agent
    at pos int32 (2,) facing direction int32 ()."""
    ahead = O.DIR_DELTA[direction]                       # (2,) (d_row, d_col)
    right = jnp.stack([ahead[1], -ahead[0]])             # the agent's right, (row, col)
    vx = jnp.arange(VIEW)[:, None, None]
    vy = jnp.arange(VIEW)[None, :, None]
    return (pos[None, None, :] + ahead[None, None, :] * (VIEW - 1 - vy)
            + right[None, None, :] * (vx - AGENT_VX)).astype(jnp.int32)


def view_contents(grid, cells):
    """uint8 (VIEW, VIEW, 3): the encoding of each view cell (grid uint8 (H, W, 3), cells from
    :func:`view_cells`); off the grid, a wall."""
    h, w = grid.shape[:2]
    inside = (cells[..., 0] >= 0) & (cells[..., 0] < h) & (cells[..., 1] >= 0) & (cells[..., 1] < w)
    r = jnp.clip(cells[..., 0], 0, h - 1)
    c = jnp.clip(cells[..., 1], 0, w - 1)
    return jnp.where(inside[..., None], grid[r, c], jnp.asarray(O.WALL_CELL, jnp.uint8))


def _sweep_row(seen, clear):
    """One row of minigrid's sweep (``Grid.process_vis``): seen bool (VIEW,) the row's cells
    reached so far, clear bool (VIEW,) see-through -> (the row's visible cells, the cells of
    the next row reached from it). The pass to the right spreads from a visible see-through
    cell to its right neighbour (a run of see-through cells: no opaque cell from the source up
    to, not including, the target), then the pass to the left likewise; each cell a pass
    spreads from (the pass to the right never from the last cell, the one to the left never
    from the first) also reaches the cell beyond it in the next row and the one diagonally
    in the pass's direction."""
    idx = jnp.arange(VIEW)
    blocked = jnp.concatenate([jnp.zeros(1, jnp.int32), jnp.cumsum(~clear)])  # (VIEW + 1,)
    # to the right: cell i from source k <= i when cells k .. i-1 are all clear
    k, i = idx[:, None], idx[None, :]
    rightward = (k <= i) & (blocked[i] == blocked[k])
    after_right = jnp.any(seen[:, None] & rightward, axis=0)
    # to the left: cell i from source k >= i when cells i+1 .. k are all clear
    leftward = (k >= i) & (blocked[k + 1] == blocked[i + 1])
    visible = jnp.any(after_right[:, None] & leftward, axis=0)
    from_right = after_right & clear & (idx < VIEW - 1)   # sources of the pass to the right
    from_left = visible & clear & (idx > 0)               # sources of the pass to the left
    shift_right = jnp.concatenate([jnp.zeros(1, bool), from_right[:-1]])
    shift_left = jnp.concatenate([from_left[1:], jnp.zeros(1, bool)])
    return visible, from_right | shift_right | from_left | shift_left


def visibility(contents):
    """bool (VIEW, VIEW) [vx, vy]: which view cells the agent sees (contents uint8 (VIEW,
    VIEW, 3)): minigrid's sweep, row by row from the agent's (vy = VIEW - 1) outwards
    (:func:`_sweep_row`)."""
    clear = ~O.opaque(contents)                                   # [vx, vy]
    reached = jnp.zeros(VIEW, bool).at[AGENT_VX].set(True)
    rows = []
    for vy in range(VIEW - 1, -1, -1):
        visible, reached = _sweep_row(reached, clear[:, vy])
        rows.append(visible)
    return jnp.stack(rows[::-1], axis=1)


def observe(grid, pos, direction, carrying):
    """minigrid's observation image and what it covers.

    Returns (image uint8 (VIEW, VIEW, 3) indexed [vx, vy]: visible cells encoded, others 0
    ("unseen"), the agent's own cell showing what it carries (or empty); visible bool (VIEW,
    VIEW); cells int32 (VIEW, VIEW, 2) the world cell of each view cell)."""
    cells = view_cells(pos, direction)
    contents = view_contents(grid, cells)
    visible = visibility(contents)
    contents = contents.at[AGENT_VX, AGENT_VY].set(carrying.astype(jnp.uint8))
    image = jnp.where(visible[..., None], contents, jnp.uint8(O.UNSEEN))
    return image, visible, cells


def remember(known, image, visible, cells):
    """The agent's map after an observation: known uint8 (H, W, 3) (0 where never seen) with
    every visible view cell on the grid overwritten by what the image shows, except the agent's
    own cell (the image shows what it carries there, not the floor)."""
    h, w = known.shape[:2]
    inside = (cells[..., 0] >= 0) & (cells[..., 0] < h) & (cells[..., 1] >= 0) & (cells[..., 1] < w)
    write = visible & inside
    write = write.at[AGENT_VX, AGENT_VY].set(False)
    rows = jnp.where(write, cells[..., 0], h).ravel()    # h: out of range, dropped
    cols = jnp.where(write, cells[..., 1], w).ravel()
    return known.at[rows, cols].set(image.reshape(-1, 3), mode="drop")

