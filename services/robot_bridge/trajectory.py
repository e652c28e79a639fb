"""Cartesian articulation trajectories from a kinematic model and the grasp pose.

The model arrives in its ``frame_id`` ("camera", or "world" for a moving camera) and is moved
into the robot base frame with that frame's calibration (``T_base_camera`` / ``T_base_world``,
see :meth:`~services.robot_bridge.config.RobotBridgeConfig.base_T_frame`). From the
end-effector (TCP) pose at grasp ``(p0, R0)`` and a minimum-jerk joint profile ``theta(t)`` from
0 to ``amount``:

- revolute (unit axis ``a`` through ``c``): ``p = c + R(a, theta) (p0 - c)``,
  ``R = R(a, theta) R0``, ``w = theta_dot a``, ``v = w x (p - c)``;
- prismatic (unit axis ``a``): ``p = p0 + s a``, ``R = R0``, ``v = s_dot a``, ``w = 0``.

Positive ``amount`` turns right-handed about / slides along the model's axis. Poses are 4x4
``T_base_ee`` (m), twists ``[v, w]`` (m/s, rad/s) in the base frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import KinematicModel
from services.common.se3 import so3_exp_fast
from services.robot_bridge.safety import Refusal

Array = NDArray[np.float64]

# Panda reach: shoulder (joint 2) height and the longest distance from it to the TCP [m].
SHOULDER_BASE_M = np.array([0.0, 0.0, 0.333])
MAX_REACH_M = 0.80  # 0.316 + 0.384 + 0.088 + 0.107 + 0.1034, less a margin for the elbow offsets
MIN_TCP_HEIGHT_M = 0.02
_EYE4 = np.eye(4)


@dataclass(frozen=True)
class JointInBase:
    """A joint in the robot base frame: unit ``axis``, ``point`` on it (m)."""

    joint_type: str
    axis: Array
    point: Array


def joint_in_base(model: KinematicModel, T_base_frame: Array) -> JointInBase:
    """The model's most probable joint moved from its frame into the base frame with
    ``T_base_frame``, the calibration of the model's ``frame_id``.

    Raises ``ValueError`` when the model carries no revolute/prismatic parameters for its type.
    """
    R, t = T_base_frame[:3, :3], T_base_frame[:3, 3]
    if model.type == "revolute" and model.revolute is not None:
        axis = R @ np.asarray(model.revolute.axis, float)
        point = R @ np.asarray(model.revolute.point, float) + t
        return JointInBase("revolute", axis / np.linalg.norm(axis), point)
    if model.type == "prismatic" and model.prismatic is not None:
        axis = R @ np.asarray(model.prismatic.axis, float)
        point = R @ np.asarray(model.reference_pose, float)[:3, 3] + t
        return JointInBase("prismatic", axis / np.linalg.norm(axis), point)
    raise ValueError(f"model type {model.type!r} has no joint to articulate")


def min_jerk(t: float, duration_s: float) -> tuple[float, float]:
    """Minimum-jerk progress ``s`` in [0, 1] and its rate ``ds/dt`` (1/s) at time ``t``."""
    if t <= 0.0:
        return 0.0, 0.0
    if t >= duration_s:
        return 1.0, 0.0
    x = t / duration_s
    x2 = x * x
    s = x2 * x * (10.0 - 15.0 * x + 6.0 * x2)
    ds = 30.0 * x2 * (1.0 - 2.0 * x + x2) / duration_s
    return s, ds


# Peak of ds/dt of the minimum-jerk profile, times the duration (at t = T/2).
MIN_JERK_PEAK_RATE = 1.875


def cross3(a: Array, b: Array) -> Array:
    """``a x b`` for 3-vectors (``np.cross`` costs ~30 us of argument handling per call)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


