"""Geometry and EKF helpers shared by the joint filters (pure functions, no state).

Conventions as in :mod:`services.common.se3`: poses 4x4, twists linear first ``(v, w)``, left
perturbations ``T = Exp(d) T_hat``. The ``*_fast`` functions compute exactly what their
:mod:`services.common.se3` namesakes compute (same formulas and small-angle branches), on Python
floats instead of many tiny numpy operations, because the estimator runs them on every frame; the
tests check them against :mod:`services.common.se3`.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dposv

from services.common.se3 import (  # noqa: F401 - the float kernels, re-exported
    _jl_coeffs,
    _rotation_rows,
    _so3_coeffs,
    rotation_angle_fast,
    se3_exp_fast,
    se3_inverse_fast,
    se3_log_fast,
    skew,
    so3_exp_fast,
    so3_left_jacobian_fast,
    so3_log_fast,
)
from services.common.se3 import se3_adjoint_fast as adjoint_fast  # noqa: F401
from services.common.snapshot import SnapshotError, SnapshotReader
from services.kinematics.config import KinematicsConfig

Array = NDArray[np.float64]

# Below this rotation angle (rad) the closed forms lose precision and Taylor series are used
# (the same threshold as services.common.se3).
_SMALL_ANGLE = 1e-4
_SMALL_ANGLE_SQ = _SMALL_ANGLE * _SMALL_ANGLE
_LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------------------------
# 3-vectors
# --------------------------------------------------------------------------------------------


def cross3(a: Array, b: Array) -> Array:
    """``a x b`` for two 3-vectors (faster than ``np.cross`` on single vectors)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def tangent_basis(u: Array) -> Array:
    """Deterministic orthonormal basis ``[t1 t2]`` (3x2) of the plane orthogonal to the unit ``u``.

    ``t1 = normalize(a x u)`` where ``a`` is the coordinate axis with the smallest ``|u_i|`` (lowest
    index on ties) and ``t2 = u x t1``, so ``(t1, t2, u)`` is right-handed. Well conditioned for
    every ``u`` (``|a x u| >= sqrt(2/3)``), including ``u = +-z``. It is the basis of the axis
    coordinates ``(b1, b2)`` of every published covariance.
    """
    x, y, z = u.tolist()
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax <= ay and ax <= az:  # a = e_x: a x u = (0, -z, y)
        t1 = (0.0, -z, y)
    elif ay <= az:  # a = e_y: a x u = (z, 0, -x)
        t1 = (z, 0.0, -x)
    else:  # a = e_z: a x u = (-y, x, 0)
        t1 = (-y, x, 0.0)
    n = math.sqrt(t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2])
    a0, a1, a2 = t1[0] / n, t1[1] / n, t1[2] / n
    b0, b1, b2 = y * a2 - z * a1, z * a0 - x * a2, x * a1 - y * a0  # t2 = u x t1
    return np.array([[a0, b0], [a1, b1], [a2, b2]])


def axis_basis(state: SnapshotReader, u: Array, key: str = "basis") -> Array:
    """The tangent basis (3x2) of the unit axis ``u`` restored from ``state[key]``: orthonormal
    and orthogonal to ``u`` (1e-6), else SnapshotError."""
    B = state.array(key, (3, 2))
    M = np.column_stack([B, u])
    err = float(np.abs(M.T @ M - np.eye(3)).max())
    if err > 1e-6:
        raise SnapshotError(f"{state.path}.{key}: not an orthonormal basis of the plane "
                            f"orthogonal to the axis (error {err:.3g})")
    return B


