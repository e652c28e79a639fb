"""The Jacobian-transpose Cartesian impedance law, in numpy, exactly as the real Panda runs it.

On the real robot panda-py's C++ ``CartesianImpedance`` controller computes, at 1 kHz::

    e   = [p - p_d,  -R vec(q^-1 q_d)]                  (vec = quaternion x, y, z)
    tau = J^T (-K e - D J dq) + (I - J^T pinv(J^T)) (k_n (q_n - q) - 2 sqrt(k_n) dq) + coriolis

with ``D = 2 zeta sqrt(K)`` element-wise. :func:`impedance_torque` is that law written with the
sign flipped into the usual "target minus actual" form, plus an optional feed-forward twist
``D v_d`` (panda-py has none; :func:`lead_target` turns the feed-forward into an equivalent
shifted target for it). The rotational error ``2 vec(q_d q^-1)`` equals the rotation vector for
small angles, so the rotational stiffness is given per radian (``k_rot``) and panda-py receives
``2 k_rot`` (its error is the bare quaternion vector, half the angle).

Everything is in the robot base frame: positions in m, rotations as 3x3 matrices, twists
``[v, w]`` (m/s, rad/s, linear first), wrenches ``[f, t]`` (N, N m), torques in N m. Gravity is
not part of the law (the real robot adds it itself; the simulation adds it, see
:mod:`services.robot_bridge.mujoco_backend`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dposv

from services.common.se3 import quat_wxyz_from_matrix, so3_exp

Array = NDArray[np.float64]

_EPS_JJT = 1e-9  # regulariser of J J^T in the null-space projector (well below any eigenvalue)


@dataclass(frozen=True)
class ImpedanceGains:
    """Cartesian impedance (base frame, diagonal) and the null-space posture spring."""

    translational_n_per_m: float = 1000.0
    rotational_nm_per_rad: float = 50.0
    damping_ratio: float = 1.0
    nullspace_nm_per_rad: float = 0.5

    def __post_init__(self) -> None:
        for name in ("translational_n_per_m", "rotational_nm_per_rad", "damping_ratio"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not self.nullspace_nm_per_rad >= 0.0:
            raise ValueError(f"nullspace_nm_per_rad must be >= 0, got {self.nullspace_nm_per_rad}")

    @cached_property
    def stiffness(self) -> Array:
        """Diagonal (6,) of K in the form of :func:`impedance_torque` (N/m, N m/rad)."""
        return np.array([self.translational_n_per_m] * 3 + [self.rotational_nm_per_rad] * 3)

    @cached_property
    def damping(self) -> Array:
        """Diagonal (6,) of D (N s/m, N m s/rad): panda-py's ``2 zeta sqrt(K_panda)``.

        panda-py's rotational stiffness is ``2 k_rot`` (see the module docstring), so its
        rotational damping is ``2 zeta sqrt(2 k_rot)``; the simulation uses the same numbers.
        """
        kt = 2.0 * self.damping_ratio * math.sqrt(self.translational_n_per_m)
        kr = 2.0 * self.damping_ratio * math.sqrt(2.0 * self.rotational_nm_per_rad)
        return np.array([kt] * 3 + [kr] * 3)

    @cached_property
    def nullspace_damping(self) -> float:
        """Null-space damping ``2 sqrt(k_n)`` (N m s/rad), as panda-py."""
        return 2.0 * math.sqrt(self.nullspace_nm_per_rad)

    def panda_py_impedance(self) -> Array:
        """The 6x6 ``impedance`` matrix for panda-py's ``CartesianImpedance``."""
        return np.diag([self.translational_n_per_m] * 3 + [2.0 * self.rotational_nm_per_rad] * 3)


def orientation_error(R_target: Array, R: Array) -> Array:
    """``2 vec(q_d q^-1)`` (3,) in the base frame: the rotation vector for small angles.

    The quaternion of ``R_d R^T`` is taken with ``w >= 0`` (shortest rotation), as panda-py
    flips it. Equals ``2 sin(theta / 2) n`` for the rotation ``theta`` about ``n`` taking the
    current orientation to the target.
    """
    E = R_target @ R.T
    # Shepperd-free form: 4 w^2 = 1 + trace; for w >= 0.5 (|theta| <= 120 deg) use it directly.
    trace = E[0, 0] + E[1, 1] + E[2, 2]
    vee = np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])
    if trace > 0.0:
        w4 = 2.0 * math.sqrt(1.0 + trace)  # 4 w
        return 2.0 * vee / w4
    q = quat_wxyz_from_matrix(E)
    return 2.0 * q[1:]


