"""The pick-and-place primitive: inverse kinematics, then a fixed number of physics steps.

``pick_and_place(data, block, place_pos, waypoints_xy)`` moves the arm from wherever its servos
point to above the block, descends onto the block's top centre, switches the block's suction
weld on, lifts it to the carry height, carries it along the waypoints, lowers it onto place_pos,
switches the weld off and retreats upwards while the block settles. Every phase has a fixed
number of physics steps (:data:`PHASES`, 249 in all = 1.245 simulated seconds), so the whole
primitive is one ``lax.scan`` of ``mjx.step``: it jits and vmaps over episodes.

All joint targets are computed up front from the state at the call (the block's pose and the
place target do not depend on what happens during the motion): a pointing-down IK solution
(:mod:`envs.kuka.ik`) for every key pose, the branch chosen once for the whole carry and the
flange yaw set to the block's own (:func:`ik.choose_branch`: the weld's relative pose is fixed
in the model, so the block is carried exactly as it lay; a block knocked far from its initial,
world-aligned yaw can need joint 7 beyond its limit on some paths, where the IK clips it and
the weld twists the block as it grasps), and the servo targets interpolated in joint space
between key poses with a cosine ease over each phase. Phases that end in contact (the grasp and
the place) hold their last pose for a few steps so that the servos settle to well under a
millimetre.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs.kuka import ik, physics, scene

CARRY_HEIGHT = 0.40
"""Flange height (m) while carrying: the held block's bottom is then at 0.34 m, above a tower of
four (0.24 m)."""
APPROACH_OFFSET = 0.05
"""The descents slow down over their last APPROACH_OFFSET m (a key pose this far above)."""
RETREAT_HEIGHT = 0.10
PLACE_GAP = 0.004
"""The block is released this far (m) above its support."""

PHASES = (
    # name, move steps, hold steps, weld on
    ("approach", 50, 0, False),
    ("descend", 30, 8, False),
    ("grasp", 0, 4, True),
    ("lift", 25, 0, True),
    ("carry", 60, 0, True),
    ("lower", 30, 8, True),
    ("release", 0, 4, False),
    ("retreat", 30, 0, False),
)
NUM_STEPS = sum(move + hold for _, move, hold, _ in PHASES)
NUM_WAYPOINTS = 12
"""Default number of carry waypoints (the path is interpolated linearly in joint space between
their IK solutions)."""


def _ease(num: int) -> np.ndarray:
    """(num,) cosine ease from 0 (excluded) to 1 (included)."""
    u = (np.arange(num) + 1) / num
    return 0.5 - 0.5 * np.cos(np.pi * u)


def _along(keys, s):
    """Joint targets (T, 7) at fractions s (T,) in [0, 1] of the polyline through keys (K, 7)."""
    k = keys.shape[0]
    x = jnp.asarray(s) * (k - 1)
    lo = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, k - 2)
    frac = (x - lo)[:, None]
    return keys[lo] * (1 - frac) + keys[lo + 1] * frac


def reference(phase_keys):
    """Servo targets and weld flags of the whole primitive from each phase's key poses.

    phase_keys: one (K_p, 7) array per phase of PHASES (K_p >= 1; a phase with move steps goes
    from its first key to its last through the others). Returns (ctrl float32 (NUM_STEPS, 7),
    weld bool (NUM_STEPS,)), both static-length."""
    ctrls, welds = [], []
    for (name, move, hold, weld), keys in zip(PHASES, phase_keys):
        if move:
            if keys.shape[0] < 2:
                raise ValueError(f"phase {name} moves: it needs at least 2 key poses")
            ctrls.append(_along(keys, _ease(move)))
        if hold:
            ctrls.append(jnp.broadcast_to(keys[-1], (hold, keys.shape[-1])))
        welds.append(np.full(move + hold, weld))
    return jnp.concatenate(ctrls).astype(jnp.float32), jnp.asarray(np.concatenate(welds))


def plan(data, block, place_pos, waypoints_xy):
    """The primitive's servo targets (see :func:`reference`) and the worst IK error.

    data: mjx.Data at the call; block: int32 () the block to move (-1: none, the arm moves
    without grasping); place_pos: float (3,) where the held block's top centre goes (its
    support's top + a block height + PLACE_GAP); waypoints_xy: float (N, 2) the carry path, its
    ends replaced by the block's and the place's xy.
    Returns (ctrl float32 (NUM_STEPS, 7), weld bool (NUM_STEPS,), ik position error float ()).
    """
    index = jnp.clip(block, 0, scene.NUM_BLOCKS - 1)
    pos = physics.block_pos(data)[index]
    pick = pos + jnp.array([0.0, 0.0, scene.BLOCK_HALF_SIZE[2]])
    place_pos = jnp.asarray(place_pos, jnp.float32)
    carry_xy = jnp.asarray(waypoints_xy, jnp.float32)
    carry_xy = carry_xy.at[0].set(pick[:2]).at[-1].set(place_pos[:2])
    # The flange matches the block's yaw: the weld then holds it as it lies (no twist on grasp).
    q1, yaw = ik.choose_branch(carry_xy, physics.block_yaw(data)[index])
    up = jnp.array([0.0, 0.0, 1.0])
    carry = jnp.concatenate([carry_xy, jnp.full((carry_xy.shape[0], 1), CARRY_HEIGHT)], axis=1)
    ends = jnp.stack([pick + APPROACH_OFFSET * up, pick,
                      place_pos + APPROACH_OFFSET * up, place_pos,
                      place_pos + RETREAT_HEIGHT * up])
    targets = jnp.concatenate([carry, ends])
    target_q1 = jnp.concatenate([q1, jnp.stack([q1[0], q1[0], q1[-1], q1[-1], q1[-1]])])
    q, pos_err, _ = ik.solve_down(targets, target_q1, yaw)
    n = carry.shape[0]
    carry_q = q[:n]
    mid_pick, at_pick, mid_place, at_place, retreat = (q[n + i][None] for i in range(5))
    above_pick, above_place = carry_q[:1], carry_q[-1:]
    start = data.ctrl[None, physics.ARM_QPOS]
    phase_keys = (
        jnp.concatenate([start, above_pick]),                    # approach
        jnp.concatenate([above_pick, mid_pick, at_pick]),        # descend
        at_pick,                                                 # grasp
        jnp.concatenate([at_pick, mid_pick, above_pick]),        # lift
        carry_q,                                                 # carry
        jnp.concatenate([above_place, mid_place, at_place]),     # lower
        at_place,                                                # release
        jnp.concatenate([at_place, retreat]),                    # retreat
    )
    ctrl, weld = reference(phase_keys)
    return ctrl, weld, jnp.max(pos_err)


FRAME_EVERY = 8
"""The primitive records the physics state every FRAME_EVERY steps (0.04 s: 25 frames per
simulated second) for videos."""
NUM_FRAMES = NUM_STEPS // FRAME_EVERY


def run(data, ctrl, weld, block):
    """Steps the physics along servo targets ctrl (T, 7) with block's weld on where weld (T,).

    Returns (the final mjx.Data, qpos float32 (T // FRAME_EVERY, nq) of every FRAME_EVERY-th
    step, for videos)."""
    from mujoco import mjx

    model = physics.mjx_model()
    onehot = (jnp.arange(scene.NUM_BLOCKS) == block)

    def body(d, inputs):
        target, on = inputs
        d = d.replace(ctrl=target, eq_active=(onehot & on).astype(d.eq_active.dtype))
        d = mjx.step(model, d)
        return d, d.qpos

    data, qpos = jax.lax.scan(body, data, (ctrl, weld))
    return data, qpos[FRAME_EVERY - 1::FRAME_EVERY][:ctrl.shape[0] // FRAME_EVERY]


def pick_and_place(data, block, place_pos, waypoints_xy):
    """Moves block (int32 (), -1: none) to place_pos float (3,) (the block's top centre when
    placed) along waypoints_xy float (N, 2) under physics (NUM_STEPS steps).

    Returns (the final mjx.Data, nothing held; frames float32 (NUM_FRAMES, nq), see run)."""
    ctrl, weld, _ = plan(data, block, place_pos, waypoints_xy)
    return run(data, ctrl, weld, block)


def place_target(support_top, xy):
    """float32 (3,): the top-centre target of a block placed at xy (2,) on a support whose top is
    at height support_top (m; 0 for the floor)."""
    z = support_top + 2 * scene.BLOCK_HALF_SIZE[2] + PLACE_GAP
    return jnp.concatenate([jnp.asarray(xy, jnp.float32), jnp.reshape(z, (1,))]).astype(
        jnp.float32)
