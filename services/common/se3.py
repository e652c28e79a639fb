"""SO(3) and SE(3) maps: exp, log, adjoint and left Jacobians.

One module although it is long: it is the one home of these maps, each in an array form and a
Python-float ``*_fast`` form that must agree (tested pairwise), so they stay side by side.

Conventions (the same everywhere in handkse):

- A pose ``T_a_b`` is a 4x4 homogeneous ``float64`` matrix mapping points in frame b to frame a.
- Twists and exponential coordinates are ordered **linear first**: ``xi = [vx, vy, vz, wx, wy, wz]``.
- ``se3_exp(xi) = [[Exp(w), J_l(w) v], [0, 1]]`` where ``J_l`` is the left Jacobian of SO(3).
- Left perturbations: ``T = se3_exp(delta) @ T_hat``; covariances of ``delta`` change frame as
  ``Ad(T) @ Sigma @ Ad(T).T`` with ``Ad(T) = [[R, [t]x R], [0, R]]``.
- ``so3_log`` returns rotation vectors with angle in [0, pi]; it goes through the quaternion
  (atan2 of the half angle), so it is stable near 0 and near pi, where ``1/sin`` forms are not.

Lengths are metres, angles radians. Functions take and return numpy arrays and do not check
their inputs; callers at module boundaries validate, with :func:`check_pose` for poses (the one
pose check of handkse: the protocol decoder and the libraries' own input checks use it).
:func:`skew_batch` and :func:`so3_exp` also take stacks ``(..., 3)`` of vectors. This module is
the one home of ``[v]x`` and Rodrigues' formula; rigid fits of point sets are in
:mod:`services.common.kabsch`.

The ``*_fast`` functions compute the same maps for one input on Python floats, with the same
small-angle branches: a few microseconds where a dozen tiny numpy operations take tens, for
filters that run them on every frame. They agree with their namesakes to round-off (the sums run
in another order; :func:`se3_left_jacobian_fast` uses an equivalent closed form of the ``Q`` block).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# Tolerance of check_pose on a rotation's orthonormality and determinant; the wire contract's
# (docs/protocol.md, validation rules).
POSE_TOLERANCE = 1e-6

# Below this rotation angle (rad) the closed forms lose precision and Taylor series are used.
_SMALL_ANGLE = 1e-4


def skew(v: Array) -> Array:
    """Return the 3x3 matrix ``[v]x`` with ``[v]x @ u == cross(v, u)``."""
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


# [v]x flattened row-major is ``v @ _SKEW_MAP``: rows v0, v1, v2; columns the nine entries.
_SKEW_MAP = np.zeros((3, 9))
_SKEW_MAP[2, 1] = _SKEW_MAP[1, 6] = _SKEW_MAP[0, 5] = -1.0
_SKEW_MAP[1, 2] = _SKEW_MAP[2, 3] = _SKEW_MAP[0, 7] = 1.0


def skew_batch(v: Array) -> Array:
    """``[v]x`` for a stack of 3-vectors: (..., 3) -> (..., 3, 3) (as :func:`skew`)."""
    out: Array = (v @ _SKEW_MAP).reshape(*v.shape[:-1], 3, 3)
    return out


def so3_exp(w: Array) -> Array:
    """Rotation matrix of the rotation vector ``w`` (Rodrigues' formula).

    ``w`` (3,) gives (3, 3); a stack (..., 3) gives (..., 3, 3), each as for a single vector
    (to round-off: the stack is evaluated with array operations).
    """
    if w.ndim > 1:
        return _so3_exp_stack(w)
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


def _so3_exp_stack(w: Array) -> Array:
    """:func:`so3_exp` of a stack (..., 3) of rotation vectors, same coefficients and branch."""
    theta_sq = np.einsum("...i,...i->...", w, w)
    theta = np.sqrt(theta_sq)
    small = theta_sq < _SMALL_ANGLE**2
    safe = np.where(small, 1.0, theta)  # no 0/0 in the branch np.where discards
    a = np.where(small, 1.0 - theta_sq / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta_sq / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    W = skew_batch(w)
    out: Array = np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)
    return out


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


def _q_coeffs(theta_sq: float) -> tuple[float, float, float]:
    """Coefficients ``(c1, c2, c3)`` of Barfoot's ``Q(v, w)`` at ``|w|^2 = theta_sq``."""
    if theta_sq < _SMALL_ANGLE**2:
        return (1.0 / 6.0 - theta_sq / 120.0, 1.0 / 24.0 - theta_sq / 720.0,
                1.0 / 120.0 - theta_sq / 2520.0)
    theta = math.sqrt(theta_sq)
    s, c = math.sin(theta), math.cos(theta)
    return ((theta - s) / (theta_sq * theta),
            (theta_sq + 2.0 * c - 2.0) / (2.0 * theta_sq * theta_sq),
            (2.0 * theta - 3.0 * s + theta * c) / (2.0 * theta_sq * theta_sq * theta))


def _se3_q_block(v: Array, w: Array) -> Array:
    """Upper-right block ``Q(v, w)`` of the SE(3) left Jacobian (Barfoot, eq. 7.86)."""
    theta_sq = float(w @ w)
    V, W = skew(v), skew(w)
    WV, VW = W @ V, V @ W
    WVW = WV @ W
    c1, c2, c3 = _q_coeffs(theta_sq)
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


def check_pose(T: object, tol: float = POSE_TOLERANCE) -> str | None:
    """What is wrong with ``T`` as a pose ``T_a_b``, or None when it is a rigid transform.

    ``T``: array-like, shape (4, 4). A rigid transform is finite, its rotation block ``R`` has
    ``max |R^T R - I| <= tol`` and ``|det R - 1| <= tol`` (no reflection, no scale), and its
    bottom row is exactly ``[0, 0, 0, 1]``. Never raises: the answer is a short description of
    the first problem found, for the caller's error message (callers decide whether to raise,
    reject or count).
    """
    try:
        M = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        return "not a numeric array"
    if M.shape != (4, 4):
        return f"shape must be (4, 4), got {M.shape}"
    if not np.isfinite(M).all():
        return "contains NaN or infinity"
    if (M[3] != (0.0, 0.0, 0.0, 1.0)).any():
        return f"bottom row must be [0, 0, 0, 1], got {M[3].tolist()}"
    R = M[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > tol:
        return f"rotation is not orthonormal (max |R^T R - I| = {err:.3g} > {tol:g})"
    det = float(np.linalg.det(R))
    if abs(det - 1.0) > tol:
        return f"rotation has determinant {det:.9g}, not 1"
    return None


def rotation_angle(R: Array) -> float:
    """Angle in [0, pi] of a rotation matrix, stable at 0 and pi."""
    return float(np.linalg.norm(so3_log(R)))


# --- Float kernels (see the module docstring) -------------------------------------------------

_SMALL_ANGLE_SQ = _SMALL_ANGLE * _SMALL_ANGLE


def _so3_coeffs(th2: float) -> tuple[float, float]:
    """``(sin t / t, (1 - cos t) / t^2)`` with their series below the small angle."""
    if th2 < _SMALL_ANGLE_SQ:
        return 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    th = math.sqrt(th2)
    return math.sin(th) / th, (1.0 - math.cos(th)) / th2


def _jl_coeffs(th2: float) -> tuple[float, float]:
    """``(a, b)`` of ``J_l(w) = I + a [w]x + b [w]x^2``."""
    if th2 < _SMALL_ANGLE_SQ:
        return 0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0
    th = math.sqrt(th2)
    return (1.0 - math.cos(th)) / th2, (th - math.sin(th)) / (th2 * th)


def _rotation_rows(w0: float, w1: float, w2: float, a: float, b: float,
                   th2: float) -> list[list[float]]:
    """Rows of ``I + a [w]x + b [w]x^2`` (with ``[w]x^2 = w w^T - |w|^2 I``)."""
    d = 1.0 - b * th2
    return [[d + b * w0 * w0, b * w0 * w1 - a * w2, b * w0 * w2 + a * w1],
            [b * w1 * w0 + a * w2, d + b * w1 * w1, b * w1 * w2 - a * w0],
            [b * w2 * w0 - a * w1, b * w2 * w1 + a * w0, d + b * w2 * w2]]


def so3_exp_fast(w: Array) -> Array:
    """Rotation matrix of the rotation vector ``w`` (as ``se3.so3_exp``)."""
    w0, w1, w2 = w.tolist()
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    a, b = _so3_coeffs(th2)
    return np.array(_rotation_rows(w0, w1, w2, a, b, th2))


def so3_left_jacobian_fast(w: Array) -> Array:
    """Left Jacobian of SO(3) at ``w`` (as ``se3.so3_left_jacobian``)."""
    w0, w1, w2 = w.tolist()
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    a, b = _jl_coeffs(th2)
    return np.array(_rotation_rows(w0, w1, w2, a, b, th2))


def se3_exp_fast(xi: Array) -> Array:
    """4x4 pose ``Exp(xi)``, ``xi = (v, w)`` (as ``se3.se3_exp``)."""
    v0, v1, v2, w0, w1, w2 = xi.tolist()
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    a, b = _so3_coeffs(th2)
    rows = _rotation_rows(w0, w1, w2, a, b, th2)
    ja, jb = _jl_coeffs(th2)
    # t = J_l(w) v = v + ja (w x v) + jb (w x (w x v))
    c0, c1, c2 = w1 * v2 - w2 * v1, w2 * v0 - w0 * v2, w0 * v1 - w1 * v0
    cc0, cc1, cc2 = w1 * c2 - w2 * c1, w2 * c0 - w0 * c2, w0 * c1 - w1 * c0
    rows[0].append(v0 + ja * c0 + jb * cc0)
    rows[1].append(v1 + ja * c1 + jb * cc1)
    rows[2].append(v2 + ja * c2 + jb * cc2)
    rows.append([0.0, 0.0, 0.0, 1.0])
    return np.array(rows)


def _quat_from_rows(r00: float, r01: float, r02: float, r10: float, r11: float, r12: float,
                    r20: float, r21: float, r22: float) -> tuple[float, float, float, float]:
    """Unit quaternion ``(w, x, y, z)``, ``w >= 0`` (Shepperd, as ``se3.quat_wxyz_from_matrix``)."""
    trace = r00 + r11 + r22
    if trace >= max(r00, r11, r22):
        s = 2.0 * math.sqrt(max(1.0 + trace, 0.0))
        qw, qx, qy, qz = 0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
    elif r00 >= r11 and r00 >= r22:
        s = 2.0 * math.sqrt(max(1.0 + r00 - r11 - r22, 0.0))
        qw, qx, qy, qz = (r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s
    elif r11 >= r22:
        s = 2.0 * math.sqrt(max(1.0 - r00 + r11 - r22, 0.0))
        qw, qx, qy, qz = (r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(max(1.0 - r00 - r11 + r22, 0.0))
        qw, qx, qy, qz = (r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if qw < 0.0:
        n = -n
    return qw / n, qx / n, qy / n, qz / n


def _so3_log_rows(r00: float, r01: float, r02: float, r10: float, r11: float, r12: float,
                  r20: float, r21: float, r22: float) -> tuple[float, float, float]:
    """Rotation vector (angle in [0, pi]) via the quaternion (as ``se3.so3_log``)."""
    qw, qx, qy, qz = _quat_from_rows(r00, r01, r02, r10, r11, r12, r20, r21, r22)
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    f = (2.0 / qw) * (1.0 - n * n / (3.0 * qw * qw)) if n < 1e-8 else 2.0 * math.atan2(n, qw) / n
    return f * qx, f * qy, f * qz


def so3_log_fast(R: Array) -> Array:
    """Rotation vector of a rotation matrix (as ``se3.so3_log``)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    return np.array(_so3_log_rows(r00, r01, r02, r10, r11, r12, r20, r21, r22))


def se3_log_fast(T: Array) -> Array:
    """Exponential coordinates ``(v, w)`` of a pose, angle in [0, pi] (as ``se3.se3_log``)."""
    (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2) = T[:3].tolist()
    w0, w1, w2 = _so3_log_rows(r00, r01, r02, r10, r11, r12, r20, r21, r22)
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < _SMALL_ANGLE_SQ:
        c = 1.0 / 12.0 + th2 / 720.0
    else:
        half = 0.5 * math.sqrt(th2)
        c = (1.0 - half * math.cos(half) / math.sin(half)) / th2
    # v = J_l^-1 t = t - (w x t) / 2 + c (w (w . t) - |w|^2 t)
    x0, x1, x2 = w1 * t2 - w2 * t1, w2 * t0 - w0 * t2, w0 * t1 - w1 * t0
    wt = w0 * t0 + w1 * t1 + w2 * t2
    return np.array([t0 - 0.5 * x0 + c * (w0 * wt - th2 * t0),
                     t1 - 0.5 * x1 + c * (w1 * wt - th2 * t1),
                     t2 - 0.5 * x2 + c * (w2 * wt - th2 * t2), w0, w1, w2])


def rotation_angle_fast(R: Array) -> float:
    """Angle in [0, pi] of a rotation matrix, ``atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)``."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    s0, s1, s2 = r21 - r12, r02 - r20, r10 - r01
    return math.atan2(0.5 * math.sqrt(s0 * s0 + s1 * s1 + s2 * s2), 0.5 * (r00 + r11 + r22 - 1.0))


def se3_inverse_fast(T: Array) -> Array:
    """Inverse ``[[R^T, -R^T t], [0, 1]]`` of a homogeneous pose (as ``se3.se3_inverse``)."""
    (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2) = T[:3].tolist()
    return np.array([
        [r00, r10, r20, -(r00 * t0 + r10 * t1 + r20 * t2)],
        [r01, r11, r21, -(r01 * t0 + r11 * t1 + r21 * t2)],
        [r02, r12, r22, -(r02 * t0 + r12 * t1 + r22 * t2)],
        [0.0, 0.0, 0.0, 1.0]])


def se3_adjoint_fast(T: Array) -> Array:
    """6x6 adjoint ``[[R, [t]x R], [0, R]]`` (as ``se3.se3_adjoint``)."""
    (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2) = T[:3].tolist()
    # [t]x R, column j = t x R[:, j]
    x00, x10, x20 = t1 * r20 - t2 * r10, t2 * r00 - t0 * r20, t0 * r10 - t1 * r00
    x01, x11, x21 = t1 * r21 - t2 * r11, t2 * r01 - t0 * r21, t0 * r11 - t1 * r01
    x02, x12, x22 = t1 * r22 - t2 * r12, t2 * r02 - t0 * r22, t0 * r12 - t1 * r02
    return np.array([[r00, r01, r02, x00, x01, x02],
                     [r10, r11, r12, x10, x11, x12],
                     [r20, r21, r22, x20, x21, x22],
                     [0.0, 0.0, 0.0, r00, r01, r02],
                     [0.0, 0.0, 0.0, r10, r11, r12],
                     [0.0, 0.0, 0.0, r20, r21, r22]])


def se3_left_jacobian_fast(xi: Array) -> Array:
    """:func:`se3_left_jacobian` on Python floats: ``[[J_l(w), Q(v, w)], [0, J_l(w)]]``.

    ``Q`` in closed form: with ``W = [w]x``, ``V = [v]x``, ``s = w . v``, ``u = w x v`` and the
    identities ``WV = v w' - s I``, ``VW = w v' - s I``, ``WVW = -s W``, ``W^2 = w w' - |w|^2 I``,
    Barfoot's ``Q = V/2 + c1 (WV + VW + WVW) + c2 (W^2 V + V W^2 - 3 WVW) + c3 (WVW W + W WVW)``
    (:func:`_se3_q_block`) is ``[g]x + w p' + r w' + k I`` with ``g = (1/2 - 2 c2 |w|^2) v +
    (3 c2 - c1) s w``, ``p = c1 v + c2 u - 2 c3 s w``, ``r = c1 v - c2 u``,
    ``k = 2 s (c3 |w|^2 - c1)``.
    """
    v0, v1, v2, w0, w1, w2 = xi.tolist()
    theta_sq = w0 * w0 + w1 * w1 + w2 * w2
    ja, jb = _jl_coeffs(theta_sq)
    J = _rotation_rows(w0, w1, w2, ja, jb, theta_sq)
    c1, c2, c3 = _q_coeffs(theta_sq)
    s = w0 * v0 + w1 * v1 + w2 * v2
    u0, u1, u2 = w1 * v2 - w2 * v1, w2 * v0 - w0 * v2, w0 * v1 - w1 * v0
    kv, kw, k = 0.5 - 2.0 * c2 * theta_sq, (3.0 * c2 - c1) * s, 2.0 * s * (c3 * theta_sq - c1)
    g0, g1, g2 = kv * v0 + kw * w0, kv * v1 + kw * w1, kv * v2 + kw * w2
    e = 2.0 * c3 * s
    p0, p1, p2 = c1 * v0 + c2 * u0 - e * w0, c1 * v1 + c2 * u1 - e * w1, c1 * v2 + c2 * u2 - e * w2
    r0, r1, r2 = c1 * v0 - c2 * u0, c1 * v1 - c2 * u1, c1 * v2 - c2 * u2
    (j00, j01, j02), (j10, j11, j12), (j20, j21, j22) = J
    return np.array([
        [j00, j01, j02, w0 * p0 + r0 * w0 + k, w0 * p1 + r0 * w1 - g2, w0 * p2 + r0 * w2 + g1],
        [j10, j11, j12, w1 * p0 + r1 * w0 + g2, w1 * p1 + r1 * w1 + k, w1 * p2 + r1 * w2 - g0],
        [j20, j21, j22, w2 * p0 + r2 * w0 - g1, w2 * p1 + r2 * w1 + g0, w2 * p2 + r2 * w2 + k],
        [0.0, 0.0, 0.0, j00, j01, j02],
        [0.0, 0.0, 0.0, j10, j11, j12],
        [0.0, 0.0, 0.0, j20, j21, j22]])
