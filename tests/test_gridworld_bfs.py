"""envs.gridworld.bfs against plain-Python oracles (collections.deque BFS, heapq Dijkstra)."""
from __future__ import annotations

import collections
import heapq

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envs.gridworld import bfs

MOVES = ((-1, 0), (0, 1), (1, 0), (0, -1))  # N, E, S, W; row 0 is north
BATCH = 32
DESCEND_STEPS = 80


def oracle_bfs(passable: np.ndarray, source) -> np.ndarray:
    """Moves from each cell to source over passable cells (4-connected); -1 if unreachable.
    Impassable cells are -1, except the source (0)."""
    h, w = passable.shape
    dist = np.full((h, w), -1, np.int64)
    dist[source] = 0
    if not passable[source]:
        return dist  # the source cannot be entered, so nothing reaches it
    queue = collections.deque([tuple(source)])
    while queue:
        r, c = queue.popleft()
        for dr, dc in MOVES:
            nr, nc = r + dr, c + dc
            if 0 <= nr < h and 0 <= nc < w and passable[nr, nc] and dist[nr, nc] < 0:
                dist[nr, nc] = dist[r, c] + 1
                queue.append((nr, nc))
    return dist


def oracle_dijkstra(passable: np.ndarray, source, enter_cost: np.ndarray) -> np.ndarray:
    """Cheapest sum of enter_cost over the cells entered on a path from each cell to source
    (float64); inf where unreachable or impassable (except the source, 0)."""
    h, w = passable.shape
    dist = np.full((h, w), np.inf)
    dist[source] = 0.0
    heap = [(0.0, tuple(source))]
    while heap:
        d, (r, c) = heapq.heappop(heap)
        if d > dist[r, c] or not passable[r, c]:
            continue
        # A path from a neighbour n through (r, c) pays the cost of entering (r, c).
        nd = d + enter_cost[r, c]
        for dr, dc in MOVES:
            nr, nc = r + dr, c + dc
            if 0 <= nr < h and 0 <= nc < w and passable[nr, nc] and nd < dist[nr, nc]:
                dist[nr, nc] = nd
                heapq.heappush(heap, (nd, (nr, nc)))
    return dist


def random_problems(seed: int, shape=(16, 16), batch=BATCH, passable_source=True):
    """Random grids: per grid an obstacle density in [0, 0.55], a source cell, entry costs."""
    rng = np.random.default_rng(seed)
    density = rng.uniform(0.0, 0.55, size=(batch, 1, 1))
    passable = rng.uniform(size=(batch,) + shape) >= density
    sources = np.stack([rng.integers(0, shape[0], batch), rng.integers(0, shape[1], batch)], -1)
    if passable_source:
        passable[np.arange(batch), sources[:, 0], sources[:, 1]] = True
    enter_cost = rng.uniform(0.1, 5.0, size=(batch,) + shape).astype(np.float32)
    return passable, sources.astype(np.int32), enter_cost


@pytest.fixture(scope="session")
def fields():
    """Jitted vmapped (bfs_distance, unit cost_to_go, float cost_to_go) -> numpy; compiled once
    per grid shape."""

    @jax.jit
    def run(passable, sources, enter_cost):
        dist = jax.vmap(bfs.bfs_distance)(passable, sources)
        unit = jax.vmap(bfs.cost_to_go)(passable, sources)
        weighted = jax.vmap(bfs.cost_to_go)(passable, sources, enter_cost)
        return dist, unit, weighted

    return lambda *args: tuple(np.asarray(a) for a in run(*args))


@pytest.fixture(scope="session")
def descend_fn():
    """Jitted vmapped: unit field towards source, then bfs.descend from start."""

    @jax.jit
    def run(passable, sources, starts):
        def one(p, s, start):
            field = bfs.cost_to_go(p, s)
            return field, bfs.descend(field, p, start, DESCEND_STEPS)

        return jax.vmap(one)(passable, sources, starts)

    return lambda *args: tuple(np.asarray(a) for a in run(*args))


def check_against_oracles(fields, passable, sources, enter_cost):
    dist, unit, weighted = fields(passable, sources, enter_cost)
    assert dist.dtype == np.int32 and unit.dtype == np.float32 and weighted.dtype == np.float32
    for i in range(len(passable)):
        src = tuple(sources[i])
        expected = oracle_bfs(passable[i], src)
        np.testing.assert_array_equal(dist[i], expected, err_msg=f"grid {i}")
        np.testing.assert_array_equal(unit[i], np.where(expected < 0, bfs.INF, expected))
        expected_w = oracle_dijkstra(passable[i], src, enter_cost[i])
        finite = np.isfinite(expected_w)
        np.testing.assert_array_equal(weighted[i] >= bfs.INF, ~finite, err_msg=f"grid {i}")
        np.testing.assert_allclose(weighted[i][finite], expected_w[finite], rtol=1e-5, atol=1e-4)


