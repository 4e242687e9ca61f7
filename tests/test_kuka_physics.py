"""The scene's physics in MJX: a four-block tower stands, and reset never overlaps blocks."""
from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envs.kuka import env, physics, scene
from envs.kuka.episode import MIN_GAP, sample_layout
import kuka_fixtures as kf

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)


def test_model_prunes_contacts_to_blocks_and_floor():
    import mujoco

    m = scene.mj_model()
    colliding = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) for g in range(m.ngeom)
                 if m.geom_contype[g] or m.geom_conaffinity[g]]
    assert sorted(colliding) == sorted(["floor"] + [f"block_{n}" for n in scene.BLOCK_NAMES])
    assert m.neq == 4 and not m.eq_active0.any()  # the suction welds start off
    assert m.opt.timestep == scene.TIMESTEP
    np.testing.assert_allclose(m.body_mass[[physics.body_id(f"block_{n}")
                                            for n in scene.BLOCK_NAMES]], scene.BLOCK_MASS)


def test_four_block_tower_stands_five_seconds():
    """One tower of four per episode (at four places around the base, the arm at home): after
    1000 steps (5 s) every block is within 1 cm of where it started."""
    states = env.reset_batch(kf.episodes("stacking_multi", 0))
    angles = np.linspace(0, 2 * np.pi, kf.BATCH, endpoint=False) + 0.3
    pos = np.zeros((kf.BATCH, 4, 3), np.float32)
    pos[..., 0] = (0.6 * np.cos(angles))[:, None]
    pos[..., 1] = (0.6 * np.sin(angles))[:, None]
    pos[..., 2] = scene.BLOCK_HALF_SIZE[2] * (1 + 2 * np.arange(4))
    quat = np.tile(np.array([1.0, 0, 0, 0], np.float32), (kf.BATCH, 4, 1))
    data = jax.jit(jax.vmap(physics.set_blocks))(states.data, pos, quat)
    final = physics.simulate_batch(data, 1000)
    drift = np.linalg.norm(np.asarray(jax.vmap(physics.block_pos)(final)) - pos, axis=-1)
    assert drift.max() < 0.01, drift
    assert float(final.time[0]) > 4.99


_layouts = jax.jit(jax.vmap(sample_layout))


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1))
def test_reset_never_overlaps_blocks(seed):
    """256 layouts per example (one vmapped call): centres 0.6 m from the base, footprints at
    least MIN_GAP apart (axis-aligned squares: separated along x or y)."""
    xy = np.asarray(_layouts(jax.random.split(jax.random.PRNGKey(seed), 256)))
    np.testing.assert_allclose(np.linalg.norm(xy, axis=-1), scene.BLOCK_RADIUS, atol=1e-5)
    sep = np.abs(xy[:, :, None] - xy[:, None]).max(-1) + 10 * np.eye(4)
    assert sep.min() >= 2 * scene.BLOCK_HALF_SIZE[0] + MIN_GAP - 1e-6


def test_reset_rests_flat_without_contact_between_blocks():
    states = env.reset_batch(kf.episodes("rearrangement_multi", 1))
    pos = np.asarray(jax.vmap(physics.block_pos)(states.data))
    np.testing.assert_allclose(pos[..., 2], scene.BLOCK_HALF_SIZE[2], atol=1e-6)
    np.testing.assert_allclose(pos[..., :2], kf.episodes("rearrangement_multi", 1).block_xy)
    # Reset derives positions only (mjx.kinematics); contacts come with the first step, so
    # they are computed here from the reset data.
    from mujoco import mjx

    model = physics.mjx_model()
    contact = jax.vmap(lambda d: mjx.forward(model, d))(states.data)._impl.contact
    g1, g2 = np.asarray(contact.geom1)[0], np.asarray(contact.geom2)[0]
    floor = physics_geom("floor")
    between_blocks = (g1 != floor) & (g2 != floor)
    assert between_blocks.any()
    assert (np.asarray(contact.dist)[:, between_blocks] > 0.02).all()
    assert not np.asarray(states.done).any() and (np.asarray(states.t) == 0).all()


def test_directions_are_uniform():
    """Kolmogorov-Smirnov distance of 4 x 4096 drawn directions to the uniform law."""
    xy = np.asarray(_layouts(jax.random.split(jax.random.PRNGKey(7), 4096)))
    angles = np.sort(np.arctan2(xy[..., 1], xy[..., 0]).ravel())
    cdf = (angles + np.pi) / (2 * np.pi)
    ks = np.max(np.abs(cdf - (np.arange(len(cdf)) + 0.5) / len(cdf)))
    assert ks < 0.02


def physics_geom(name: str) -> int:
    import mujoco

    return mujoco.mj_name2id(scene.mj_model(), mujoco.mjtObj.mjOBJ_GEOM, name)