@dataclass(frozen=True)
class ArticulationPlan:
    """A minimum-jerk articulation of ``amount`` (rad or m) over ``duration_s``, then a hold."""

    joint: JointInBase
    T_base_grasp: Array
    amount: float
    duration_s: float
    hold_s: float = 0.5

    @property
    def total_s(self) -> float:
        return self.duration_s + self.hold_s

    def sample(self, t: float) -> tuple[Array, Array, float]:
        """Target pose (4, 4), feed-forward twist (6,) and joint progress (rad or m) at ``t``."""
        s, ds = min_jerk(t, self.duration_s)
        theta, dtheta = s * self.amount, ds * self.amount
        a = self.joint.axis
        T0 = self.T_base_grasp
        T = _EYE4.copy()
        twist = np.zeros(6)
        if self.joint.joint_type == "revolute":
            Ra = so3_exp_fast(theta * a)
            c = self.joint.point
            T[:3, 3] = c + Ra @ (T0[:3, 3] - c)
            T[:3, :3] = Ra @ T0[:3, :3]
            w = dtheta * a
            twist[3:] = w
            twist[:3] = cross3(w, T[:3, 3] - c)
        else:
            T[:3, 3] = T0[:3, 3] + theta * a
            T[:3, :3] = T0[:3, :3]
            twist[:3] = dtheta * a
        return T, twist, theta

    def peak_speeds(self) -> tuple[float, float]:
        """Peak linear (m/s) and angular (rad/s) TCP speeds of the plan."""
        rate = MIN_JERK_PEAK_RATE * abs(self.amount) / self.duration_s
        if self.joint.joint_type == "prismatic":
            return rate, 0.0
        d = self.T_base_grasp[:3, 3] - self.joint.point
        r = float(np.linalg.norm(d - (d @ self.joint.axis) * self.joint.axis))
        return rate * r, rate

    def positions(self, n: int = 50) -> Array:
        """TCP positions (n, 3) along the plan (for workspace checks)."""
        return np.array([self.sample(t)[0][:3, 3]
                         for t in np.linspace(0.0, self.duration_s, n)])

    def joint7_change(self) -> float:
        """Predicted change of joint 7 (rad): the articulation's rotation about the flange axis.

        Joint 7 turns about the TCP z axis, so a rotation ``theta`` about ``a`` needs about
        ``theta (a . z_tcp)`` of it; the other joints supply the rest.
        """
        if self.joint.joint_type != "revolute":
            return 0.0
        return float(self.amount * (self.joint.axis @ self.T_base_grasp[:3, 2]))

    def progress_from_pose(self, T_base_ee: Array, previous: float = 0.0) -> float:
        """Joint progress (rad or m, signed like ``amount``) implied by an end-effector pose:
        :meth:`progress_from_motion` of the TCP's motion since the grasp pose (the real robot,
        where the object's joint is not measured)."""
        T0 = self.T_base_grasp
        return self.progress_from_motion(T_base_ee[:3, :3] @ T0[:3, :3].T,
                                         T_base_ee[:3, 3] - T0[:3, 3], previous)

    def progress_from_motion(self, R_moved: Array, displacement: Array,
                             previous: float = 0.0) -> float:
        """Joint progress (rad or m, signed like ``amount``) of a rigid motion of the grasp.

        ``R_moved`` (3x3) is the rotation since the grasp pose (base frame, applied on the
        left), ``displacement`` (3,) that of the grasp point [m]. Revolute: the rotation
        projected on the axis (the twist angle of a swing-twist decomposition), unwrapped to
        the branch nearest ``previous``; prismatic: the displacement along the axis.
        """
        a = self.joint.axis
        if self.joint.joint_type == "prismatic":
            return float(displacement @ a)
        angle = twist_angle(R_moved, a)
        return angle + 2.0 * math.pi * round((previous - angle) / (2.0 * math.pi))


def twist_angle(R: Array, axis: Array) -> float:
    """Angle in (-pi, pi] of the twist of ``R`` about the unit ``axis`` (swing-twist
    decomposition): ``2 atan2(v . axis, w)`` of its quaternion ``(w, v)`` with ``w >= 0``.

    The quaternion is Shepperd's (largest component as pivot, exact at pi) scaled by its
    positive pivot divisor, which ``atan2`` ignores: no square root (called every control tick).
    """
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = R.tolist()
    trace = m00 + m11 + m22
    if trace >= m00 and trace >= m11 and trace >= m22:
        w, x, y, z = 1.0 + trace, m21 - m12, m02 - m20, m10 - m01
    elif m00 >= m11 and m00 >= m22:
        w, x, y, z = m21 - m12, 1.0 + m00 - m11 - m22, m01 + m10, m02 + m20
    elif m11 >= m22:
        w, x, y, z = m02 - m20, m01 + m10, 1.0 - m00 + m11 - m22, m12 + m21
    else:
        w, x, y, z = m10 - m01, m02 + m20, m12 + m21, 1.0 - m00 - m11 + m22
    ax, ay, az = axis.tolist()
    along = x * ax + y * ay + z * az
    if w < 0.0:
        w, along = -w, -along
    return 2.0 * math.atan2(along, w)