def rotate_axis(u: Array, B: Array, b: Array) -> tuple[Array, Array]:
    """Apply the tangent error ``b`` (2,): ``u' = R u`` and ``B' = R B`` with ``R = Exp(u x (B b))``.

    ``B'`` is re-orthonormalised against ``u'`` (``t2' = u' x t1'``) so round-off cannot drift.
    Computed on floats (Rodrigues' formula as in :func:`so3_exp_fast`).
    """
    u0, u1, u2 = u.tolist()
    (a0, c0), (a1, c1), (a2, c2) = B.tolist()
    b0, b1 = b.tolist()
    d0, d1, d2 = a0 * b0 + c0 * b1, a1 * b0 + c1 * b1, a2 * b0 + c2 * b1  # d = B b
    w0, w1, w2 = u1 * d2 - u2 * d1, u2 * d0 - u0 * d2, u0 * d1 - u1 * d0  # w = u x d
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    s, v = _so3_coeffs(th2)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = _rotation_rows(w0, w1, w2, s, v, th2)
    x0 = r00 * u0 + r01 * u1 + r02 * u2
    x1 = r10 * u0 + r11 * u1 + r12 * u2
    x2 = r20 * u0 + r21 * u1 + r22 * u2
    n = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    x0, x1, x2 = x0 / n, x1 / n, x2 / n
    e0 = r00 * a0 + r01 * a1 + r02 * a2
    e1 = r10 * a0 + r11 * a1 + r12 * a2
    e2 = r20 * a0 + r21 * a1 + r22 * a2
    k = e0 * x0 + e1 * x1 + e2 * x2
    e0, e1, e2 = e0 - k * x0, e1 - k * x1, e2 - k * x2
    n = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    e0, e1, e2 = e0 / n, e1 / n, e2 / n
    f0, f1, f2 = x1 * e2 - x2 * e1, x2 * e0 - x0 * e2, x0 * e1 - x1 * e0  # t2' = u' x t1'
    return np.array([x0, x1, x2]), np.array([[e0, f0], [e1, f1], [e2, f2]])


def axis_basis_change(B_from: Array, B_to: Array, sign: float = 1.0) -> Array:
    """2x2 map of axis tangent coordinates from basis ``B_from`` to ``B_to`` for ``u_to = sign u``.

    ``du_to = sign du = sign B_from b_from``, so ``b_to = sign B_to^T B_from b_from``.
    """
    return sign * (B_to.T @ B_from)


# --------------------------------------------------------------------------------------------
# SO(3) / SE(3) on floats
# --------------------------------------------------------------------------------------------


def rotation_angles_from_trace(trace: Array) -> Array:
    """Rotation angles (rad, in [0, pi]) from matrix traces, ``arccos((tr - 1) / 2)`` clipped."""
    return np.arccos(np.clip(0.5 * (trace - 1.0), -1.0, 1.0))


def mahalanobis2_3(v: Array, S: Array) -> float:
    """``v^T S^-1 v`` for a 3-vector and a symmetric 3x3 ``S`` (Cholesky on floats, the
    per-frame tests' kernel); infinite when ``S`` is not positive definite (nothing is inside a
    degenerate ellipsoid)."""
    (a, b, c), (_, d, e), (_, _, f) = S.tolist()
    x0, x1, x2 = v.tolist()
    if a <= 0.0:
        return math.inf
    l00 = math.sqrt(a)
    l10, l20 = b / l00, c / l00
    t = d - l10 * l10
    if t <= 0.0:
        return math.inf
    l11 = math.sqrt(t)
    l21 = (e - l20 * l10) / l11
    t = f - l20 * l20 - l21 * l21
    if t <= 0.0:
        return math.inf
    l22 = math.sqrt(t)
    y0 = x0 / l00  # solve L y = v; v^T S^-1 v = |y|^2
    y1 = (x1 - l10 * y0) / l11
    y2 = (x2 - l20 * y0 - l21 * y1) / l22
    return y0 * y0 + y1 * y1 + y2 * y2


