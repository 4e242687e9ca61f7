"""Pure-JAX inverse kinematics of the arm's flange: damped least squares on MJX kinematics.

:func:`solve` iterates ``q <- clip(q + J^T (J J^T + lambda^2 I)^-1 e)`` a fixed number of times
in ``lax.scan``, with ``e`` the 6-d pose error (position, and orientation weighted by
ROT_WEIGHT m/rad) of the flange computed by ``mjx.kinematics`` and ``J`` its geometric Jacobian
from ``mjx.jac`` (about 4x cheaper to compile than ``jax.jacfwd`` through the kinematics, same
result); joints are clipped to their limits after each step. Jit- and vmap-able.

Top-down grasps (the flange's z pointing down, :func:`down_rotation`) get a seed from the arm's
planar structure (:func:`planar_seed`): with joints 3 and 5 at zero the arm is a planar chain of
joints 2, 4, 6 in the vertical plane at azimuth q1, which a two-link solution places exactly;
DLS then refines it (and moves joints 3 and 5 where joint 1 is at its limit). Joint 1 spans
+-170 deg, so the arm reaches behind itself "flipped" (q1 = azimuth - pi, leaning backwards):
:func:`choose_branch` picks the branch for a whole carry path at once so that joints 1 and 7
move continuously along it, the flange keeping the held block's yaw.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs.kuka import physics, scene

ROT_WEIGHT = 0.2
"""Metres of position error worth one radian of orientation error."""
DAMPING = 0.02
SHOULDER_Z = scene.LINK_OFFSETS[0] + scene.LINK_OFFSETS[1]
UPPER_ARM = scene.LINK_OFFSETS[2] + scene.LINK_OFFSETS[3]
FOREARM = scene.LINK_OFFSETS[4] + scene.LINK_OFFSETS[5]
HAND = scene.LINK_OFFSETS[6] + scene.FLANGE_OFFSET
LIMITS = jnp.asarray(scene.JOINT_LIMITS)


def _kinematics(q):
    """mjx.Data with positions and com-based quantities derived for arm joints q (7,)."""
    from mujoco import mjx

    model = physics.mjx_model()
    data = mjx.make_data(model)
    data = data.replace(qpos=data.qpos.at[physics.ARM_QPOS].set(q))
    return mjx.com_pos(model, mjx.kinematics(model, data))


def flange_pose(q):
    """Flange (pos float (3,), rot float (3, 3)) of arm joints q float (7,) by mjx.kinematics."""
    data = _kinematics(q)
    fid = physics.flange_id()
    return data.xpos[fid], data.xmat[fid]


def pose_error_and_jacobian(q, target_pos, target_rot):
    """(e float (6,), J float (6, 7)) at arm joints q: the flange's position error (m) and
    ROT_WEIGHT * orientation error (0.5 * sum_i R_i x R*_i, the rotation vector from R to R* for
    small errors), and the geometric Jacobian of the flange's (position, ROT_WEIGHT * rotation)
    with respect to the arm joints (mjx.jac)."""
    from mujoco import mjx

    data = _kinematics(q)
    fid = physics.flange_id()
    pos, rot = data.xpos[fid], data.xmat[fid]
    jacp, jacr = mjx.jac(physics.mjx_model(), data, pos, fid)  # (nv, 3) each
    rot_err = 0.5 * jnp.sum(jnp.cross(rot.T, jnp.asarray(target_rot).T), axis=0)
    e = jnp.concatenate([target_pos - pos, ROT_WEIGHT * rot_err])
    jac = jnp.concatenate([jacp.T, ROT_WEIGHT * jacr.T])[:, physics.ARM_QPOS]
    return e, jac


def solve(q_seed, target_pos, target_rot, iterations: int = 12, damping: float = DAMPING):
    """Damped least squares from q_seed float (7,) towards the flange pose (target_pos (3,),
    target_rot (3, 3)); a fixed number of iterations in lax.scan.

    Returns (q float32 (7,) within the joint limits, position error float () m, orientation
    error float () rad) at the final q.
    """
    target_pos = jnp.asarray(target_pos, jnp.float32)
    target_rot = jnp.asarray(target_rot, jnp.float32)
    eye = jnp.eye(6)

    def body(q, _):
        e, jac = pose_error_and_jacobian(q, target_pos, target_rot)
        dq = jac.T @ jnp.linalg.solve(jac @ jac.T + damping ** 2 * eye, e)
        return jnp.clip(q + dq, -LIMITS, LIMITS), None

    q, _ = jax.lax.scan(body, jnp.asarray(q_seed, jnp.float32), None, length=iterations)
    e, _ = pose_error_and_jacobian(q, target_pos, target_rot)
    return q, jnp.linalg.norm(e[:3]), jnp.linalg.norm(e[3:]) / ROT_WEIGHT


def down_rotation(yaw) -> jax.Array:
    """float (3, 3): the flange pointing straight down (its z = world -z), turned by yaw about
    the world z: Rz(yaw) @ Ry(pi)."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    rz = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rz @ jnp.diag(jnp.array([-1.0, 1.0, -1.0]))


