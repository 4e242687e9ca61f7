"""The Kuka block world's MJCF scene, written here (no external assets), and its constants.

Geometry follows Diffuser's ``kuka`` block task (docs/DESIGN.md, "Kuka world (MJX)"):

* a 7-joint iiwa14-like arm fixed at the origin: link offsets 0.1575, 0.2025, 0.2045, 0.2155,
  0.1845, 0.2155, 0.081 m along each link's z and 0.045 m from joint 7 to the flange (the arm
  points straight up at q = 0, the flange at z = 1.306 m); joint axes z, y, z, y, z, y, z;
  limits +-2.967 / +-2.094 / +-3.054 rad. Position servos with joint damping and armature; the
  links are gravity-compensated (``gravcomp``) so the servos track their targets without
  steady-state sag. kp is 4000 (MuJoCo Menagerie's iiwa14 uses 2000): measured in C MuJoCo on a
  0.8 rad, 0.2 s move, the flange settles within 0.3 mm 10 steps after the move (kp 2000: 2.5 mm
  with more damping, 8 mm with less), and Euler with explicit damping stays stable (damping 50,
  armature 0.2: damping * dt / inertia <= 1.25; kp 8000 diverged). Capsule geoms draw the
  links but collide with nothing (contype = conaffinity = 0): the arm acts only through the
  suction weld.
* a floor plane whose top is z = 0 and four blocks (red, green, blue, yellow) of
  0.2 x 0.2 x 0.06 m and 0.068 kg on free joints. Only block-block and block-floor contacts
  exist (the floor and blocks are the only geoms with contype/conaffinity bits).
* suction: one weld per block from the flange body to the block, off in the model
  (``active="false"``) and switched per episode through ``mjx.Data.eq_active``. Its relative
  pose is fixed in the Model: the block's centre half a block height below the flange, the
  block's frame the flange's turned upside down (the flange's z points down when grasping).

Solver settings measured for stable stacks (docs/DESIGN.md): timestep 0.005 s, Newton, 8 iterations,
8 line-search iterations, pyramidal friction cone, condim 3, friction 0.8, eulerdamp disabled.
"""
from __future__ import annotations

import functools

import numpy as np

BLOCK_NAMES: tuple[str, ...] = ("red", "green", "blue", "yellow")
"""Block i is BLOCK_NAMES[i] (the index order of contract 4)."""
NUM_BLOCKS = len(BLOCK_NAMES)
BLOCK_RGBA = ((0.85, 0.12, 0.1, 1.0), (0.15, 0.7, 0.2, 1.0), (0.15, 0.3, 0.9, 1.0),
              (0.95, 0.85, 0.1, 1.0))
BLOCK_HALF_SIZE = np.array([0.1, 0.1, 0.03], np.float32)
"""Half extents (m) of a block: 0.2 x 0.2 x 0.06 m, Diffuser's cuboid."""
BLOCK_MASS = 0.068
BLOCK_RADIUS = 0.6
"""Blocks start flat with their centres this far (m) from the arm's base."""

TIMESTEP = 0.005
FRICTION = 0.8

LINK_OFFSETS = (0.1575, 0.2025, 0.2045, 0.2155, 0.1845, 0.2155, 0.081)
"""z offset (m) of joint k+1's frame in its parent's frame; joint 1 sits at z = 0.1575."""
FLANGE_OFFSET = 0.045
JOINT_AXES = ("z", "y", "z", "y", "z", "y", "z")
JOINT_LIMITS = np.array([2.967, 2.094, 2.967, 2.094, 2.967, 2.094, 3.054], np.float32)
NUM_JOINTS = 7
LINK_MASSES = (1.5, 1.5, 1.0, 1.0, 0.8, 0.6, 0.3)
"""Link masses (kg): lighter than the real iiwa14 (whose links weigh 1-6 kg); with gravity
compensation and no arm collisions they only set how fast the servos settle."""
KP = 4000.0
JOINT_DAMPING = 50.0
ARMATURE = 0.2

HOME_QPOS = np.array([0.0, 0.35, 0.0, 1.45, 0.0, 1.34, 0.0], np.float32)
"""The arm's configuration at reset: leaning forward over +x, the flange pointing down."""


def _link_xml(k: int) -> tuple[str, str]:
    """(opening, closing) XML of link k+1 (body, hinge joint, capsule, inertial)."""
    axis = {"x": "1 0 0", "y": "0 1 0", "z": "0 0 1"}[JOINT_AXES[k]]
    length = LINK_OFFSETS[k + 1] if k + 1 < NUM_JOINTS else FLANGE_OFFSET
    mass = LINK_MASSES[k]
    inertia = max(mass * (3 * 0.06 ** 2 + length ** 2) / 12, 1e-3)
    lim = JOINT_LIMITS[k]
    opening = (
        f'<body name="link{k + 1}" pos="0 0 {LINK_OFFSETS[k]}" gravcomp="1">\n'
        f'  <joint name="joint{k + 1}" axis="{axis}" range="{-lim} {lim}"/>\n'
        f'  <inertial pos="0 0 {length / 2:.4f}" mass="{mass}" '
        f'diaginertia="{inertia:.5f} {inertia:.5f} {max(mass * 0.06 ** 2 / 2, 1e-3):.5f}"/>\n'
        f'  <geom class="arm" fromto="0 0 0 0 0 {length}" size="{0.06 - 0.004 * k:.3f}"/>\n')
    return opening, "</body>\n"


