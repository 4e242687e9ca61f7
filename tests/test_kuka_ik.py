"""Damped least squares IK on MJX kinematics reaches reachable targets within 1 cm."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kuka_fixtures as kf
from envs.kuka import ik, scene

pytestmark = pytest.mark.filterwarnings(kf.MJX_CAST_WARNING)

LIMITS = scene.JOINT_LIMITS


@jax.jit
@jax.vmap
def _reach(q_target, q_seed):
    """Solve for the flange pose of q_target from q_seed: (position error, orientation error,
    solution)."""
    pos, rot = ik.flange_pose(q_target)
    q, _, _ = ik.solve(q_seed, pos, rot, iterations=30)
    got_pos, got_rot = ik.flange_pose(q)
    angle = jnp.arccos(jnp.clip((jnp.trace(got_rot.T @ rot) - 1) / 2, -1, 1))
    return jnp.linalg.norm(got_pos - pos), angle, q


def test_reaches_random_reachable_poses():
    """Targets: the flange poses of 64 random configurations (within 80% of the limits); seeds
    perturbed by up to 0.3 rad per joint. Checked by forward kinematics of the solution."""
    rng = np.random.default_rng(0)
    q_target = (rng.uniform(-0.8, 0.8, (64, 7)) * LIMITS).astype(np.float32)
    q_seed = np.clip(q_target + rng.uniform(-0.3, 0.3, (64, 7)), -LIMITS, LIMITS).astype(
        np.float32)
    pos_err, rot_err, q = (np.asarray(x) for x in _reach(q_target, q_seed))
    assert pos_err.max() < 0.01, pos_err.max()
    assert np.degrees(rot_err).max() < 1.0
    assert (np.abs(q) <= LIMITS + 1e-6).all()


@jax.jit
@jax.vmap
def _reach_down(target):
    q1, yaw = ik.choose_branch(target[None, :2])
    q, _, _ = ik.solve_down(target[None], q1, yaw)
    pos, rot = ik.flange_pose(q[0])
    return jnp.linalg.norm(pos - target), rot, yaw, q[0]


def test_reaches_pointing_down_targets_all_around_the_base():
    """The primitive's targets: pointing down, 0.4-0.75 m from the base in every direction
    (behind the arm too, where joint 1 cannot point), 3-45 cm high."""
    rng = np.random.default_rng(1)
    angle = rng.uniform(-np.pi, np.pi, 64)
    radius = rng.uniform(0.4, 0.75, 64)
    targets = np.stack([radius * np.cos(angle), radius * np.sin(angle),
                        rng.uniform(0.03, 0.45, 64)], 1).astype(np.float32)
    err, rot, yaw, q = (np.asarray(x) for x in _reach_down(targets))
    assert err.max() < 0.01, err.max()
    down = np.asarray(jax.vmap(ik.down_rotation)(yaw))
    np.testing.assert_allclose(rot, down, atol=0.02)
    assert (np.abs(q) <= LIMITS + 1e-6).all()


def test_branch_follows_a_path_behind_the_arm_continuously():
    """A carry from 150 to -150 degrees crosses behind the base: joint 1 moves continuously
    (flipped branch) and within its limits; the flange keeps the block's yaw (up to 2 pi) with
    q7 = q1 - yaw within joint 7's limits (for blocks near their initial, world-aligned yaw:
    one turned by ~180 deg would need q7 beyond its limit on some paths; the IK then clips it
    and the weld twists the block on grasp)."""
    angles = np.radians(np.linspace(150, 210, 12))
    pts = 0.6 * np.stack([np.cos(angles), np.sin(angles)], 1)
    for block_yaw in (0.0, 0.1, -0.15):
        q1, yaw = (np.asarray(x) for x in jax.jit(ik.choose_branch)(pts, block_yaw))
        assert np.abs(np.diff(q1)).max() < 0.2
        assert np.abs(q1).max() < LIMITS[0]
        assert np.isclose(np.cos(yaw - block_yaw), 1.0, atol=1e-6)
        assert np.abs(q1 - yaw).max() < np.pi / 2
