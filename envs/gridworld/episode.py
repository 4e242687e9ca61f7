"""Episode generation: a pure function of a PRNG key, vmap-able over keys.

An :class:`Episode` holds everything fixed for an episode: the grid, the start, the goal, the
instruction (as token ids) and the expert path (a shortest obstacle-free 4-connected path from the
agent through the reference, if any, to the target). Every generated episode is solvable within
``max_steps`` moves: layouts whose expert path would not exist (or, with
``GridConfig.all_objects_reachable``, that wall off any object) are re-drawn.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from diffplan import language
from envs.gridworld import bfs, grammar
from envs.gridworld.config import GridConfig

EMPTY_CELL, OBSTACLE_CELL = 0, -1
_MAX_LAYOUT_TRIES = 16


@struct.dataclass
class Episode:
    """One episode's fixed content (leading batch axes allowed when vmapped).

    grid: int8 (H, W): 0 empty, -1 obstacle, k >= 1 object class k (grammar.OBJECT_NAMES[k-1]).
    agent, target, reference: int32 (2,) (row, col); reference is (-1, -1) without one.
    target_class, reference_class: int32 () 1-based classes (reference_class 0 without one).
    direction: int32 () compass sector 0..7 from reference to target (grammar.DIRECTIONS), -1 none.
    template: int32 () index of the instruction template (grammar.all_phrasings: 0-11 the
      grammar's phrasings, from grammar.NUM_TEMPLATES on the natural-language set's).
    tokens: int32 (L,) the instruction's token ids (0 padded); for a natural-language
      template, the canonical phrasing's (its words are outside the vocabulary).
    expert_positions: int32 (max_steps + 1, 2) the expert path, padded by repeating the target.
    expert_length: int32 () number of moves of the expert path.
    expert_path: bool (H, W) the cells of the expert path, ends included.
    features: None, or float32 (L, D) the instruction's pretrained text features
      (``diffplan.instruction``), filled on the host before a rollout of a denoiser that
      reads them (``envs.gridworld.sentences.with_features``; ``GridTask(text="features")``
      hands them to the planner). Never generated inside jit.
    """

    grid: jax.Array
    agent: jax.Array
    target: jax.Array
    reference: jax.Array
    target_class: jax.Array
    reference_class: jax.Array
    direction: jax.Array
    template: jax.Array
    tokens: jax.Array
    expert_positions: jax.Array
    expert_length: jax.Array
    expert_path: jax.Array
    features: jax.Array | None = None


def chebyshev(a, b):
    """Chebyshev distance between cells (..., 2) -> int32 (...)."""
    return jnp.max(jnp.abs(a - b), axis=-1)


def compass_sector(src, dst):
    """Compass sector 0..7 (grammar.DIRECTIONS) of dst seen from src; north = row 0. int32 ()."""
    d_row = (dst[0] - src[0]).astype(jnp.float32)
    d_col = (dst[1] - src[1]).astype(jnp.float32)
    angle = jnp.arctan2(-d_row, d_col)  # counter-clockwise from east, north up
    return (jnp.round(angle / (jnp.pi / 4)).astype(jnp.int32) % 8).astype(jnp.int32)


def _cell_coords(size):
    rows, cols = jnp.meshgrid(jnp.arange(size), jnp.arange(size), indexing="ij")
    return jnp.stack([rows, cols], axis=-1).astype(jnp.int32)  # (H, W, 2)


def _threefry2x32(k1, k2, x1, x2):
    """The Threefry-2x32 hash (20 rounds) of counters (x1, x2) under the key (k1, k2), all
    uint32 (broadcastable) -> (uint32, uint32): jax's threefry2x32 (jax._src.prng), unrolled."""
    rotations = ((13, 15, 26, 6), (17, 29, 16, 24))
    ks = (k1, k2, k1 ^ k2 ^ np.uint32(0x1BD11BDA))
    x1, x2 = x1 + ks[0], x2 + ks[1]
    for block in range(5):
        for r in rotations[block % 2]:
            x1 = x1 + x2
            x2 = x1 ^ ((x2 << np.uint32(r)) | (x2 >> np.uint32(32 - r)))
        x1 = x1 + ks[(block + 1) % 3]
        x2 = x2 + ks[(block + 2) % 3] + np.uint32(block + 1)
    return x1, x2