def excess_sigmas(mahalanobis2: Array, sigmas: float) -> Array:
    """By how many sigmas a deviation lies beyond the rigid test (docs/estimation.md#rigid-test):
    ``max(0, sqrt(mahalanobis2) - sigmas)``, with ``mahalanobis2`` (m,) its ``e^T Sigma^-1 e``
    against its published covariance. 0 inside the ``sigmas``-sigma ellipsoid."""
    out: Array = np.maximum(np.sqrt(np.maximum(mahalanobis2, 0.0)) - sigmas, 0.0)
    return out


# --------------------------------------------------------------------------------------------
# Joint models
# --------------------------------------------------------------------------------------------


def prismatic_twist_jacobian(u: Array, B: Array, q: float) -> Array:
    """Jacobian (6x4) of the twist ``h = (q u, 0)`` w.r.t. ``(b1, b2, q, qdot)``."""
    J = np.zeros((6, 4))
    J[:3, :2] = q * B  # d(q u)/db = q B
    J[:3, 2] = u  # d(q u)/dq = u
    return J


def revolute_twist(u: Array, p: Array, q: float) -> Array:
    """Twist ``h = q (p x u, u)`` (6,) of a rotation by ``q`` about the line ``p + s u``."""
    h = np.empty(6)
    h[:3] = q * cross3(p, u)
    h[3:] = q * u
    return h


def revolute_twist_jacobian(u: Array, p: Array, B: Array, q: float) -> Array:
    """Jacobian (6x7) of ``h = q (p x u, u)`` w.r.t. ``(b1, b2, px, py, pz, q, qdot)``.

    ``dh/db = q (p x B, B)``; ``dh/dp = (-q [u]x, 0)`` (since ``p x u = -[u]x p``);
    ``dh/dq = (p x u, u)``; the ``qdot`` column is 0.
    """
    J = np.zeros((6, 7))
    J[:3, :2] = q * (skew(p) @ B)
    J[3:, :2] = q * B
    J[:3, 2:5] = -q * skew(u)
    J[:3, 5] = cross3(p, u)
    J[3:, 5] = u
    return J


def revolute_left_jacobian(u: Array, p: Array, q: float) -> Array:
    """SE(3) left Jacobian (6x6) at the revolute twist ``h = q (p x u, u)``.

    ``h = Ad(X) (0, q u)`` with ``X`` the translation by ``p``, and ``J_l(Ad(X) xi) = Ad(X) J_l(xi)
    Ad(X)^-1``; for the pure rotation ``(0, w)`` ``J_l = blkdiag(J_w, J_w)``, so
    ``J_l(h) = [[J_w, [p]x J_w - J_w [p]x], [0, J_w]]`` with ``J_w`` the SO(3) left Jacobian of ``q u``.
    """
    Jw = so3_left_jacobian_fast(q * u)
    P = skew(p)
    J = np.zeros((6, 6))
    J[:3, :3] = Jw
    J[3:, 3:] = Jw
    J[:3, 3:] = P @ Jw - Jw @ P
    return J


def revolute_delta(u: Array, p: Array, q: float) -> Array:
    """Pose ``Exp(q (p x u, u)) = [[R, (I - R) p], [0, 1]]`` with ``R = Exp(q u)``; any q."""
    T = np.eye(4)
    R = so3_exp_fast(q * u)
    T[:3, :3] = R
    T[:3, 3] = p - R @ p
    return T


def _jl_apply(w0: float, w1: float, w2: float, ja: float, jb: float, x0: float, x1: float,
              x2: float) -> tuple[float, float, float]:
    """``J_l(w) x = x + ja (w x x) + jb (w x (w x x))``."""
    c0, c1, c2 = w1 * x2 - w2 * x1, w2 * x0 - w0 * x2, w0 * x1 - w1 * x0
    d0, d1, d2 = w1 * c2 - w2 * c1, w2 * c0 - w0 * c2, w0 * c1 - w1 * c0
    return x0 + ja * c0 + jb * d0, x1 + ja * c1 + jb * d1, x2 + ja * c2 + jb * d2