def impedance_wrench(p_target: Array, R_target: Array, twist_target: Array | None,
                     p: Array, R: Array, twist: Array, gains: ImpedanceGains) -> Array:
    """Task wrench ``K e + D (v_d - v)`` (6,) [N, N m] in the base frame.

    ``gains`` has diagonal (6,) ``stiffness``/``damping`` (:class:`ImpedanceGains`) or full 6x6
    ones (:class:`~services.robot_bridge.compliance.MatrixGains`).
    """
    e = np.empty(6)
    e[:3] = p_target - p
    e[3:] = orientation_error(R_target, R)
    de = -twist if twist_target is None else twist_target - twist
    K, D = gains.stiffness, gains.damping
    if K.ndim == 2:  # full 6x6 gains of the compliance law (services.robot_bridge.compliance)
        return K @ e + D @ de
    return K * e + D * de


def nullspace_torque(J: Array, q: Array, dq: Array, q_nullspace: Array,
                     gains: ImpedanceGains) -> Array:
    """``(I - J^T pinv(J^T)) (k_n (q_n - q) - 2 sqrt(k_n) dq)`` (7,); ``pinv(J^T) = (J J^T)^-1 J``.

    ``J J^T`` is symmetric positive definite away from singularities: a Cholesky solve (LAPACK
    ``dposv``, ~2 us instead of ~12 us for ``np.linalg.solve``); least squares at a singularity.
    """
    kn = gains.nullspace_nm_per_rad
    tau0 = kn * (q_nullspace - q) - gains.nullspace_damping * dq
    JJt = J @ J.T
    JJt.flat[::7] += _EPS_JJT
    _, y, info = dposv(JJt, J @ tau0)
    if info != 0:
        y = np.linalg.lstsq(JJt, J @ tau0, rcond=None)[0]
    return tau0 - J.T @ y


def impedance_torque(J: Array, q: Array, dq: Array, T_base_ee: Array, T_target: Array,
                     twist_target: Array | None, q_nullspace: Array,
                     gains: ImpedanceGains) -> tuple[Array, Array]:
    """Joint torques (7,) of the JT law (no gravity, no Coriolis) and the task wrench (6,).

    ``J`` (6, 7) is the base-frame ("zero") Jacobian of the end-effector point, linear rows
    first; ``T_base_ee``/``T_target`` are 4x4 poses; ``twist_target`` the feed-forward twist.
    """
    twist = J @ dq
    F = impedance_wrench(T_target[:3, 3], T_target[:3, :3], twist_target, T_base_ee[:3, 3],
                         T_base_ee[:3, :3], twist, gains)
    return J.T @ F + nullspace_torque(J, q, dq, q_nullspace, gains), F


def lead_target(T_target: Array, twist_target: Array, gains: ImpedanceGains) -> Array:
    """Target pose that gives a feed-forward-free impedance controller the ``D v_d`` term.

    ``K (x_d - x) + D (v_d - v) = K (x_d + K^-1 D v_d - x) - D v``, so shifting the target by
    ``K^-1 D v_d`` reproduces the feed-forward exactly for translation and to first order for
    rotation (the shift is applied as a left rotation by ``K_r^-1 D_r w_d``).
    """
    K, D = gains.stiffness, gains.damping
    shift = D * twist_target / K
    T = T_target.copy()
    T[:3, 3] = T_target[:3, 3] + shift[:3]
    T[:3, :3] = so3_exp(shift[3:]) @ T_target[:3, :3]
    return T


def quat_xyzw_from_matrix(R: Array) -> Array:
    """Unit quaternion ``[x, y, z, w]`` (panda-py / Eigen order) of a rotation matrix."""
    q = quat_wxyz_from_matrix(R)
    return np.array([q[1], q[2], q[3], q[0]])
