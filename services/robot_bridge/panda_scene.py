"""A hermetic, mesh-free MuJoCo model of the Franka Emika Panda plus one articulated object.

The kinematic tree, inertials, joint ranges, joint armature (0.1 kg m^2) and joint damping
(1 N m s/rad) are copied from MuJoCo Menagerie's ``franka_emika_panda/panda.xml`` (Copyright
Google DeepMind, Apache License 2.0; see the NOTICE file at the repository root). Meshes are
replaced by capsules that neither collide nor add mass; the fingers are welded to the hand
(their mass is kept). Actuators are plain ``motor`` torques limited to Franka's joint torque
limits. Nothing is read from disk or downloaded: the XML is generated here.

Frames (all metres, radians): the world frame is the robot base frame ``base`` (Panda link0).
The ``tcp`` body sits at Franka's default end-effector frame: flange + 0.1034 m along z, hand
rotated -45 deg about z (libfranka's ``F_T_EE``). Its centre of mass and the ``tcp`` site are at
that point, so a force in ``xfrc_applied`` acts exactly at the TCP. The object is a body with a
``hinge`` (revolute) or ``slide`` (prismatic) joint; its child ``handle`` has its centre of mass
at the grasp point, oriented like the TCP at grasp time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import check_pose, quat_wxyz_from_matrix

Array = NDArray[np.float64]

# --- Franka limits (libfranka / Franka documentation, FER "Panda") ---
TAU_MAX_NM = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
TAU_RATE_MAX_NM_PER_S = 1000.0
Q_MIN_RAD = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
Q_MAX_RAD = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
DQ_MAX_RAD_PER_S = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
# libfranka F_T_EE of the Franka Hand: 0.1034 m along the flange z, -45 deg about z.
FLANGE_TO_TCP_M = 0.1034
# Grasp configuration: TCP about 27 deg below horizontal, q7 near its lower limit so a +180 deg
# turn about the approach axis fits in joint 7's range (docs/robot_bridge.md#grasp-configuration).
Q_GRASP_RAD = np.array([0.0, -0.3, 0.0, -2.4, 0.0, 3.3, -2.35])

# Menagerie panda.xml: (name, pos, quat wxyz, mass, CoM, fullinertia Ixx Iyy Izz Ixy Ixz Iyz, range)
_LINKS: tuple[tuple[str, tuple[float, ...], tuple[float, ...], float, tuple[float, ...],
                    tuple[float, ...], tuple[float, float]], ...] = (
    ("link1", (0, 0, 0.333), (1, 0, 0, 0), 4.970684, (0.003875, 0.002081, -0.04762),
     (0.70337, 0.70661, 0.0091170, -0.00013900, 0.0067720, 0.019169), (-2.8973, 2.8973)),
    ("link2", (0, 0, 0), (1, -1, 0, 0), 0.646926, (-0.003141, -0.02872, 0.003495),
     (0.0079620, 2.8110e-2, 2.5995e-2, -3.925e-3, 1.0254e-2, 7.04e-4), (-1.7628, 1.7628)),
    ("link3", (0, -0.316, 0), (1, 1, 0, 0), 3.228604, (2.7518e-2, 3.9252e-2, -6.6502e-2),
     (3.7242e-2, 3.6155e-2, 1.083e-2, -4.761e-3, -1.1396e-2, -1.2805e-2), (-2.8973, 2.8973)),
    ("link4", (0.0825, 0, 0), (1, 1, 0, 0), 3.587895, (-5.317e-2, 1.04419e-1, 2.7454e-2),
     (2.5853e-2, 1.9552e-2, 2.8323e-2, 7.796e-3, -1.332e-3, 8.641e-3), (-3.0718, -0.0698)),
    ("link5", (-0.0825, 0.384, 0), (1, -1, 0, 0), 1.225946, (-1.1953e-2, 4.1065e-2, -3.8437e-2),
     (3.5549e-2, 2.9474e-2, 8.627e-3, -2.117e-3, -4.037e-3, 2.29e-4), (-2.8973, 2.8973)),
    ("link6", (0, 0, 0), (1, 1, 0, 0), 1.666555, (6.0149e-2, -1.4117e-2, -1.0517e-2),
     (1.964e-3, 4.354e-3, 5.433e-3, 1.09e-4, -1.158e-3, 3.41e-4), (-0.0175, 3.7525)),
    ("link7", (0.088, 0, 0), (1, 1, 0, 0), 7.35522e-01, (1.0517e-2, -4.252e-3, 6.1597e-2),
     (1.2516e-2, 1.0027e-2, 4.815e-3, -4.28e-4, -1.196e-3, -7.41e-4), (-2.8973, 2.8973)),
)
_LINK0 = (0.629769, (-0.041018, -0.00014, 0.049974),
          (0.00315, 0.00388, 0.004285, 8.2904e-7, 0.00015, 8.2299e-6))
_HAND = (0.73, (-0.01, 0.0, 0.03), (0.001, 0.0025, 0.0017))  # diaginertia
_FINGER = (0.015, (2.375e-6, 2.375e-6, 7.5e-7))  # each, at hand z = 0.0584
_ARMATURE = 0.1
_DAMPING = 1.0
# Capsule segments (from, to) per body for the visual, in that body's frame; purely cosmetic.
_VISUAL: dict[str, tuple[tuple[float, float, float], tuple[float, float, float], float]] = {
    "link0": ((0, 0, 0.0), (0, 0, 0.25), 0.06),
    "link1": ((0, 0, -0.15), (0, 0, 0.0), 0.06),
    "link2": ((0, 0, 0), (0, -0.3, 0), 0.06),
    "link3": ((0, 0, -0.1), (0.08, 0, 0), 0.05),
    "link4": ((0, 0, 0), (-0.08, 0.12, 0), 0.05),
    "link5": ((0, 0, -0.25), (0, 0.05, -0.05), 0.045),
    "link6": ((0, 0, 0), (0.088, 0, 0), 0.04),
    "link7": ((0, 0, 0), (0, 0, 0.1), 0.04),
}


@dataclass(frozen=True)
class ObjectSpec:
    """An articulated object in the robot base frame (metres, radians, SI dynamics).

    ``axis_base`` unit joint axis; ``point_base`` a point on the revolute axis (prismatic: on the
    sliding line). ``T_base_handle`` is the grasp pose: the handle body's frame, whose origin is
    the grasp point and whose orientation equals the TCP's at grasp. ``range`` limits the joint
    (None: unlimited). Positive joint values rotate (right hand) about / slide along the axis.
    """

    name: str
    joint_type: Literal["revolute", "prismatic"]
    axis_base: Array
    point_base: Array
    T_base_handle: Array
    range: tuple[float, float] | None = None
    damping: float = 0.2         # N m s/rad or N s/m
    frictionloss: float = 0.3    # N m or N
    armature: float = 1e-3       # kg m^2 or kg (reflected inertia; keeps the grasp spring stable)
    handle_mass_kg: float = 0.05

    def __post_init__(self) -> None:
        if self.joint_type not in ("revolute", "prismatic"):
            raise ValueError(f"joint_type must be revolute or prismatic, got {self.joint_type!r}")
        a = np.asarray(self.axis_base, float)
        if a.shape != (3,) or abs(float(np.linalg.norm(a)) - 1.0) > 1e-6:
            raise ValueError(f"axis_base must be a unit 3-vector, got {a}")
        if (problem := check_pose(self.T_base_handle)) is not None:
            raise ValueError(f"T_base_handle must be a 4x4 rigid transform: {problem}")

    @property
    def lever_m(self) -> float:
        """Distance from the grasp point to the revolute axis (0 for prismatic)."""
        if self.joint_type == "prismatic":
            return 0.0
        d = self.T_base_handle[:3, 3] - self.point_base
        return float(np.linalg.norm(d - (d @ self.axis_base) * self.axis_base))


def _fmt(v: object) -> str:
    return " ".join(f"{float(x):.9g}" for x in v)  # type: ignore[attr-defined]


def _quat_fmt(R: Array) -> str:
    return _fmt(quat_wxyz_from_matrix(R))


def _arm_xml() -> str:
    """The Panda bodies from link0 to the tcp, nested."""
    m0, c0, i0 = _LINK0
    lines = ['<body name="link0">',
             f'<inertial mass="{m0}" pos="{_fmt(c0)}" fullinertia="{_fmt(i0)}"/>',
             _capsule("link0")]
    for name, pos, quat, mass, com, inertia, rng in _LINKS:
        lines += [f'<body name="{name}" pos="{_fmt(pos)}" quat="{_fmt(quat)}">',
                  f'<inertial mass="{mass}" pos="{_fmt(com)}" fullinertia="{_fmt(inertia)}"/>',
                  f'<joint name="joint{name[-1]}" range="{rng[0]} {rng[1]}"/>',
                  _capsule(name)]
    hm, hc, hi = _HAND
    fm, fi = _FINGER
    cz = math.cos(-math.pi / 8.0)
    sz = math.sin(-math.pi / 8.0)
    lines += [
        '<body name="link8" pos="0 0 0.107">',
        f'<body name="hand" quat="{cz:.9g} 0 0 {sz:.9g}">',
        f'<inertial mass="{hm}" pos="{_fmt(hc)}" diaginertia="{_fmt(hi)}"/>',
        '<geom type="box" size="0.02 0.1 0.025" pos="0 0 0.03" rgba="0.9 0.9 0.9 1"/>',
        '<body name="left_finger" pos="0 0 0.0584">',
        f'<inertial mass="{fm}" pos="0 0 0" diaginertia="{_fmt(fi)}"/>',
        '<geom type="box" size="0.01 0.005 0.025" pos="0 0.01 0.025" rgba="0.3 0.3 0.3 1"/>',
        '</body>',
        '<body name="right_finger" pos="0 0 0.0584" quat="0 0 0 1">',
        f'<inertial mass="{fm}" pos="0 0 0" diaginertia="{_fmt(fi)}"/>',
        '<geom type="box" size="0.01 0.005 0.025" pos="0 0.01 0.025" rgba="0.3 0.3 0.3 1"/>',
        '</body>',
        f'<body name="tcp" pos="0 0 {FLANGE_TO_TCP_M}">',
        '<inertial mass="0.001" pos="0 0 0" diaginertia="1e-7 1e-7 1e-7"/>',
        '<site name="tcp" size="0.005" rgba="1 0 0 1"/>',
        '</body>',
        '</body>',  # hand
        '</body>',  # link8
    ]
    lines += ["</body>"] * (len(_LINKS) + 1)
    return "\n".join(lines)


def _capsule(body: str) -> str:
    a, b, r = _VISUAL[body]
    return f'<geom type="capsule" fromto="{_fmt(a)} {_fmt(b)}" size="{r}" rgba="0.95 0.95 0.95 1"/>'


def _object_xml(obj: ObjectSpec) -> str:
    """Object base at the axis point (world-aligned), joint, and the handle at the grasp."""
    c = np.asarray(obj.point_base, float)
    T = np.asarray(obj.T_base_handle, float)
    kind = "hinge" if obj.joint_type == "revolute" else "slide"
    limit = ("" if obj.range is None
             else f' limited="true" range="{obj.range[0]:.9g} {obj.range[1]:.9g}"')
    m = obj.handle_mass_kg
    inertia = 0.4 * m * 0.01**2  # a 1 cm ball
    rel = T[:3, 3] - c
    lever = (f'<geom type="capsule" fromto="0 0 0 {_fmt(rel)}" size="0.006" rgba="0.8 0.6 0.2 1"/>'
             if float(np.linalg.norm(rel)) > 1e-3
             else '<geom type="sphere" size="0.01" rgba="0.8 0.6 0.2 1"/>')
    return "\n".join([
        f'<body name="object" pos="{_fmt(c)}">',
        f'<joint name="object_joint" type="{kind}" axis="{_fmt(obj.axis_base)}"'
        f' damping="{obj.damping}" frictionloss="{obj.frictionloss}" armature="{obj.armature}"'
        f'{limit}/>',
        lever,
        f'<body name="handle" pos="{_fmt(rel)}" quat="{_quat_fmt(T[:3, :3])}">',
        f'<inertial mass="{m}" pos="0 0 0" diaginertia="{inertia} {inertia} {inertia}"/>',
        '<site name="handle" size="0.006" rgba="0 0 1 1"/>',
        '</body>',
        '</body>',
    ])


def scene_xml(obj: ObjectSpec | None, timestep_s: float = 0.001) -> str:
    """MJCF text of the Panda (torque motors within Franka's limits) and ``obj``."""
    motors = "\n".join(
        f'<motor name="motor{i + 1}" joint="joint{i + 1}" ctrllimited="true"'
        f' ctrlrange="{-t} {t}"/>' for i, t in enumerate(TAU_MAX_NM))
    return f"""<mujoco model="panda_articulation">
<compiler angle="radian" autolimits="true"/>
<option timestep="{timestep_s}" integrator="implicitfast" gravity="0 0 -9.81"/>
<default>
  <joint armature="{_ARMATURE}" damping="{_DAMPING}" axis="0 0 1"/>
  <geom contype="0" conaffinity="0" group="2"/>
</default>
<worldbody>
<light name="top" pos="0 0 2"/>
{_arm_xml()}
{_object_xml(obj) if obj is not None else ""}
</worldbody>
<actuator>
{motors}
</actuator>
</mujoco>
"""
