"""The shared MJX model and pure accessors of the physics state (an ``mjx.Data``).

One ``mjx.Model`` serves every episode (:func:`mjx_model`); everything episode-specific lives
in ``mjx.Data``: qpos = 7 arm joints then 4 free joints (x, y, z, qw, qx, qy, qz each), the
servo targets in ``ctrl`` (7,) and the suction in ``eq_active`` (4,), weld i holding block i.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from envs.kuka import scene

ARM_QPOS = slice(0, scene.NUM_JOINTS)
BLOCK_QPOS0 = scene.NUM_JOINTS
"""Block i's free joint occupies qpos[BLOCK_QPOS0 + 7 i : BLOCK_QPOS0 + 7 i + 7]."""
BLOCK_QVEL0 = scene.NUM_JOINTS


@functools.lru_cache(maxsize=None)
def mjx_model():
    """The scene as an ``mjx.Model`` (built once per process, shared by every episode; safe to
    call first inside a jit trace: its arrays are concrete)."""
    from mujoco import mjx

    with jax.ensure_compile_time_eval():
        return mjx.put_model(scene.mj_model())


@functools.lru_cache(maxsize=None)
def body_id(name: str) -> int:
    import mujoco

    return mujoco.mj_name2id(scene.mj_model(), mujoco.mjtObj.mjOBJ_BODY, name)


def flange_id() -> int:
    return body_id("flange")


def block_pos(data) -> jax.Array:
    """float (4, 3) block centres (world frame, m)."""
    q = data.qpos[BLOCK_QPOS0:BLOCK_QPOS0 + 7 * scene.NUM_BLOCKS].reshape(scene.NUM_BLOCKS, 7)
    return q[:, :3]


def block_quat(data) -> jax.Array:
    """float (4, 4) block orientations (w, x, y, z)."""
    q = data.qpos[BLOCK_QPOS0:BLOCK_QPOS0 + 7 * scene.NUM_BLOCKS].reshape(scene.NUM_BLOCKS, 7)
    return q[:, 3:]


def block_yaw(data) -> jax.Array:
    """float (4,) each block's rotation about the world z (rad; its heading for flat blocks)."""
    w, x, y, z = jnp.moveaxis(block_quat(data), -1, 0)
    return jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def held(data) -> jax.Array:
    """bool (4,) the suction holds block i."""
    return data.eq_active.astype(bool)


def initial_data(block_xy, arm_q=None):
    """mjx.Data at rest: blocks flat (identity orientation) on the floor at block_xy float (4, 2),
    the arm at arm_q (7,) (default scene.HOME_QPOS) with its servos targeting it, nothing held.
    Positions are derived (mjx.kinematics), so the data is ready to observe; every mjx.step
    derives everything else from qpos, qvel, ctrl, eq_active and qacc_warmstart again, so
    stepping it gives bit for bit what stepping mjx.forward's data gives (tested), and it
    compiles in a fraction of mjx.forward's time (a reset inside a jitted rollout)."""
    from mujoco import mjx

    model = mjx_model()
    arm_q = jnp.asarray(scene.HOME_QPOS if arm_q is None else arm_q, jnp.float32)
    block_xy = jnp.asarray(block_xy, jnp.float32)
    n = scene.NUM_BLOCKS
    blocks = jnp.concatenate([
        block_xy, jnp.full((n, 1), scene.BLOCK_HALF_SIZE[2], jnp.float32),
        jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32), (n, 1))], axis=1)
    data = mjx.make_data(model)
    data = data.replace(qpos=jnp.concatenate([arm_q, blocks.ravel()]), ctrl=arm_q,
                        eq_active=jnp.zeros(n, jnp.uint8))
    return mjx.kinematics(model, data)


def set_blocks(data, pos, quat):
    """data with block poses replaced (pos float (4, 3), quat (4, 4)), block velocities zeroed."""
    n = scene.NUM_BLOCKS
    blocks = jnp.concatenate([jnp.asarray(pos), jnp.asarray(quat)], axis=1).ravel()
    qpos = data.qpos.at[BLOCK_QPOS0:BLOCK_QPOS0 + 7 * n].set(blocks.astype(data.qpos.dtype))
    qvel = data.qvel.at[BLOCK_QVEL0:].set(0.0)
    return data.replace(qpos=qpos, qvel=qvel)


def quat_to_mat(quat) -> jax.Array:
    """(..., 4) (w, x, y, z) unit quaternions -> (..., 3, 3) rotation matrices (jnp or numpy)."""
    xp = jnp if isinstance(quat, jax.Array) else np
    q = quat / xp.linalg.norm(quat, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def simulate(data, num_steps):
    """data after num_steps (int, may be traced: one compilation serves every count) physics
    steps with the servo targets and suction held as they are."""
    from mujoco import mjx

    model = mjx_model()
    return jax.lax.fori_loop(0, num_steps, lambda _, d: mjx.step(model, d), data)


simulate_batch = jax.jit(jax.vmap(simulate, in_axes=(0, None)))
"""jitted simulate over a batch of mjx.Data (one compilation per batch size)."""
