"""envs.gridworld.episode and config: generated episodes checked against independent plain-Python
geometry (deque BFS, math.atan2 compass sectors), determinism, and config validation."""
from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_gridworld_bfs import oracle_bfs

from envs.gridworld import episode, grammar
from envs.gridworld.config import SETTINGS, GridConfig, make_config

SEEDS = st.integers(0, 2**32 - 1)


def compass_sector(src, dst) -> int:
    """Sector 0..7 of grammar.DIRECTIONS (counter-clockwise from east; sector s covers angles
    (s*45 - 22.5, s*45 + 22.5] degrees) of dst seen from src, with row 0 north."""
    d_row, d_col = int(dst[0]) - int(src[0]), int(dst[1]) - int(src[1])
    degrees = math.degrees(math.atan2(-d_row, d_col))
    return math.ceil((degrees - 22.5) / 45.0) % 8


def test_compass_sector_oracle():
    assert [compass_sector((5, 5), d) for d in [(5, 9), (1, 9), (1, 5), (1, 1), (5, 1), (9, 1),
                                                (9, 5), (9, 9)]] == list(range(8))
    assert compass_sector((5, 5), (3, 10)) == 0  # 21.8 degrees: east
    assert compass_sector((5, 5), (2, 10)) == 1  # 31.0 degrees: northeast


def chebyshev(a, b) -> int:
    return max(abs(int(a[0]) - int(b[0])), abs(int(a[1]) - int(b[1])))


def check_episode(config: GridConfig, ep, i: int, visible0):
    """All invariants of episode i of a generated batch (numpy arrays)."""
    size = config.size
    grid = ep.grid[i]
    agent, target, reference = (tuple(int(v) for v in a[i]) for a in
                                (ep.agent, ep.target, ep.reference))
    msg = f"{config.setting} episode {i}"
    assert grid.dtype == np.int8 and grid.shape == (size, size)
    assert set(np.unique(grid).tolist()) <= {-1, 0} | set(range(1, config.num_classes + 1)), msg
    for cell in (agent, target):
        assert 0 <= cell[0] < size and 0 <= cell[1] < size, msg
    assert grid[agent] == 0, msg  # the agent starts on an empty cell
    assert agent != target, msg

    objects = grid[grid > 0]
    assert len(np.unique(objects)) == len(objects), f"{msg}: repeated object classes"
    assert config.min_objects <= len(objects) <= config.max_objects, msg
    assert (grid == -1).sum() <= config.max_obstacles, msg
    target_class = int(grid[target])
    assert target_class == int(ep.target_class[i]) >= 1, msg
    if config.setting == "1o1g":
        assert (grid == -1).sum() == 0 and len(objects) == 1, msg

    passable = grid != -1
    to_target = oracle_bfs(passable, target)
    if config.has_reference:
        assert 0 <= reference[0] < size and 0 <= reference[1] < size, msg
        ref_class = int(grid[reference])
        assert ref_class == int(ep.reference_class[i]) >= 1 and ref_class != target_class, msg
        assert chebyshev(reference, target) <= config.ref_target_radius, msg
        assert reference != agent, msg
        # The target is hidden at t=0, the reference visible.
        assert not visible0[i][target] and visible0[i][reference], msg
        direction = compass_sector(reference, target)
        assert int(ep.direction[i]) == direction, msg
        to_ref = oracle_bfs(passable, reference)
        shortest = int(to_ref[agent]) + int(to_target[reference])
        assert to_ref[agent] >= 0 and to_target[reference] >= 0, msg
    else:
        assert reference == (-1, -1) and int(ep.reference_class[i]) == 0, msg
        assert int(ep.direction[i]) == -1, msg
        ref_class, direction = 0, -1
        shortest = int(to_target[agent])
        assert shortest >= 0, msg

    # Instruction: the text of the episode's template filled with what is really on the grid.
    template = int(ep.template[i])
    assert 0 <= template < config.num_templates, msg
    if not config.paraphrase:
        assert template == 0, msg
    text = grammar.decode(ep.tokens[i])
    assert text == grammar.render(config.setting, template, ref_class, target_class, direction), \
        msg

    # Expert path: a shortest obstacle-free 4-connected path agent -> (reference ->) target.
    length = int(ep.expert_length[i])
    assert length == shortest <= config.max_steps, msg
    pos = ep.expert_positions[i]
    assert pos.shape == (config.max_steps + 1, 2)
    path = pos[: length + 1]
    assert tuple(path[0]) == agent and tuple(path[-1]) == target, msg
    assert (pos[length:] == np.array(target)).all(), msg  # padded with the target
    assert (np.abs(np.diff(path, axis=0)).sum(-1) == 1).all(), f"{msg}: not 4-connected"
    assert ((path >= 0) & (path < size)).all(), msg
    assert passable[path[:, 0], path[:, 1]].all(), f"{msg}: path crosses an obstacle"
    if config.has_reference:
        assert (path == np.array(reference)).all(-1).any(), f"{msg}: misses the reference"
    mask = np.zeros((size, size), bool)
    mask[path[:, 0], path[:, 1]] = True
    np.testing.assert_array_equal(ep.expert_path[i], mask, err_msg=msg)


