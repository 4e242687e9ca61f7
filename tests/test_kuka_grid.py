"""The planner's top-down view against a plain-numpy oracle, and the grid geometry."""
from __future__ import annotations

import jax
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from envs.kuka import grid, scene


def _oracle_view(pos, yaw, held):
    """Plain numpy: for every cell, the blocks whose footprint (a square turned by yaw, corners
    computed explicitly) contains the cell centre, by a same-side test on its four edges."""
    size, cell, half = grid.GRID_SIZE, grid.CELL, scene.BLOCK_HALF_SIZE[:2]
    top = np.full((size, size), -1)
    height = np.zeros((size, size), int)
    corners = []
    for (x, y, _), a in zip(pos, yaw):
        c, s = np.cos(a), np.sin(a)
        local = np.array([[-half[0], -half[1]], [half[0], -half[1]], [half[0], half[1]],
                          [-half[0], half[1]]])
        corners.append(local @ np.array([[c, s], [-s, c]]) + [x, y])
    for row in range(size):
        for col in range(size):
            px, py = -0.8 + (col + 0.5) * cell, 0.8 - (row + 0.5) * cell
            best = None
            for b, poly in enumerate(corners):
                if held[b]:
                    continue
                inside = True
                for k in range(4):
                    (x0, y0), (x1, y1) = poly[k], poly[(k + 1) % 4]
                    if (x1 - x0) * (py - y0) - (y1 - y0) * (px - x0) < -1e-9:
                        inside = False
                if inside:
                    height[row, col] += 1
                    if best is None or pos[b][2] > pos[best][2]:
                        best = b
            if best is not None:
                top[row, col] = best
    return top, height


def test_view_matches_numpy_oracle():
    rng = np.random.default_rng(0)
    view = jax.jit(grid.top_down_view)
    for _ in range(20):
        pos = np.zeros((4, 3), np.float32)
        pos[:, :2] = rng.uniform(-0.6, 0.6, (4, 2))
        # Some blocks stacked on others (same xy, higher).
        for b in range(1, 4):
            if rng.random() < 0.5:
                pos[b, :2] = pos[rng.integers(0, b), :2] + rng.uniform(-0.03, 0.03, 2)
        pos[:, 2] = 0.03 + 0.06 * rng.permutation(4)
        yaw = rng.uniform(-np.pi, np.pi, 4)
        quat = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], 1).astype(
            np.float32)
        held = rng.random(4) < 0.15
        top, height = view(pos, quat, held)
        o_top, o_height = _oracle_view(pos, yaw, held)
        np.testing.assert_array_equal(np.asarray(height), o_height)
        np.testing.assert_array_equal(np.asarray(top), o_top)


def test_a_flat_block_covers_three_by_three_cells():
    pos = np.array([[0.6, 0.0, 0.03], [-0.6, 0.0, 0.03], [0.0, 0.6, 0.03], [0.0, -0.6, 0.03]],
                   np.float32)
    pos[:, :2] += grid.CELL / 2  # centred in a cell
    quat = np.tile([1.0, 0, 0, 0], (4, 1)).astype(np.float32)
    top, height = grid.top_down_view(pos, quat)
    for b in range(4):
        assert int((np.asarray(top) == b).sum()) == 9
        r, c = np.asarray(grid.block_cells(pos))[b]
        assert int(top[r, c]) == b
    assert int(np.asarray(height).max()) == 1


def test_cells_and_centres_round_trip():
    cells = np.stack(np.meshgrid(np.arange(24), np.arange(24), indexing="ij"), -1).reshape(-1, 2)
    centres = np.asarray(jax.vmap(grid.cell_center)(cells))
    np.testing.assert_allclose(centres, grid.cell_centers().reshape(-1, 2), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(grid.xy_to_cell(centres)), cells)
    assert tuple(np.asarray(grid.xy_to_cell(np.array([5.0, -5.0])))) == (23, 23)


def test_arc_goes_around_the_base_the_short_way():
    rng = np.random.default_rng(1)
    for _ in range(50):
        a0, a1 = rng.uniform(-np.pi, np.pi, 2)
        start = 0.6 * np.array([np.cos(a0), np.sin(a0)])
        end = 0.55 * np.array([np.cos(a1), np.sin(a1)])
        pts = np.asarray(grid.arc_points(start, end, 64))
        np.testing.assert_allclose(pts[0], start, atol=1e-5)
        np.testing.assert_allclose(pts[-1], end, atol=1e-5)
        assert np.linalg.norm(pts, axis=1).min() >= 0.55 - 1e-5
        turn = np.abs(np.diff(np.unwrap(np.arctan2(pts[:, 1], pts[:, 0])))).sum()
        assert turn <= np.pi + 1e-4
        path = np.asarray(grid.path_map(start, end))
        cells = np.asarray(grid.xy_to_cell(pts))
        assert path[tuple(cells[0])] and path[tuple(cells[-1])]
        # Consecutive samples land in the same or a neighbouring cell: the path is connected.
        assert np.abs(np.diff(cells, axis=0)).max() <= 1
        assert path.sum() == len({tuple(c) for c in cells})


@settings(max_examples=50, deadline=None)
@given(row=st.integers(0, grid.GRID_SIZE - 1), col=st.integers(0, grid.GRID_SIZE - 1))
def test_flat_cell_index_round_trip(row, col):
    """cell_of inverts cell_index (row-major), against plain Python."""
    index = int(grid.cell_index(np.array([row, col])))
    assert index == row * grid.GRID_SIZE + col
    assert tuple(np.asarray(grid.cell_of(index))) == (row, col)
    assert np.asarray(grid.cell_of(np.array([index, 0]))).shape == (2, 2)