def planar_seed(target_pos, q1, yaw) -> jax.Array:
    """float32 (7,) a pointing-down configuration reaching target_pos (3,) with joint 1 at q1
    (the branch: the target in front of the arm's plane or behind it) and the flange's yaw
    (q7 = q1 - yaw), from the two-link solution for the wrist; exact when q1 points the arm's
    plane through the target and the wrist is in reach, clipped to the joint limits."""
    target_pos = jnp.asarray(target_pos)
    rho = target_pos[0] * jnp.cos(q1) + target_pos[1] * jnp.sin(q1)  # signed, in the plane
    sign = jnp.where(rho >= 0, 1.0, -1.0)
    wx = jnp.abs(rho)
    wz = target_pos[2] + HAND - SHOULDER_Z
    dist2 = wx ** 2 + wz ** 2
    cos4 = jnp.clip((dist2 - UPPER_ARM ** 2 - FOREARM ** 2) / (2 * UPPER_ARM * FOREARM), -1, 1)
    q4 = jnp.arccos(cos4)  # elbow up
    q2 = jnp.arctan2(wx, wz) - jnp.arctan2(FOREARM * jnp.sin(q4), UPPER_ARM + FOREARM * cos4)
    q6 = jnp.pi - q2 - q4
    q = jnp.stack([q1, sign * q2, 0.0 * q1, sign * q4, 0.0 * q1, sign * q6, q1 - yaw])
    return jnp.clip(q, -LIMITS, LIMITS).astype(jnp.float32)


def choose_branch(points_xy, yaw=0.0):
    """Joint-1 angles and flange yaw for a path the flange follows pointing down.

    points_xy float (P, 2); yaw float (): the flange yaw wanted along the whole path (the held
    block's yaw: the suction weld's relative pose is fixed, so the flange must match the block's
    orientation when it grasps, and keeps it while carrying). Returns (q1 float32 (P,), yaw
    float32 ()): q1 follows the points' azimuths continuously (unwrapped), on the branch (facing
    them, or flipped by pi, leaning backwards) and 2 pi shift that keep it farthest inside joint
    1's limits; yaw is the given one shifted by a multiple of 2 pi (the same orientation) to
    keep q7 = q1 - yaw nearest zero along the path.
    """
    points_xy = jnp.asarray(points_xy)
    azimuth = jnp.arctan2(points_xy[:, 1], points_xy[:, 0])
    steps = jnp.mod(jnp.diff(azimuth) + jnp.pi, 2 * jnp.pi) - jnp.pi
    unwrapped = azimuth[0] + jnp.concatenate([jnp.zeros(1), jnp.cumsum(steps)])
    candidates = []
    for offset in (0.0, -np.pi, np.pi):
        for shift in (-2 * np.pi, 0.0, 2 * np.pi):
            candidates.append(unwrapped + offset + shift)
    candidates = jnp.stack(candidates)  # (9, P)
    worst = jnp.max(jnp.abs(candidates), axis=1)
    q1 = candidates[jnp.argmin(worst)]
    middle = 0.5 * (jnp.min(q1) + jnp.max(q1))
    yaws = jnp.asarray(yaw, jnp.float32) + 2 * np.pi * jnp.arange(-2, 3)
    best = yaws[jnp.argmin(jnp.abs(middle - yaws))]
    return q1.astype(jnp.float32), best.astype(jnp.float32)


def solve_down(targets, q1, yaw, iterations: int = 12):
    """IK of pointing-down flange targets float (N, 3) with joint-1 angles q1 (N,) (their
    branch) and one yaw: vmapped :func:`solve` from :func:`planar_seed`.

    Returns (q float32 (N, 7), position error (N,), orientation error (N,))."""
    rot = down_rotation(yaw)
    seeds = jax.vmap(planar_seed, in_axes=(0, 0, None))(targets, q1, yaw)
    return jax.vmap(lambda s, t: solve(s, t, rot, iterations))(seeds, targets)