def _uniform(key, shape):
    """float32 uniform in [0, 1) of a static shape: bit for bit ``jax.random.uniform(key, shape)``.

    On CPU jax lowers the threefry hash as a rolled 5-step loop that XLA does not fuse; unrolled
    (:func:`_threefry2x32`), the whole draw is one fused elementwise loop, about 10x faster
    under vmap. This reproduces jax's partitionable threefry bits (jax_threefry_partitionable,
    the default since jax 0.5: counter = flat index, bits = hash words XORed) and its
    bits-to-float map; other key implementations or settings fall back to jax.random.uniform.
    tests/test_gridworld_speed_identity.py checks the equality.
    """
    typed = jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key)
    impl = str(jax.random.key_impl(key)) if typed else jax.config.jax_default_prng_impl
    if impl != "threefry2x32" or not jax.config.jax_threefry_partitionable:
        return jax.random.uniform(key, shape)
    data = jax.random.key_data(key) if typed else key
    counter = jnp.arange(np.prod(shape, dtype=int), dtype=jnp.uint32).reshape(shape)
    hi, lo = _threefry2x32(data[0], data[1], jnp.zeros_like(counter), counter)
    mantissa = ((hi ^ lo) >> np.uint32(9)) | np.uint32(0x3F800000)  # a float in [1, 2)
    return jnp.maximum(0.0, jax.lax.bitcast_convert_type(mantissa, jnp.float32) - 1.0)


def _first_argmax(values):
    """Index (int32 ()) of the first maximum of values (N,) without NaNs: jnp.argmax, written as
    a max and a min reduction, which XLA vectorises on CPU (its argmax reduction is scalar)."""
    index = jnp.arange(values.shape[0], dtype=jnp.int32)
    return jnp.min(jnp.where(values == jnp.max(values), index, values.shape[0]))