@settings(max_examples=5, deadline=None, database=None)
@given(seed=SEEDS)
@pytest.mark.parametrize("setting", SETTINGS)
def test_generated_episodes_are_valid(gen_batch, grid_configs, setting, seed):
    eps, visible0 = gen_batch(setting, seed)
    config = grid_configs[setting]
    for i in range(len(eps.agent)):
        check_episode(config, eps, i, visible0)


@pytest.mark.parametrize("setting", SETTINGS)
def test_generated_episodes_vary(gen_batch, setting, grid_configs):
    """Across a batch: agents, targets and object counts are not constant; p_mo2g uses several
    directions; mo1g and p_mo2g have obstacles in some episodes."""
    config = grid_configs[setting]
    eps, _ = gen_batch(setting, 0)
    assert len({tuple(a) for a in eps.agent}) > 20
    assert len({tuple(a) for a in eps.target}) > 20
    num_objects = (eps.grid > 0).sum((1, 2))
    if setting == "1o1g":
        assert (num_objects == 1).all()
    else:
        assert len(set(num_objects.tolist())) >= 3
        assert (eps.grid == -1).sum((1, 2)).max() > 0
    if config.has_reference:
        assert len(set(eps.direction.tolist())) >= 5
    assert len(set(eps.target_class.tolist())) >= 8


@pytest.mark.parametrize("setting", SETTINGS)
def test_determinism_per_seed(gen_batch, setting):
    first, v1 = gen_batch.__wrapped__(setting, 11)  # bypass the memo: regenerate
    again, v2 = gen_batch.__wrapped__(setting, 11)
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(v1, v2)
    other, _ = gen_batch(setting, 12)
    differs = (first.grid != other.grid).any((1, 2)) | (first.agent != other.agent).any(1)
    assert differs.mean() > 0.9


@pytest.fixture(scope="module")
def generate_16():
    """jit(generate_batch(key, 1o1g, 16)): a different n from gen_batch's, compiled once."""
    config = make_config("1o1g")
    return jax.jit(lambda key: episode.generate_batch(key, config, 16))


def test_generate_batch_prefix_stable(gen_batch, generate_16):
    """The first 16 of a batch of GRID_BATCH equal a batch of 16, and episode i is
    generate(fold_in(key, i))."""
    full, _ = gen_batch("1o1g", 5)
    prefix = jax.tree.map(np.asarray, generate_16(jax.random.PRNGKey(5)))
    for a, b in zip(jax.tree.leaves(prefix), jax.tree.leaves(full)):
        np.testing.assert_array_equal(a, b[:16])
    assert len(full.agent) > 16


@pytest.mark.parametrize("overrides, message", [
    (dict(setting="mo2g"), "unknown setting"),
    (dict(setting="mo1g", min_objects=2, max_objects=16, view_radius=None), "distinct classes"),
    (dict(setting="mo1g", min_objects=2, max_objects=8, num_classes=5, view_radius=None),
     "distinct classes"),
    (dict(setting="mo1g", size=4, min_objects=2, max_objects=8, max_obstacles=10,
          view_radius=None), "do not fit"),
    (dict(view_radius=-1), "view_radius"),
    (dict(ref_target_radius=-1), "ref_target_radius"),
    (dict(ref_target_radius=7), "ref_target_radius"),
    (dict(view_radius=None), "finite view_radius"),
    (dict(view_radius=8), "whole"),
    (dict(min_objects=1), "min_objects >= 2"),
    (dict(min_objects=6, max_objects=5), "min_objects <= max_objects"),
    (dict(max_obstacles=-1), "max_obstacles"),
    (dict(max_steps=0), "max_steps"),
    (dict(size=3), "size"),
    (dict(num_classes=0), "num_classes"),
    (dict(num_classes=16), "num_classes"),
    (dict(setting="1o1g", min_objects=1, max_objects=2, view_radius=None, max_obstacles=0),
     "exactly one object"),
])
def test_bad_config_raises(overrides, message):
    with pytest.raises(ValueError, match=message):
        GridConfig(**overrides)


def test_make_config():
    for setting in SETTINGS:
        config = make_config(setting)
        assert config.setting == setting and config.size == 16 and config.max_steps == 100
        hash(config)  # usable as a jit static argument
    assert make_config("1o1g").max_obstacles == 0
    assert make_config("p_mo2g").view_radius == 6
    assert make_config("mo1g").view_radius is None
    assert make_config("p_mo2g", paraphrase=True).language == "paraphrased"
    with pytest.raises(ValueError, match="unknown setting"):
        make_config("p_mo3g")
    with pytest.raises(ValueError, match="view_radius"):
        make_config("p_mo2g", view_radius=-2)
