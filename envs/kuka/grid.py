"""The planner's top-down view of the workspace: a 24 x 24 grid (the paper release's size).

The grid covers the square [-0.8, 0.8]^2 m around the arm's base (blocks start 0.6 m from it, so
every block lies inside): cell (row, col) has its centre at x = -0.8 + (col + 0.5) * CELL,
y = 0.8 - (row + 0.5) * CELL, CELL = 1/15 m; row 0 is north (+y), col 0 west (-x). A block
(0.2 m wide) covers 3 x 3 cells. A cell is covered by a block when the cell's centre, at the
block's height, lies inside the block's footprint in the block's own frame.

Everything here is a pure jnp function of block poses (jit/vmap-able); shapes in docstrings are
for one episode.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs.kuka import physics, scene

GRID_SIZE = 24
HALF_EXTENT = 0.8
CELL = 2 * HALF_EXTENT / GRID_SIZE
NO_BLOCK = -1


def cell_centers() -> np.ndarray:
    """float32 (24, 24, 2) the xy (m) of every cell's centre."""
    idx = np.arange(GRID_SIZE)
    x = -HALF_EXTENT + (idx + 0.5) * CELL
    y = HALF_EXTENT - (idx + 0.5) * CELL
    return np.stack(np.meshgrid(x, y, indexing="xy"), axis=-1).astype(np.float32)


def cell_center(cell) -> jax.Array:
    """float32 (2,) xy (m) of cell int (2,) = (row, col)."""
    cell = jnp.asarray(cell)
    return jnp.stack([-HALF_EXTENT + (cell[1] + 0.5) * CELL,
                      HALF_EXTENT - (cell[0] + 0.5) * CELL]).astype(jnp.float32)


def cell_index(cell) -> jax.Array:
    """int32 (): the flat index of a cell int (2,) (row-major over the GRID_SIZE x GRID_SIZE
    grid)."""
    return (cell[0] * GRID_SIZE + cell[1]).astype(jnp.int32)


def cell_of(index) -> jax.Array:
    """int32 (..., 2): the cells of flat indices int (...) (:func:`cell_index`'s inverse)."""
    index = jnp.asarray(index, jnp.int32)
    return jnp.stack([index // GRID_SIZE, index % GRID_SIZE], -1)


def xy_to_cell(xy) -> jax.Array:
    """int32 (..., 2) (row, col) of the cell containing xy float (..., 2), clipped to the grid."""
    xy = jnp.asarray(xy)
    col = jnp.floor((xy[..., 0] + HALF_EXTENT) / CELL)
    row = jnp.floor((HALF_EXTENT - xy[..., 1]) / CELL)
    return jnp.clip(jnp.stack([row, col], axis=-1), 0, GRID_SIZE - 1).astype(jnp.int32)


def footprints(block_pos, block_quat) -> jax.Array:
    """bool (4, 24, 24): cell centres inside each block's footprint (block pos float (4, 3),
    quat (4, 4) (w, x, y, z))."""
    rot = physics.quat_to_mat(jnp.asarray(block_quat))  # (4, 3, 3)
    centers = jnp.asarray(cell_centers())  # (24, 24, 2)
    pos = jnp.asarray(block_pos)
    delta = jnp.concatenate([
        centers[None] - pos[:, None, None, :2],
        jnp.zeros((pos.shape[0], GRID_SIZE, GRID_SIZE, 1), centers.dtype)], axis=-1)
    local = jnp.einsum("bji,bhwj->bhwi", rot, delta)  # R^T (c - p)
    half = jnp.asarray(scene.BLOCK_HALF_SIZE)
    return (jnp.abs(local[..., 0]) <= half[0]) & (jnp.abs(local[..., 1]) <= half[1])


def top_down_view(block_pos, block_quat, held=None):
    """The planner's view: (top int32 (24, 24), height int32 (24, 24)).

    top: the index (0 red, 1 green, 2 blue, 3 yellow) of the highest block covering the cell,
    NO_BLOCK (-1) where none does; height: how many blocks cover the cell (the stack height).
    Held blocks (bool (4,)) are not part of the view.
    """
    cover = footprints(block_pos, block_quat)
    if held is not None:
        cover = cover & ~jnp.asarray(held)[:, None, None]
    z = jnp.where(cover, jnp.asarray(block_pos)[:, 2, None, None], -jnp.inf)
    top = jnp.where(cover.any(0), jnp.argmax(z, axis=0), NO_BLOCK).astype(jnp.int32)
    return top, cover.sum(0).astype(jnp.int32)


def view_of(data):
    """top_down_view of an mjx.Data."""
    return top_down_view(physics.block_pos(data), physics.block_quat(data), physics.held(data))


def block_cells(block_pos) -> jax.Array:
    """int32 (4, 2) the cell of each block's centre."""
    return xy_to_cell(jnp.asarray(block_pos)[:, :2])


def arc_points(start_xy, end_xy, num: int) -> jax.Array:
    """float32 (num, 2) points from start_xy to end_xy around the base: the angle about the
    origin interpolated the short way, the radius linearly (blocks start on the 0.6 m circle, so
    the expert carries them along it, never over the base). Ends included."""
    start_xy, end_xy = jnp.asarray(start_xy), jnp.asarray(end_xy)
    a0 = jnp.arctan2(start_xy[1], start_xy[0])
    a1 = jnp.arctan2(end_xy[1], end_xy[0])
    delta = jnp.mod(a1 - a0 + jnp.pi, 2 * jnp.pi) - jnp.pi
    r0, r1 = jnp.linalg.norm(start_xy), jnp.linalg.norm(end_xy)
    s = jnp.linspace(0.0, 1.0, num)
    angle = a0 + s * delta
    radius = r0 + s * (r1 - r0)
    return jnp.stack([radius * jnp.cos(angle), radius * jnp.sin(angle)], axis=-1)


def rasterize(points_xy) -> jax.Array:
    """bool (24, 24): the cells containing any of points_xy float (P, 2)."""
    cells = xy_to_cell(points_xy)
    return jnp.zeros((GRID_SIZE, GRID_SIZE), bool).at[cells[:, 0], cells[:, 1]].set(True)


PATH_SAMPLES = 64
"""Points sampled along a carry path when it is drawn on the grid (spacing < half a cell)."""


def path_map(start_xy, end_xy) -> jax.Array:
    """bool (24, 24): the cells the end effector passes over carrying a block from start_xy to
    end_xy along :func:`arc_points` (both ends' cells included)."""
    return rasterize(arc_points(start_xy, end_xy, PATH_SAMPLES))