def _choose_cell(key, allowed):
    """A uniformly random cell among allowed (bool (H, W)) -> int32 (2,)."""
    size = allowed.shape[1]
    scores = _uniform(key, allowed.shape)
    flat = _first_argmax(jnp.where(allowed, scores, -1.0).ravel())
    return jnp.stack([flat // size, flat % size]).astype(jnp.int32)


def _random_subset(key, allowed, count, max_count):
    """bool (H, W): `count` (traced, <= max_count static) random cells among allowed."""
    scores = jnp.where(allowed, _uniform(key, allowed.shape), -1.0).ravel()
    _, idx = jax.lax.top_k(scores, max_count)
    take = (jnp.arange(max_count) < count) & (scores[idx] >= 0)
    return jnp.zeros(scores.shape, jnp.int32).at[idx].add(take.astype(jnp.int32)).reshape(
        allowed.shape) > 0


def _place_goal_cells(key, config: GridConfig, agent):
    """Target and reference cells (reference (-1,-1) when the setting has none)."""
    coords = _cell_coords(config.size)
    k_target, k_ref = jax.random.split(key)
    d_agent = chebyshev(coords, agent)
    if config.target_beyond_reference_view:
        return _place_far_goal_cells(k_target, k_ref, config, coords, d_agent)
    if config.has_reference:
        vr, rtr = config.view_radius, config.ref_target_radius
        # Unseen at t=0, yet close enough to some cell the agent sees for a reference to exist.
        target = _choose_cell(k_target, (d_agent > vr) & (d_agent <= vr + rtr))
        ref_ok = (d_agent <= vr) & (chebyshev(coords, target) <= rtr) & (d_agent > 0)
        reference = _choose_cell(k_ref, ref_ok)
    else:
        target = _choose_cell(k_target, d_agent > 0)
        reference = jnp.array([-1, -1], jnp.int32)
    return target, reference


def _place_far_goal_cells(k_target, k_ref, config: GridConfig, coords, d_agent):
    """p_mo2g_far's (target, reference), int32 (2,) each: the reference uniform among the cells
    the agent sees at t=0 (Chebyshev 1..view_radius from it), then the target uniform among the
    cells view_radius + 1 .. ref_target_radius from the reference (never in its view) that the
    agent does not see at t=0 either. The instruction's direction is the target's compass
    sector from the reference (compass_sector). GridConfig's check guarantees a target cell."""
    vr = config.view_radius
    reference = _choose_cell(k_ref, (d_agent > 0) & (d_agent <= vr))
    d_ref = chebyshev(coords, reference)
    target = _choose_cell(k_target,
                          (d_ref > vr) & (d_ref <= config.ref_target_radius) & (d_agent > vr))
    return target, reference


def _objects_grid(key, config: GridConfig, agent, target, reference):
    """int8 (H, W) grid with the objects placed (no obstacles yet), and the goal classes."""
    size = config.size
    k_classes, k_count, k_cells = jax.random.split(key, 3)
    classes = jax.random.permutation(k_classes, config.num_classes)[: config.max_objects] + 1
    num_objects = jax.random.randint(k_count, (), config.min_objects, config.max_objects + 1)
    grid = jnp.zeros((size, size), jnp.int32).at[target[0], target[1]].set(classes[0])
    taken = jnp.zeros((size, size), bool).at[agent[0], agent[1]].set(True)
    taken = taken.at[target[0], target[1]].set(True)
    num_fixed = 1
    if config.has_reference:
        grid = grid.at[reference[0], reference[1]].set(classes[1])
        taken = taken.at[reference[0], reference[1]].set(True)
        num_fixed = 2
    num_distractors = config.max_objects - num_fixed
    if num_distractors > 0:
        cells = _random_subset(k_cells, ~taken, num_objects - num_fixed, num_distractors)
        # Distractor j (in raster order) gets classes[num_fixed + j].
        order = jnp.cumsum(cells.ravel()).reshape(cells.shape) - 1
        distractor_class = classes[num_fixed:][jnp.clip(order, 0, num_distractors - 1)]
        grid = jnp.where(cells, distractor_class, grid)
    reference_class = classes[1] if config.has_reference else jnp.int32(0)
    return grid, classes[0], reference_class


def _goal_fields(config: GridConfig, passable, target, reference):
    """Unit cost-to-go fields (float32 (H, W)) towards the target and, if the setting has one,
    the reference (else None) over passable cells (bool (H, W))."""
    to_target = bfs.cost_to_go(passable, target)
    to_ref = bfs.cost_to_go(passable, reference) if config.has_reference else None
    return to_target, to_ref


def _expert_length(config: GridConfig, fields, agent, reference):
    """Moves of the expert path given _goal_fields: float32 () (>= INF if none exists)."""
    to_target, to_ref = fields
    if config.has_reference:
        return to_ref[agent[0], agent[1]] + to_target[reference[0], reference[1]]
    return to_target[agent[0], agent[1]]


def _solvable(config: GridConfig, fields, length, objects):
    """bool (): the expert path (length from _expert_length) fits in max_steps and, with
    config.all_objects_reachable, every object cell (objects bool (H, W)) is reachable: it
    lies in the target's component (to_target finite), which the agent's is when the expert
    path exists (moves are reversible)."""
    ok = length <= config.max_steps
    if config.all_objects_reachable:
        ok &= ~jnp.any(objects & (fields[0] >= bfs.INF))
    return ok


def _expert_positions(config: GridConfig, passable, fields, agent, reference):
    """int32 (max_steps+1, 2) positions of the expert path (see expert_path_positions) by
    descending _goal_fields from the agent (through the reference)."""
    to_target, to_ref = fields
    if not config.has_reference:
        return bfs.descend(to_target, passable, agent, config.max_steps)
    leg1 = bfs.descend(to_ref, passable, agent, config.max_steps)
    leg2 = bfs.descend(to_target, passable, reference, config.max_steps)
    n1 = jnp.minimum(to_ref[agent[0], agent[1]], config.max_steps).astype(jnp.int32)
    # Positions: leg1[0..n1], then leg2[1..]; index i >= n1 maps to leg2[i - n1].
    idx = jnp.arange(config.max_steps + 1)
    return jnp.where((idx <= n1)[:, None], leg1, leg2[jnp.clip(idx - n1, 0, config.max_steps)])


def expert_path_positions(config: GridConfig, passable, agent, target, reference):
    """A shortest path agent -> reference (if the setting has one) -> target over passable
    cells (bool (H, W)): positions int32 (max_steps+1, 2) padded by repeating the end,
    length int32 () in moves (capped at max_steps), and whether it fits in max_steps."""
    fields = _goal_fields(config, passable, target, reference)
    length = _expert_length(config, fields, agent, reference)
    positions = _expert_positions(config, passable, fields, agent, reference)
    return positions, jnp.minimum(length, config.max_steps).astype(jnp.int32), \
        length <= config.max_steps


def generate(key, config: GridConfig) -> Episode:
    """Draws one solvable episode. Pure; vmap over keys for a batch. config is static."""
    size = config.size
    k_agent, k_goal, k_objects, k_obstacles, k_template = jax.random.split(key, 5)
    agent = _choose_cell(k_agent, jnp.ones((size, size), bool))
    target, reference = _place_goal_cells(k_goal, config, agent)
    grid, target_class, reference_class = _objects_grid(k_objects, config, agent, target,
                                                        reference)
    free = (grid == 0).at[agent[0], agent[1]].set(False)

    def draw_layout(attempt_key, attempt):
        k_count, k_cells = jax.random.split(attempt_key)
        count = jax.random.randint(k_count, (), 0, config.max_obstacles + 1)
        # After the last failed attempt, fall back to no obstacles (always solvable).
        count = jnp.where(attempt >= _MAX_LAYOUT_TRIES, 0, count)
        if config.max_obstacles == 0:
            return jnp.zeros((size, size), bool)
        return _random_subset(k_cells, free, count, config.max_obstacles)

    def cond(carry):
        # The obstacle-free fallback is always solvable (GridConfig checks max_steps; every
        # object is reachable), so the attempt cap is only a guard.
        return ~carry[3] & (carry[0] <= _MAX_LAYOUT_TRIES + 1)

    def body(carry):
        # Only the distance fields are computed per attempt; the path is descended once, after
        # the loop (under vmap every attempt of any episode runs the body for the whole batch).
        attempt = carry[0]
        obstacles = draw_layout(jax.random.fold_in(k_obstacles, attempt), attempt)
        fields = _goal_fields(config, ~obstacles, target, reference)
        length = _expert_length(config, fields, agent, reference)
        return attempt + 1, obstacles, fields, _solvable(config, fields, length, grid > 0), \
            length

    _, obstacles, fields, _, length = jax.lax.while_loop(cond, body,
                                                         body((jnp.int32(0), None, None, None)))
    positions = _expert_positions(config, ~obstacles, fields, agent, reference)
    length = jnp.minimum(length, config.max_steps).astype(jnp.int32)

    grid = jnp.where(obstacles, OBSTACLE_CELL, grid).astype(jnp.int8)
    if config.has_reference:
        direction = compass_sector(reference, target)
    else:
        direction = jnp.int32(-1)
    templates = jnp.asarray(grammar.compile_templates(config.setting))
    template = language.draw_template(k_template, config.template_pool)
    tokens = grammar.fill_template(templates[grammar.token_template(template)],
                                   reference_class, target_class,
                                   jnp.maximum(direction, 0))
    valid = jnp.arange(config.max_steps + 1) <= length
    return Episode(
        grid=grid, agent=agent, target=target, reference=reference,
        target_class=jnp.int32(target_class), reference_class=jnp.int32(reference_class),
        direction=direction, template=template.astype(jnp.int32), tokens=tokens,
        expert_positions=positions, expert_length=length,
        expert_path=bfs.positions_to_mask(positions, size, valid),
    )


def generate_batch(key, config: GridConfig, n: int) -> Episode:
    """n episodes from one key (episode i uses fold_in(key, i): any prefix is stable)."""
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(n))
    return jax.vmap(generate, in_axes=(0, None))(keys, config)


def fingerprints(episodes: Episode, instruction: bool = True) -> list[bytes]:
    """One 16-byte digest per episode (numpy or jax arrays with a leading axis): equal
    digests mean equal episodes (grid, agent, target, reference, instruction), the content a
    planner is evaluated on (the expert path follows from it). instruction=False leaves the
    instruction's tokens out: equal digests then mean the same world, whatever its wording."""
    import hashlib

    fields = (episodes.grid, episodes.agent, episodes.target, episodes.reference) + \
        ((episodes.tokens,) if instruction else ())
    n = int(np.shape(episodes.agent)[0])
    rows = np.concatenate([np.asarray(f).reshape(n, -1).astype(np.int16) for f in fields],
                          axis=1)
    return [hashlib.blake2b(row.tobytes(), digest_size=16).digest() for row in rows]