def revolute_measurement_jacobian(u: Array, p: Array, B: Array, q: float) -> tuple[Array, Array]:
    """``(H, Exp(h))`` of the revolute group residual ``log(D (Exp(h) E)^-1)``.

    ``H`` (6x12) is the derivative w.r.t. the error state ``(b1, b2, c1, c2, q, qdot, e1..e6)``
    (axis ``u(b) = Exp(u x B b) u``, point ``p(c) = p + B c``, reference ``E = Exp(e) E``):
    ``H = [J_l(h) dh/d(b, c, q, qdot), Ad(Exp(h))]`` with ``h = q (p x u, u)``. With ``X`` the
    translation by ``p``, ``J_l(h) = Ad(X) blkdiag(J_w, J_w) Ad(X)^-1`` and
    ``Ad(X)^-1 dh/dx = [[0, -q [u]x B, 0, 0], [q B, 0, u, 0]]``, so
    ``H_top = [q p x (J_w B), -q J_w (u x B), p x u, 0]`` and ``H_bottom = [q J_w B, 0, u, 0]``
    (``J_w u = u``). ``Exp(h) = [[R, p - R p], [0, 1]]``, ``R = Exp(q u)`` (4x4).
    """
    u0, u1, u2 = u.tolist()
    p0, p1, p2 = p.tolist()
    (a0, c0), (a1, c1), (a2, c2) = B.tolist()
    w0, w1, w2 = q * u0, q * u1, q * u2
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    sa, sb = _so3_coeffs(th2)
    ja, jb = _jl_coeffs(th2)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = _rotation_rows(w0, w1, w2, sa, sb, th2)
    # Exp(h): translation t = p - R p
    t0 = p0 - (r00 * p0 + r01 * p1 + r02 * p2)
    t1 = p1 - (r10 * p0 + r11 * p1 + r12 * p2)
    t2 = p2 - (r20 * p0 + r21 * p1 + r22 * p2)
    # J_w t1, J_w t2 and J_w (u x t1), J_w (u x t2)
    g0, g1, g2 = _jl_apply(w0, w1, w2, ja, jb, a0, a1, a2)
    h0, h1, h2 = _jl_apply(w0, w1, w2, ja, jb, c0, c1, c2)
    k0, k1, k2 = _jl_apply(w0, w1, w2, ja, jb, u1 * a2 - u2 * a1, u2 * a0 - u0 * a2,
                           u0 * a1 - u1 * a0)
    m0, m1, m2 = _jl_apply(w0, w1, w2, ja, jb, u1 * c2 - u2 * c1, u2 * c0 - u0 * c2,
                           u0 * c1 - u1 * c0)
    # p x (J_w t_i)
    pg0, pg1, pg2 = p1 * g2 - p2 * g1, p2 * g0 - p0 * g2, p0 * g1 - p1 * g0
    ph0, ph1, ph2 = p1 * h2 - p2 * h1, p2 * h0 - p0 * h2, p0 * h1 - p1 * h0
    pu0, pu1, pu2 = p1 * u2 - p2 * u1, p2 * u0 - p0 * u2, p0 * u1 - p1 * u0
    # [t]x R, column j = t x R[:, j]
    x00, x10, x20 = t1 * r20 - t2 * r10, t2 * r00 - t0 * r20, t0 * r10 - t1 * r00
    x01, x11, x21 = t1 * r21 - t2 * r11, t2 * r01 - t0 * r21, t0 * r11 - t1 * r01
    x02, x12, x22 = t1 * r22 - t2 * r12, t2 * r02 - t0 * r22, t0 * r12 - t1 * r02
    H = np.array([
        [q * pg0, q * ph0, -q * k0, -q * m0, pu0, 0.0, r00, r01, r02, x00, x01, x02],
        [q * pg1, q * ph1, -q * k1, -q * m1, pu1, 0.0, r10, r11, r12, x10, x11, x12],
        [q * pg2, q * ph2, -q * k2, -q * m2, pu2, 0.0, r20, r21, r22, x20, x21, x22],
        [q * g0, q * h0, 0.0, 0.0, u0, 0.0, 0.0, 0.0, 0.0, r00, r01, r02],
        [q * g1, q * h1, 0.0, 0.0, u1, 0.0, 0.0, 0.0, 0.0, r10, r11, r12],
        [q * g2, q * h2, 0.0, 0.0, u2, 0.0, 0.0, 0.0, 0.0, r20, r21, r22]])
    Ex = np.array([[r00, r01, r02, t0], [r10, r11, r12, t1], [r20, r21, r22, t2],
                   [0.0, 0.0, 0.0, 1.0]])
    return H, Ex


