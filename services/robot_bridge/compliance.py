"""Model-aware Cartesian stiffness: soft where the joint model is unsure, stiff along the motion.

For a revolute joint with unit axis ``a`` and axis point ``f`` nearest the grasp, at commanded
progress ``theta``, with lever ``r = |p - f|`` and radial unit ``u`` (base frame, SI units):

- translation: stiff (today's ``k_t``) along the admissible tangent ``a x u``; along the radial
  ``u`` and the axial ``a`` directions ``k = k_t / (1 + (sigma_t / SIGMA_REF_M)^2)`` with
  ``sigma_t^2 = sigma_pos^2 + (2 sin(theta/2) r sigma_dir)^2`` (the grasp-position error an
  axis-position 1-sigma ``sigma_pos`` and a direction 1-sigma ``sigma_dir`` cause after turning
  by ``theta``). With the grasp on the axis (``r`` below ``MIN_LEVER_M``, the key) there is no
  tangent and every translation is soft;
  The belief's 1-sigmas are combined (root sum of squares) with how far the executed joint still
  is from the belief (angle; distance at the grasp), so stiffness returns only once the re-planned
  path has caught up with the refined model;
- rotation: stiff (today's ``k_r``) about the axis; about the two axes orthogonal to it
  ``k = k_r / (1 + (sigma_r / SIGMA_REF_RAD)^2)`` with ``sigma_r = 2 sin(theta/2) sigma_dir``.

Bounds: every stiffness lies in ``[floor, today's]``: never stiffer than the configured gains,
never softer than ``MIN_TRANSLATIONAL_N_PER_M`` / ``MIN_ROTATIONAL_NM_PER_RAD`` (the arm still
tracks within the tracking-error bound against the joint's friction). Damping follows as
``D = V diag(2 zeta sqrt(k)) V^T`` (rotation: ``sqrt(2 k)``, panda-py's convention, see
:mod:`services.robot_bridge.controller`). The force, torque and tracking limits are unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.robot_bridge.controller import ImpedanceGains

Array = NDArray[np.float64]


@dataclass(frozen=True)
class AxisBelief:
    """A revolute axis in the base frame at the grasp: unit ``axis``, ``foot`` the axis point
    nearest the grasp (m), ``cov`` 5x5 of ``(b1, b2, foot)`` with ``b`` in ``tangent_basis(axis)``."""

    axis: Array
    foot: Array
    cov: Array

    def direction_std(self) -> float:
        return math.sqrt(max(float(np.linalg.eigvalsh(self.cov[:2, :2]).max()), 0.0))

    def position_std(self) -> float:
        return math.sqrt(max(float(np.linalg.eigvalsh(self.cov[2:, 2:]).max()), 0.0))

SIGMA_REF_M = 0.003                  # grasp-position 1-sigma that halves the stiffness
SIGMA_REF_RAD = math.radians(2.0)    # orientation 1-sigma that halves the stiffness
MIN_TRANSLATIONAL_N_PER_M = 250.0
MIN_ROTATIONAL_NM_PER_RAD = 12.5
MIN_LEVER_M = 0.005


@dataclass(frozen=True)
class MatrixGains:
    """Full 6x6 Cartesian stiffness and damping (base frame, linear first) and the null-space
    spring: what :func:`services.robot_bridge.controller.impedance_torque` needs of gains."""

    stiffness: Array
    damping: Array
    nullspace_nm_per_rad: float
    nullspace_damping: float
    damping_ratio: float

    def lerp(self, other: MatrixGains, w: float) -> MatrixGains:
        """``(1 - w) self + w other`` (both symmetric positive definite, so is the result)."""
        return MatrixGains((1.0 - w) * self.stiffness + w * other.stiffness,
                           (1.0 - w) * self.damping + w * other.damping,
                           self.nullspace_nm_per_rad, self.nullspace_damping, self.damping_ratio)


class ComplianceLaw:
    """The module's stiffness law around today's ``gains`` (its upper bound)."""

    def __init__(self, gains: ImpedanceGains) -> None:
        self.base = gains
        self.k_t = gains.translational_n_per_m
        self.k_r = gains.rotational_nm_per_rad
        self.min_t = min(MIN_TRANSLATIONAL_N_PER_M, self.k_t)
        self.min_r = min(MIN_ROTATIONAL_NM_PER_RAD, self.k_r)

    def stiffnesses(self, axis: Array, foot: Array, grasp: Array, belief: AxisBelief,
                    theta: float) -> tuple[Array, Array, Array, Array]:
        """Translational and rotational principal stiffnesses (3,) and their directions (3x3
        columns, base frame) at progress ``theta`` (rad) of a grasp that started at ``grasp``."""
        from services.common.se3 import so3_exp

        a = axis / np.linalg.norm(axis)
        d = grasp - foot
        d = d - float(d @ a) * a
        r = float(np.linalg.norm(d))
        chord = 2.0 * abs(math.sin(0.5 * theta))
        # The executed joint still on its way to the belief counts as uncertainty too.
        turn = math.acos(max(-1.0, min(1.0, abs(float(a @ belief.axis)))))
        s_dir = math.hypot(belief.direction_std(), turn)
        s_pos = math.hypot(belief.position_std(), float(np.linalg.norm(
            _perp(foot - belief.foot, a))))
        s_t = math.hypot(s_pos, chord * r * s_dir)
        s_r = chord * s_dir
        k_soft_t = max(self.min_t, self.k_t / (1.0 + (s_t / SIGMA_REF_M) ** 2))
        k_soft_r = max(self.min_r, self.k_r / (1.0 + (s_r / SIGMA_REF_RAD) ** 2))
        if r >= MIN_LEVER_M:
            u = so3_exp(theta * a) @ (d / r)
            k_tangent = self.k_t
        else:
            u = _any_orthogonal(a)
            k_tangent = k_soft_t
        V = np.column_stack([u, np.cross(a, u), a])
        k_trans = np.array([k_soft_t, k_tangent, k_soft_t])
        k_rot = np.array([k_soft_r, k_soft_r, self.k_r])
        return k_trans, V, k_rot, V

    def gains(self, axis: Array, foot: Array, grasp: Array, belief: AxisBelief,
              theta: float) -> MatrixGains:
        """:class:`MatrixGains` of the law at progress ``theta`` (see the module docstring)."""
        k_t, V, k_r, _ = self.stiffnesses(axis, foot, grasp, belief, theta)
        z = self.base.damping_ratio
        K = np.zeros((6, 6))
        D = np.zeros((6, 6))
        K[:3, :3] = (V * k_t) @ V.T
        K[3:, 3:] = (V * k_r) @ V.T
        D[:3, :3] = (V * (2.0 * z * np.sqrt(k_t))) @ V.T
        D[3:, 3:] = (V * (2.0 * z * np.sqrt(2.0 * k_r))) @ V.T
        return MatrixGains(K, D, self.base.nullspace_nm_per_rad, self.base.nullspace_damping, z)


def _perp(v: Array, a: Array) -> Array:
    return v - float(v @ a) * a


def _any_orthogonal(a: Array) -> Array:
    v = np.cross(a, [1.0, 0.0, 0.0])
    if np.linalg.norm(v) < 0.1:
        v = np.cross(a, [0.0, 1.0, 0.0])
    return v / np.linalg.norm(v)