def plan_checks(plan: ArticulationPlan, q7_rad: float, *, max_linear_m_per_s: float,
                max_angular_rad_per_s: float, joint7_limits_rad: tuple[float, float],
                joint7_margin_rad: float) -> Refusal | None:
    """Refuse a plan that is too fast, leaves the workspace, or runs joint 7 out of range."""
    v, w = plan.peak_speeds()
    if v > max_linear_m_per_s or w > max_angular_rad_per_s:
        return Refusal("too_fast", f"peak speed {v:.2f} m/s, {w:.2f} rad/s exceeds "
                                   f"{max_linear_m_per_s} m/s, {max_angular_rad_per_s} rad/s; "
                                   "use a longer duration")
    pts = plan.positions()
    reach = np.linalg.norm(pts - SHOULDER_BASE_M, axis=1)
    if reach.max() > MAX_REACH_M or pts[:, 2].min() < MIN_TCP_HEIGHT_M:
        return Refusal("workspace", f"planned path reaches {reach.max():.2f} m from the shoulder "
                                    f"(limit {MAX_REACH_M} m), lowest point "
                                    f"{pts[:, 2].min():.3f} m: place the object within reach")
    q7_end = q7_rad + plan.joint7_change()
    lo, hi = joint7_limits_rad[0] + joint7_margin_rad, joint7_limits_rad[1] - joint7_margin_rad
    if not lo <= q7_end <= hi:
        return Refusal("joint7_range",
                       f"joint 7 would go from {q7_rad:.2f} to about {q7_end:.2f} rad, outside "
                       f"[{lo:.2f}, {hi:.2f}]; regrasp with the hand turned by 180 deg about the "
                       "approach axis")
    return None


# The paper's pace (sec. IV.C): 180 deg in 6 s; prismatic articulations at 2 cm/s.
SECONDS_PER_HALF_TURN = 6.0
PRISMATIC_SPEED_M_PER_S = 0.02
MIN_DURATION_S = 2.0


def default_duration(amount: float, joint_type: str) -> float:
    """Duration [s] of an articulation of ``amount`` (rad or m) at the paper's pace: 6 s per
    180 deg, 2 cm/s for a prismatic joint, at least 2 s."""
    if joint_type == "revolute":
        return max(MIN_DURATION_S, SECONDS_PER_HALF_TURN * abs(amount) / math.pi)
    return max(MIN_DURATION_S, abs(amount) / PRISMATIC_SPEED_M_PER_S)


def amount_text(amount: float, joint_type: str) -> str:
    """A joint amount for people: degrees for a revolute joint, millimetres for a prismatic one."""
    if joint_type == "revolute":
        return f"{math.degrees(amount):+.1f} deg"
    return f"{amount * 1e3:+.1f} mm"


def flipped_grasp_q7(q7_rad: float, joint7_change_rad: float,
                     joint7_limits_rad: tuple[float, float], margin_rad: float) -> float | None:
    """A joint-7 angle for the grasp (``q7`` or ``q7 +- pi``) from which the turn fits, or None.

    A parallel gripper grasps the same handle turned by pi about its approach axis, so a grasp
    planner may pick whichever branch keeps ``q7 + change`` inside the range.
    """
    lo, hi = joint7_limits_rad[0] + margin_rad, joint7_limits_rad[1] - margin_rad
    for q in (q7_rad, q7_rad + math.pi, q7_rad - math.pi):
        if lo <= q <= hi and lo <= q + joint7_change_rad <= hi:
            return q
    return None