def scene_xml() -> str:
    """The scene's MJCF text."""
    hx, hy, hz = (float(v) for v in BLOCK_HALF_SIZE)
    blocks, welds = [], []
    for i, (name, rgba) in enumerate(zip(BLOCK_NAMES, BLOCK_RGBA)):
        x = BLOCK_RADIUS * np.cos(i * np.pi / 2)
        y = BLOCK_RADIUS * np.sin(i * np.pi / 2)
        blocks.append(
            f'<body name="block_{name}" pos="{x:.4f} {y:.4f} {hz}">\n'
            f'  <freejoint name="block_{name}"/>\n'
            f'  <geom name="block_{name}" class="block" size="{hx} {hy} {hz}" '
            f'rgba="{" ".join(str(c) for c in rgba)}"/>\n'
            f'</body>\n')
        # relpose: body2's pose in body1's frame: the block centre hz along the flange's z
        # (which points down while grasping), the block turned by pi about y.
        welds.append(f'<weld name="suction_{name}" body1="flange" body2="block_{name}" '
                     f'relpose="0 0 {hz} 0 0 1 0" active="false"/>\n')
    arm_open, arm_close = zip(*(_link_xml(k) for k in range(NUM_JOINTS)))
    flange = ('<body name="flange" pos="0 0 {:.4f}" gravcomp="1">\n'
              '  <inertial pos="0 0 0" mass="0.05" diaginertia="1e-4 1e-4 1e-4"/>\n'
              '  <geom class="arm" type="cylinder" size="0.03 0.005" rgba="0.2 0.2 0.2 1"/>\n'
              '  <site name="suction" pos="0 0 0" size="0.01"/>\n'
              '</body>\n').format(FLANGE_OFFSET)
    actuators = "".join(
        f'<position name="servo{k + 1}" joint="joint{k + 1}" kp="{KP}" '
        f'ctrlrange="{-JOINT_LIMITS[k]} {JOINT_LIMITS[k]}"/>\n' for k in range(NUM_JOINTS))
    return f"""<mujoco model="kuka_blocks">
<compiler angle="radian" autolimits="true"/>
<option timestep="{TIMESTEP}" solver="Newton" iterations="8" ls_iterations="8" cone="pyramidal"
        integrator="Euler">
  <flag eulerdamp="disable"/>
</option>
<visual><global offwidth="640" offheight="480"/><headlight ambient="0.3 0.3 0.3"/></visual>
<default>
  <default class="arm">
    <geom type="capsule" contype="0" conaffinity="0" rgba="0.9 0.5 0.1 1" density="0"/>
    <joint damping="{JOINT_DAMPING}" armature="{ARMATURE}"/>
  </default>
  <default class="block">
    <geom type="box" contype="1" conaffinity="1" condim="3" friction="{FRICTION} 0.005 0.0001"
          mass="{BLOCK_MASS}"/>
  </default>
</default>
<asset>
  <texture name="grid" type="2d" builtin="checker" rgb1="0.55 0.6 0.65" rgb2="0.45 0.5 0.55"
           width="300" height="300"/>
  <material name="grid" texture="grid" texrepeat="8 8" reflectance="0.05"/>
</asset>
<worldbody>
<light pos="0 0 3" dir="0 0 -1" diffuse="0.7 0.7 0.7"/>
<light pos="1.5 -1.5 2.5" dir="-0.5 0.5 -1" diffuse="0.5 0.5 0.5"/>
<geom name="floor" type="plane" size="2 2 0.05" material="grid" contype="1" conaffinity="1"
      condim="3" friction="{FRICTION} 0.005 0.0001"/>
<camera name="top" pos="0 0 2.6" xyaxes="1 0 0 0 1 0" fovy="45"/>
<camera name="side" pos="1.35 -1.35 1.25" xyaxes="0.707 0.707 0 -0.37 0.37 0.85" fovy="55"/>
<body name="base" childclass="arm">
<geom class="arm" type="cylinder" size="0.09 0.02" pos="0 0 0.02" rgba="0.3 0.3 0.3 1"/>
{"".join(arm_open)}{flange}{"".join(arm_close)}</body>
{"".join(blocks)}</worldbody>
<equality>
{"".join(welds)}</equality>
<actuator>
{actuators}</actuator>
</mujoco>
"""


@functools.lru_cache(maxsize=None)
def mj_model():
    """The compiled mujoco.MjModel (cached; treat as read-only)."""
    import mujoco

    return mujoco.MjModel.from_xml_string(scene_xml())
