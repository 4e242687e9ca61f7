"""The grid world's speed-ups change no result: generated episodes are pinned by hashes computed
with the code before the speed-ups (episode.generate's RNG draws, layouts, tie-breaking and
expert paths), and the fast internals equal what they replace (the unrolled threefry uniform,
the batched unit-cost BFS under vmap vs one grid at a time).

If a hash changes, the generated episodes changed: models evaluated on them are no longer
comparable with the published numbers. The hashes assume jax's default threefry PRNG with
jax_threefry_partitionable on (jax 0.6.2); a jax upgrade that changes jax.random's bits changes
them too (then episodes did change, through jax)."""
from __future__ import annotations

import hashlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.gridworld import bfs, episode

EPISODE_HASHES = {
    # (setting, seed) -> sha256 prefix of gen_batch(setting, seed)'s episodes (GRID_BATCH = 64),
    # with (sum of expert lengths, number of obstacle cells) as a readable hint. The digests
    # changed once, when the vocabulary grew to 55 words (the phrasing split): the same worlds
    # and hints, the canonical instruction's words at new token ids.
    ("1o1g", 0): ("76177e1b0855668d", 729, 0),
    ("1o1g", 12): ("962159962af8ffdf", 736, 0),
    ("mo1g", 0): ("4eeece131458bbae", 731, 305),
    ("mo1g", 12): ("99821f971163c90c", 736, 323),
    ("p_mo2g", 0): ("1a2294cccfbac4f9", 999, 305),
    ("p_mo2g", 12): ("341452d78548e4ae", 995, 323),
    # p_mo2g_far (beyond the paper), pinned when it was added.
    ("p_mo2g_far", 0): ("524d4c90d95b4a93", 863, 653),
    ("p_mo2g_far", 12): ("1ea7f84d9850c0df", 907, 622),
}


def episodes_digest(eps) -> str:
    """sha256 prefix over every array field of a batch of episodes (name, dtype, shape, bytes).
    A field left None (Episode.features of a token-id episode) is no array and is skipped: its
    np.asarray would be an object array whose bytes are a pointer."""
    h = hashlib.sha256()
    for name in sorted(eps.__dict__):
        if getattr(eps, name) is None:
            continue
        a = np.ascontiguousarray(np.asarray(getattr(eps, name)))
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


@pytest.mark.parametrize("setting, seed", sorted(EPISODE_HASHES))
def test_generated_episodes_unchanged(gen_batch, setting, seed):
    eps, _ = gen_batch(setting, seed)
    digest, length_sum, obstacles = EPISODE_HASHES[setting, seed]
    assert int(eps.expert_length.sum()) == length_sum
    assert int((eps.grid == -1).sum()) == obstacles
    assert episodes_digest(eps) == digest


def test_generate_unbatched_equals_batched(gen_batch, grid_configs):
    """episode.generate of one key (the unit BFS on one grid) equals the vmapped batch (the
    grids relaxed together on the minor axis)."""
    eps, _ = gen_batch("p_mo2g", 0)
    generate = jax.jit(lambda k: episode.generate(k, grid_configs["p_mo2g"]))
    for i in (0, 5):
        one = generate(jax.random.fold_in(jax.random.PRNGKey(0), i))
        for name in eps.__dict__:
            if getattr(eps, name) is None:
                assert getattr(one, name) is None, name
                continue
            np.testing.assert_array_equal(np.asarray(getattr(one, name)),
                                          getattr(eps, name)[i], err_msg=name)


@pytest.mark.parametrize("shape", [(16, 16), (3, 5), (1, 7)])
def test_fast_uniform_is_jax_uniform(shape):
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.PRNGKey(3), i))(jnp.arange(64))
    fast = jax.jit(jax.vmap(lambda k: episode._uniform(k, shape)))(keys)
    np.testing.assert_array_equal(fast, jax.vmap(lambda k: jax.random.uniform(k, shape))(keys))
    typed = jax.random.key(7)
    np.testing.assert_array_equal(episode._uniform(typed, shape), jax.random.uniform(typed, shape))


def test_first_argmax_is_argmax():
    values = jnp.array([0.5, -1.0, 0.7, 0.7, 0.1])  # a tie: the first wins
    assert int(episode._first_argmax(values)) == int(jnp.argmax(values)) == 2
    rng = np.random.default_rng(0)
    many = rng.integers(0, 4, (200, 9)).astype(np.float32)  # many ties
    np.testing.assert_array_equal(jax.vmap(episode._first_argmax)(many), np.argmax(many, -1))


def test_unit_bfs_batched_equals_single_grid():
    """The custom vmap rule (grids on the minor axis, broadcast unbatched arguments, nested
    vmap) gives each grid's own field."""
    rng = np.random.default_rng(1)
    passable = rng.uniform(size=(2, 3, 9, 11)) >= 0.3
    sources = np.stack([rng.integers(0, 9, (2, 3)), rng.integers(0, 11, (2, 3))], -1)
    sources = sources.astype(np.int32)
    single = np.array([[bfs.cost_to_go(passable[i, j], sources[i, j]) for j in range(3)]
                       for i in range(2)])
    np.testing.assert_array_equal(jax.vmap(jax.vmap(bfs.cost_to_go))(passable, sources), single)
    np.testing.assert_array_equal(
        jax.vmap(bfs.cost_to_go, in_axes=(None, 0))(passable[0, 0], sources[0]),
        np.array([bfs.cost_to_go(passable[0, 0], s) for s in sources[0]]))