# --------------------------------------------------------------------------------------------
# Measurement noise
# --------------------------------------------------------------------------------------------


def prismatic_noise_inflation(displacement_norm_m: float, config: KinematicsConfig) -> float:
    """OMIP's prismatic factor ``f = 1 / (1 - exp(-|z| / L))``, clipped at the configured max."""
    denom = -math.expm1(-displacement_norm_m / config.prismatic_inflation_length_m)
    if denom * config.max_inflation_factor <= 1.0:
        return config.max_inflation_factor
    return 1.0 / denom


def revolute_noise_inflation(rotation_angle_rad: float, config: KinematicsConfig) -> float:
    """OMIP's revolute factor ``f = 1 / (1 - exp(-sin(|w| / 2) / s))``, clipped at the max.

    ``|w|`` is the rotation angle of the measured delta in [0, pi]; the factor inflates R near 0
    (and so near 2 pi, where the delta is again close to I).
    """
    x = abs(math.sin(0.5 * rotation_angle_rad)) / config.revolute_inflation_scale
    denom = -math.expm1(-x)
    if denom * config.max_inflation_factor <= 1.0:
        return config.max_inflation_factor
    return 1.0 / denom


def inflated_noise(Sigma_z: Array, factor: float, floor: float) -> Array:
    """Measurement covariance ``R = f Sigma_z + floor I`` (docs/estimation.md#measurement-noise)."""
    return factor * Sigma_z + floor * np.eye(len(Sigma_z))


# --------------------------------------------------------------------------------------------
# EKF step
# --------------------------------------------------------------------------------------------


_EYE = {n: np.eye(n) for n in (3, 4, 6, 7, 12, 13)}


def ekf_correct(P: Array, H: Array, R: Array, y: Array) -> tuple[Array, Array, Array, Array]:
    """Shared EKF correction of an error state; returns ``(dx, P_post, S, K)``.

    S = H P H^T + R; K = P H^T S^-1, obtained as ``K^T = solve(S, H P)`` with a Cholesky solve
    (LAPACK ``posv``; S is symmetric positive definite, P symmetric); dx = K y;
    P+ = (I - K H) P (I - K H)^T + K R K^T (Joseph form: stays symmetric positive semi-definite
    under round-off, unlike (I - K H) P), then symmetrised.
    """
    HP = H @ P
    S = HP @ H.T + R  # S = H P H^T + R
    _, Kt, info = dposv(S, HP)  # K^T = S^-1 H P
    if info:  # not numerically positive definite: general LU solve
        Kt = np.linalg.solve(S, HP)
    K = Kt.T  # K = P H^T S^-1
    dx = y @ Kt  # dx = K y
    n = len(P)
    A = (_EYE[n] if n in _EYE else np.eye(n)) - K @ H
    P_post = A @ P @ A.T + K @ R @ Kt  # Joseph form
    return dx, (P_post + P_post.T) * 0.5, S, K


def gaussian_log_density(y: Array, S: Array) -> float:
    """``log N(y; 0, S)`` via a Cholesky factor (innovation diagnostics)."""
    L = np.linalg.cholesky(S)
    a = np.linalg.solve(L, y)
    return float(-0.5 * (a @ a) - np.log(np.diag(L)).sum() - 0.5 * len(y) * _LOG_2PI)
