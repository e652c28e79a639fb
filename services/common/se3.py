"""SO(3) and SE(3) maps: exp, log, adjoint and left Jacobians.

Conventions (the same everywhere in handkse):

- A pose ``T_a_b`` is a 4x4 homogeneous ``float64`` matrix mapping points in frame b to frame a.
- Twists and exponential coordinates are ordered **linear first**: ``xi = [vx, vy, vz, wx, wy, wz]``.
- ``se3_exp(xi) = [[Exp(w), J_l(w) v], [0, 1]]`` where ``J_l`` is the left Jacobian of SO(3).
- Left perturbations: ``T = se3_exp(delta) @ T_hat``; covariances of ``delta`` change frame as
  ``Ad(T) @ Sigma @ Ad(T).T`` with ``Ad(T) = [[R, [t]x R], [0, R]]``.
- ``so3_log`` returns rotation vectors with angle in [0, pi]; it goes through the quaternion
  (atan2 of the half angle), so it is stable near 0 and near pi, where ``1/sin`` forms are not.

Lengths are metres, angles radians. Functions take and return numpy arrays and do not check
their inputs; callers at module boundaries validate.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# Below this rotation angle (rad) the closed forms lose precision and Taylor series are used.
_SMALL_ANGLE = 1e-4


def skew(v: Array) -> Array:
    """Return the 3x3 matrix ``[v]x`` with ``[v]x @ u == cross(v, u)``."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(w: Array) -> Array:
    """Rotation matrix of the rotation vector ``w`` (Rodrigues' formula)."""
    theta_sq = float(w @ w)
    W = skew(w)
    if theta_sq < _SMALL_ANGLE**2:
        a = 1.0 - theta_sq / 6.0
        b = 0.5 - theta_sq / 24.0
    else:
        theta = math.sqrt(theta_sq)
        a = math.sin(theta) / theta
        b = (1.0 - math.cos(theta)) / theta_sq
    return np.eye(3) + a * W + b * (W @ W)