@settings(max_examples=8, deadline=None, database=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_bfs_and_dijkstra_match_oracles(fields, seed):
    check_against_oracles(fields, *random_problems(seed))


def test_open_grid_distance_is_manhattan(fields):
    passable = np.ones((BATCH, 16, 16), bool)
    rng = np.random.default_rng(0)
    sources = rng.integers(0, 16, (BATCH, 2)).astype(np.int32)
    dist, unit, weighted = fields(passable, sources, np.ones((BATCH, 16, 16), np.float32))
    rows, cols = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    for i, (r, c) in enumerate(sources):
        manhattan = np.abs(rows - r) + np.abs(cols - c)
        np.testing.assert_array_equal(dist[i], manhattan)
        np.testing.assert_allclose(weighted[i], manhattan)


def test_walled_off_region_is_unreachable(fields):
    passable = np.ones((BATCH, 16, 16), bool)
    passable[:, :, 8] = False  # a full wall down column 8
    sources = np.tile(np.array([[3, 2]], np.int32), (BATCH, 1))
    dist, unit, weighted = fields(passable, sources, np.ones((BATCH, 16, 16), np.float32))
    assert (dist[:, :, 9:] == -1).all() and (unit[:, :, 9:] == bfs.INF).all()
    assert (weighted[:, :, 9:] >= bfs.INF).all()
    assert (dist[:, :, 8] == -1).all()  # impassable cells are never reached
    assert (dist[:, :, :8] >= 0).all()


def test_impassable_source_costs_zero(fields):
    passable, sources, enter_cost = random_problems(1, passable_source=False)
    passable[np.arange(BATCH), sources[:, 0], sources[:, 1]] = False
    dist, unit, weighted = fields(passable, sources, enter_cost)
    idx = np.arange(BATCH)
    assert (dist[idx, sources[:, 0], sources[:, 1]] == 0).all()
    assert (weighted[idx, sources[:, 0], sources[:, 1]] == 0).all()
    # The implementation never enters an impassable cell, the source included.
    for i in range(BATCH):
        np.testing.assert_array_equal(dist[i], oracle_bfs(passable[i], tuple(sources[i])))


def test_non_square_grid(fields):
    check_against_oracles(fields, *random_problems(7, shape=(7, 12), batch=8))


def test_descend_follows_a_shortest_path(descend_fn):
    passable, sources, _ = random_problems(3)
    rng = np.random.default_rng(3)
    starts = np.zeros_like(sources)
    for i in range(BATCH):  # a start that can reach the source
        reach = np.argwhere(oracle_bfs(passable[i], tuple(sources[i])) >= 0)
        starts[i] = reach[rng.integers(len(reach))]
    field, positions = descend_fn(passable, sources, starts)
    assert positions.shape == (BATCH, DESCEND_STEPS + 1, 2)
    for i in range(BATCH):
        d = int(field[i][tuple(starts[i])])
        assert d <= DESCEND_STEPS
        pos = positions[i]
        np.testing.assert_array_equal(pos[0], starts[i])
        np.testing.assert_array_equal(pos[d], sources[i])
        assert (pos[d:] == sources[i]).all()  # stays at the source
        steps = np.abs(np.diff(pos[: d + 1], axis=0)).sum(-1)
        assert (steps == 1).all()  # 4-connected unit moves
        assert passable[i][pos[: d + 1, 0], pos[: d + 1, 1]].all()
        np.testing.assert_array_equal(field[i][pos[: d + 1, 0], pos[: d + 1, 1]],
                                      np.arange(d, -1, -1))


def test_best_move_breaks_ties_north_first():
    passable = jnp.ones((5, 5), bool)
    field = bfs.cost_to_go(passable, jnp.array([0, 4]))
    # From (2, 2) both north and east lead closer to (0, 4): north (0) wins the tie.
    assert int(bfs.best_move(field, passable, jnp.array([2, 2]))) == 0
    # With north blocked, east.
    blocked = passable.at[1, 2].set(False)
    field = bfs.cost_to_go(blocked, jnp.array([0, 4]))
    assert int(bfs.best_move(field, blocked, jnp.array([2, 2]))) == 1


def test_best_move_on_non_square_grid():
    passable = jnp.ones((4, 8), bool)
    field = bfs.cost_to_go(passable, jnp.array([0, 7]))
    # From (0, 5) the only improving move is east to (0, 6).
    assert int(bfs.best_move(field, passable, jnp.array([0, 5]))) == 1


def test_positions_to_mask():
    positions = jnp.array([[0, 0], [0, 1], [0, 1], [3, 2]])
    mask = np.asarray(bfs.positions_to_mask(positions, 4, jnp.array([True, True, True, False])))
    expected = np.zeros((4, 4), bool)
    expected[0, 0] = expected[0, 1] = True
    np.testing.assert_array_equal(mask, expected)
