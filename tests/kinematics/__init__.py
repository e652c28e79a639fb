"""Tests of ``services.kinematics``; this module also holds the synthetic joint demonstrations.

A demonstration is a list of ``(stamp_ns, T_frame_hand, pose_covariance)`` at ``rate_hz``: the hand
starts at ``T_ref`` and moves as ``T(t) = Exp(q(t) * screw) @ T_ref`` with a minimum-jerk profile
``q(t)`` from 0 to ``q_max`` (after an optional rest). Noise, when asked for, is applied about the
hand origin (position noise ``sigma_t`` [m] per axis, rotation noise ``sigma_r`` [rad] per axis) and
the covariance given to the estimator is the matching left-perturbation covariance in the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import se3_adjoint, se3_exp, so3_exp

Array = NDArray[np.float64]

Sample = tuple[int, Array, Array]


@dataclass(frozen=True)
class Joint:
    """Ground truth: ``kind`` in {"rigid", "prismatic", "revolute"}, unit axis, axis point, T_ref."""

    kind: str
    axis: Array
    point: Array
    T_ref: Array

    def screw(self) -> Array:
        s = np.zeros(6)
        if self.kind == "prismatic":
            s[:3] = self.axis
        elif self.kind == "revolute":
            s[:3] = np.cross(self.point, self.axis)
            s[3:] = self.axis
        return s

    def closest_point(self) -> Array:
        return self.point - float(self.point @ self.axis) * self.axis

    def pose(self, q: float) -> Array:
        return se3_exp(q * self.screw()) @ self.T_ref


def unit(v: Array) -> Array:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def orthogonal(u: Array) -> Array:
    """A unit vector orthogonal to ``u``."""
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    return unit(np.cross(u, a))


def revolute_joint(axis: Array, point: Array, radius_m: float, *, along_m: float = 0.0,
                   hand_rotvec: Array | None = None, direction: Array | None = None) -> Joint:
    """Revolute joint with the hand origin ``radius_m`` from the axis line."""
    u = unit(axis)
    n = orthogonal(u) if direction is None else unit(direction - (direction @ u) * u)
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.3, -0.5, 0.2]) if hand_rotvec is None else hand_rotvec)
    T[:3, 3] = np.asarray(point, float) + radius_m * n + along_m * u
    return Joint("revolute", u, np.asarray(point, float), T)


def prismatic_joint(axis: Array, start: Array, hand_rotvec: Array | None = None) -> Joint:
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.1, 0.4, -0.3]) if hand_rotvec is None else hand_rotvec)
    T[:3, 3] = start
    return Joint("prismatic", unit(axis), np.zeros(3), T)


def min_jerk(s: Array) -> Array:
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s)


def demo(joint: Joint, q_max: float, *, duration_s: float = 2.0, rest_s: float = 0.0,
         hold_s: float = 0.0, rate_hz: float = 30.0, sigma_t: float = 0.0, sigma_r: float = 0.0,
         cov_exact: float = 1e-6, seed: int = 0, t0_ns: int = 1_000_000_000) -> list[Sample]:
    """Samples of a demonstration (see module docstring). Exact when both sigmas are 0."""
    rng = np.random.default_rng(seed)
    n = round((rest_s + duration_s + hold_s) * rate_hz) + 1
    out: list[Sample] = []
    for k in range(n):
        t = k / rate_hz
        q = q_max * float(min_jerk(np.array((t - rest_s) / duration_s)))
        T = joint.pose(q)
        if sigma_t > 0.0 or sigma_r > 0.0:
            T = T.copy()
            T[:3, :3] = so3_exp(rng.normal(0.0, sigma_r, 3)) @ T[:3, :3]
            T[:3, 3] += rng.normal(0.0, sigma_t, 3)
            Tt = np.eye(4)
            Tt[:3, 3] = T[:3, 3]
            A = se3_adjoint(Tt)
            body = np.diag([sigma_t**2] * 3 + [sigma_r**2] * 3)
            cov = A @ body @ A.T
        else:
            cov = cov_exact * np.eye(6)
        out.append((t0_ns + round(t * 1e9), T, cov))
    return out


def angle_between(a: Array, b: Array) -> float:
    """Angle between two lines (sign-agnostic) [rad]."""
    c = abs(float(unit(a) @ unit(b)))
    return float(np.arccos(min(1.0, c)))