def quat_wxyz_from_matrix(R: Array) -> Array:
    """Unit quaternion ``[w, x, y, z]`` with ``w >= 0`` of a rotation matrix (Shepperd's method).

    Picks the largest of the four squared components as pivot, so no branch divides by a
    small number; accurate for every rotation, including angles at pi.
    """
    m00, m11, m22 = R[0, 0], R[1, 1], R[2, 2]
    trace = m00 + m11 + m22
    if trace >= max(m00, m11, m22):
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s,
                      (R[1, 0] - R[0, 1]) / s])
    elif m00 >= m11 and m00 >= m22:
        s = 2.0 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s,
                      (R[0, 2] + R[2, 0]) / s])
    elif m11 >= m22:
        s = 2.0 * math.sqrt(max(1.0 - m00 + m11 - m22, 0.0))
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s,
                      (R[1, 2] + R[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(max(1.0 - m00 - m11 + m22, 0.0))
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s,
                      (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0.0 else q


def so3_log(R: Array) -> Array:
    """Rotation vector (angle in [0, pi]) of a rotation matrix.

    With the quaternion ``(qw, qv)``, ``qw >= 0``: angle = ``2 atan2(|qv|, qw)`` and the vector is
    ``angle * qv / |qv|``. For tiny ``|qv|`` the ratio ``2 atan2(n, qw) / n`` is replaced by its
    series ``2/qw (1 - n^2 / (3 qw^2))``. At exactly pi the sign of the axis is arbitrary.
    """
    q = quat_wxyz_from_matrix(R)
    qw, qv = q[0], q[1:]
    n = math.sqrt(float(qv @ qv))
    if n < 1e-8:
        return (2.0 / qw) * (1.0 - n * n / (3.0 * qw * qw)) * qv
    return (2.0 * math.atan2(n, qw) / n) * qv


def _left_jacobian_coeffs(theta_sq: float) -> tuple[float, float]:
    """Coefficients ``(a, b)`` of ``J_l(w) = I + a [w]x + b [w]x^2``."""
    if theta_sq < _SMALL_ANGLE**2:
        return 0.5 - theta_sq / 24.0, 1.0 / 6.0 - theta_sq / 120.0
    theta = math.sqrt(theta_sq)
    return (1.0 - math.cos(theta)) / theta_sq, (theta - math.sin(theta)) / (theta_sq * theta)


def so3_left_jacobian(w: Array) -> Array:
    """Left Jacobian ``J_l(w)`` of SO(3): ``Exp(w + dw) ~= Exp(J_l(w) dw) Exp(w)``."""
    a, b = _left_jacobian_coeffs(float(w @ w))
    W = skew(w)
    return np.eye(3) + a * W + b * (W @ W)


def so3_left_jacobian_inv(w: Array) -> Array:
    """Inverse left Jacobian of SO(3), valid for angles below 2 pi.

    ``J_l^-1 = I - [w]x / 2 + c [w]x^2`` with ``c = (1 - (t/2) cot(t/2)) / t^2``; the cot form
    stays finite at pi where ``(1 + cos t) / (2 t sin t)`` is 0/0.
    """
    theta_sq = float(w @ w)
    if theta_sq < _SMALL_ANGLE**2:
        c = 1.0 / 12.0 + theta_sq / 720.0
    else:
        theta = math.sqrt(theta_sq)
        half = 0.5 * theta
        c = (1.0 - half * math.cos(half) / math.sin(half)) / theta_sq
    W = skew(w)
    return np.eye(3) - 0.5 * W + c * (W @ W)


def se3_exp(xi: Array) -> Array:
    """4x4 pose of the exponential coordinates ``xi = [v, w]`` (linear first)."""
    v, w = xi[:3], xi[3:]
    T = np.eye(4)
    T[:3, :3] = so3_exp(w)
    T[:3, 3] = so3_left_jacobian(w) @ v
    return T


def se3_log(T: Array) -> Array:
    """Exponential coordinates ``[v, w]`` of a pose; the rotation angle is in [0, pi]."""
    w = so3_log(T[:3, :3])
    v = so3_left_jacobian_inv(w) @ T[:3, 3]
    return np.concatenate([v, w])


def se3_inverse(T: Array) -> Array:
    """Inverse of a homogeneous pose without a general matrix inverse."""
    R, t = T[:3, :3], T[:3, 3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -(R.T @ t)
    return Ti


def se3_adjoint(T: Array) -> Array:
    """6x6 adjoint ``[[R, [t]x R], [0, R]]`` for linear-first twists: ``Ad(T) xi = log(T Exp(xi) T^-1)``."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[:3, 3:] = skew(t) @ R
    A[3:, 3:] = R
    return A


def _se3_q_block(v: Array, w: Array) -> Array:
    """Upper-right block ``Q(v, w)`` of the SE(3) left Jacobian (Barfoot, eq. 7.86)."""
    theta_sq = float(w @ w)
    V, W = skew(v), skew(w)
    WV, VW = W @ V, V @ W
    WVW = WV @ W
    if theta_sq < _SMALL_ANGLE**2:
        c1 = 1.0 / 6.0 - theta_sq / 120.0
        c2 = 1.0 / 24.0 - theta_sq / 720.0
        c3 = 1.0 / 120.0 - theta_sq / 2520.0
    else:
        theta = math.sqrt(theta_sq)
        s, c = math.sin(theta), math.cos(theta)
        c1 = (theta - s) / (theta_sq * theta)
        c2 = (theta_sq + 2.0 * c - 2.0) / (2.0 * theta_sq * theta_sq)
        c3 = (2.0 * theta - 3.0 * s + theta * c) / (2.0 * theta_sq * theta_sq * theta)
    return (0.5 * V + c1 * (WV + VW + WVW) + c2 * (W @ WV + VW @ W - 3.0 * WVW)
            + c3 * (WVW @ W + W @ WVW))


def se3_left_jacobian(xi: Array) -> Array:
    """6x6 left Jacobian of SE(3): ``Exp(xi + d) ~= Exp(J_l(xi) d) Exp(xi)``."""
    v, w = xi[:3], xi[3:]
    J = np.zeros((6, 6))
    Jw = so3_left_jacobian(w)
    J[:3, :3] = Jw
    J[3:, 3:] = Jw
    J[:3, 3:] = _se3_q_block(v, w)
    return J


def se3_left_jacobian_inv(xi: Array) -> Array:
    """Inverse of the 6x6 SE(3) left Jacobian, from the block structure (no 6x6 solve)."""
    v, w = xi[:3], xi[3:]
    Jw_inv = so3_left_jacobian_inv(w)
    J = np.zeros((6, 6))
    J[:3, :3] = Jw_inv
    J[3:, 3:] = Jw_inv
    J[:3, 3:] = -Jw_inv @ _se3_q_block(v, w) @ Jw_inv
    return J


def transform_points(T_a_b: Array, points_b: Array) -> Array:
    """Map an (N, 3) array of points from frame b to frame a."""
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def pose_from_rotation_translation(R: Array, t: Array) -> Array:
    """4x4 pose from a 3x3 rotation and a translation 3-vector."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def rotation_angle(R: Array) -> float:
    """Angle in [0, pi] of a rotation matrix, stable at 0 and pi."""
    return float(np.linalg.norm(so3_log(R)))
