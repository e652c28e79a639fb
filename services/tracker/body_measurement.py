"""The hand-body level's measurement model, over stacked landmarks (derivation: ``body.py``).

Landmark ``i`` with body-frame coordinates ``p_i`` is measured as ``z_i`` (tracking frame, m) with
covariance ``R_i`` (3x3; ``r_i I3`` wherever a variance ``r_i`` is given); ``h_i(T) = T p_i``,
``y_i = z_i - h_i(T_p)``, and the pose part of the Jacobian is ``H_i = [I3, -[T_p p_i]x]``
(3x6, left perturbation ``[v, w]``). Because ``R = blkdiag(R_i)``, every stacked quantity reduces
to the 6x6 information sums ``A = sum H_i' R_i^-1 H_i``, ``b = sum H_i' R_i^-1 y_i``,
``c = sum y_i' R_i^-1 y_i`` (:func:`information_sums`). From them: the stacked log-likelihood of a
motion model's prediction (:func:`log_likelihoods`), and the two per-landmark gates, against the
predicted landmark (:func:`prior_gate_passes`) and leave-one-out
(:func:`posterior_residual_passes`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import skew_batch
from services.tracker.landmarks import adjugate_sym3

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_LOG_2PI = math.log(2.0 * math.pi)
_I3 = np.eye(3)
_I6 = np.eye(6)
# [v]x = (v @ _SKEW).reshape(3, 3); measurement Jacobian [I3, -[q]x] = q @ _H_Q + _H_I (flattened)
_SKEW = skew_batch(_I3).reshape(3, 9)  # rows: v0, v1, v2; columns: row-major entries
_H_Q = np.zeros((3, 18))
_H_Q[:, [3, 4, 5, 9, 10, 11, 15, 16, 17]] = -_SKEW
_H_I = np.zeros(18)
_H_I[[0, 7, 14]] = 1.0


def measurement_jacobians(points_frame: Array) -> Array:
    """Pose part of ``H_i = d(T p_i)/d delta = [I3, -[T p_i]x]``: (..., 3, 6) for (..., 3) points."""
    H: Array = (points_frame @ _H_Q + _H_I).reshape(*points_frame.shape[:-1], 3, 6)
    return H


def predicted_points(T: Array, points_body: Array) -> Array:
    """``T p_i`` for poses (..., 4, 4) and body points (n, 3) -> (..., n, 3)."""
    return points_body @ T[..., :3, :3].swapaxes(-1, -2) + T[..., None, :3, 3]


def as_covariances(r: Array) -> Array:
    """Measurement covariances (n, 3, 3) from per-landmark variances ``r`` (n,) (``r_i I3``) or
    from covariances (n, 3, 3) (returned as they are)."""
    r = np.asarray(r, dtype=float)
    if r.ndim == 1:
        return r[:, None, None] * _I3
    return r


def information_sums(q: Array, y: Array, W: Array) -> tuple[Array, Array, Array]:
    """``A = sum H_i' W_i H_i`` (m, 6, 6), ``b = sum H_i' W_i y_i`` (m, 6),
    ``c = sum y_i' W_i y_i`` (m,).

    ``q`` (m, n, 3) predicted landmarks (``H_i = [I, -[q_i]x]``), ``y`` (m, n, 3) innovations,
    ``W`` the inverse measurement covariances ``R_i^-1``: (n, 3, 3), or (n,) inverse variances
    of isotropic ``R_i = r_i I3`` (0 = not used). The (n, 3, 3) case stacks the ``H_i`` into a
    (3n, 6) ``H`` and the ``W_i H_i`` alike, so each sum is one matrix product
    (:func:`information_sums_from_jacobians`).
    """
    W = np.asarray(W, dtype=float)
    if W.ndim == 1:
        return _information_sums_isotropic(q, y, W)
    return information_sums_from_jacobians(measurement_jacobians(q), y, W)


def information_sums_from_jacobians(H: Array, y: Array, W: Array) -> tuple[Array, Array, Array]:
    """:func:`information_sums` from the measurement Jacobians ``H`` (m, n, 3, 6)
    (:func:`measurement_jacobians` of the predicted landmarks), ``y`` (m, n, 3), ``W`` (n, 3, 3)."""
    m, k = H.shape[0], 3 * H.shape[1]
    Hs = H.reshape(m, k, 6)
    WH = (W @ H).reshape(m, k, 6)  # stacked W_i H_i
    Wy = (W @ y[..., None]).reshape(m, 1, k)  # stacked (W_i y_i)'
    A: Array = Hs.transpose(0, 2, 1) @ WH  # sum H_i' W_i H_i
    b: Array = (Wy @ Hs)[:, 0]  # sum (H_i' W_i y_i)'
    c: Array = (Wy @ y.reshape(m, k, 1))[:, 0, 0]  # sum y_i' W_i y_i
    return A, b, c


def _information_sums_isotropic(q: Array, y: Array, w: Array) -> tuple[Array, Array, Array]:
    """:func:`information_sums` for ``W_i = w_i I3``: ``H'H = [[I, -Q], [Q, |q|^2 I - q q']]``
    and ``H'y = [y, q x y]``; the cross products are summed as ``vee(M - M')``, ``M = sum y q'``."""
    m = q.shape[0]
    qw = q * w[:, None]
    yw = y * w[:, None]
    Sqq = np.swapaxes(qw, 1, 2) @ q  # sum w q q'
    M = np.swapaxes(yw, 1, 2) @ q  # sum w y q'
    swq = qw.sum(axis=1)
    A = np.zeros((m, 6, 6))
    A[:, :3, :3] = float(w.sum()) * _I3
    Kq = skew_batch(swq)
    A[:, :3, 3:] = -Kq
    A[:, 3:, :3] = Kq
    A[:, 3:, 3:] = np.trace(Sqq, axis1=1, axis2=2)[:, None, None] * _I3 - Sqq
    b = np.empty((m, 6))
    b[:, :3] = yw.sum(axis=1)
    b[:, 3] = M[:, 2, 1] - M[:, 1, 2]
    b[:, 4] = M[:, 0, 2] - M[:, 2, 0]
    b[:, 5] = M[:, 1, 0] - M[:, 0, 1]
    c = np.sum(y * yw, axis=(1, 2))
    return A, b, c


def log_likelihoods(P_pose: Array, A: Array, b: Array, c: Array, logdet_R: float,
                    n: int) -> Array:
    """``log N(y; 0, S)`` of the stacked innovation for m hypotheses, ``S = H P H' + R``.

    From the information sums over the n landmarks (Woodbury, ``X = (I + A P)^-1``):
    ``y' S^-1 y = c - b' P X b`` and ``log det S = logdet_R + log det(I + A P)``; ``P_pose``
    (m, 6, 6), ``A`` (m, 6, 6), ``b`` (m, 6), ``c`` (m,), ``logdet_R = sum log det R_i``.
    """
    I_AP = _I6 + A @ P_pose
    u = np.linalg.solve(I_AP, b[:, :, None])[:, :, 0]  # X b = H' S^-1 y
    maha = c - (b * (P_pose @ u[:, :, None])[:, :, 0]).sum(axis=1)
    logdet_S = logdet_R + np.linalg.slogdet(I_AP)[1]
    ll: Array = -0.5 * (maha + logdet_S + 3 * n * _LOG_2PI)
    return ll


def mahalanobis_sq(S: Array, v: Array) -> tuple[Array, Array]:
    """``(v' S^-1 v, det S)`` for stacks of symmetric 3x3 ``S`` (..., 3, 3), ``v`` (..., 3).

    Cofactor formula (:func:`~services.tracker.landmarks.adjugate_sym3`): ``v' adj(S) v / det S``;
    only the upper triangle of ``S`` is read.
    """
    adj, det = adjugate_sym3(S)
    num = np.einsum("...i,...ij,...j->...", v, adj, v)
    out: Array = num / det
    return out, det


def prior_gate_passes(q: Array, y: Array, P_pose: Array, r: Array, threshold: float,
                      W: Array | None = None) -> BoolArray:
    """``sqrt(y_i' (H_i P H_i' + R_i)^-1 y_i) < threshold`` (m, n) for each hypothesis.

    ``q``, ``y`` (m, n, 3) predicted landmarks and innovations, ``P_pose`` (m, 6, 6), ``r`` the
    measurement covariances (n, 3, 3) or isotropic variances (n,), ``W`` their inverses
    (n, 3, 3) if the caller has them. ``S_i >= R_i``, so ``y_i' R_i^-1 y_i < threshold^2``
    already passes; the exact distance is computed only for the landmarks that fail this bound
    (usually none).
    """
    R = as_covariances(r)
    if W is None:
        d2_R, _ = mahalanobis_sq(R[None], y)
    else:
        d2_R = np.einsum("mni,nij,mnj->mn", y, W, y)
    ok: BoolArray = d2_R < threshold * threshold
    if not ok.all():
        mi, ni = np.nonzero(~ok)
        H = measurement_jacobians(q[mi, ni])
        S = H @ P_pose[mi] @ H.swapaxes(-1, -2) + R[ni]
        d2, _ = mahalanobis_sq(S, y[mi, ni])
        ok[mi, ni] = d2 < threshold * threshold
    return ok


def posterior_residuals(q: Array, y: Array, r: Array, P_pose: Array, A: Array, b: Array
                        ) -> tuple[Array, Array]:
    """Leave-one-out residuals of n landmarks: ``(e, C)``, ``e`` (n, 3), ``C`` (n, 3, 3).

    For a linear-Gaussian update, the innovation of landmark i against its prediction from the
    prior and all *other* landmarks, standardised, equals the standardised posterior residual:
    ``d_i^2 = e_i' C_i^-1 e_i`` with ``e_i = y_i - H_i delta`` and ``C_i = R_i - H_i Sigma H_i'``
    (``delta``, ``Sigma``: posterior mean and covariance of the pose error given every landmark
    in ``A``, ``b``), so no per-landmark refit is needed. ``q``, ``y`` (n, 3) predicted landmarks
    and innovations, ``r`` covariances (n, 3, 3) or isotropic variances (n,).
    """
    return _posterior_residuals(measurement_jacobians(q), y, r, P_pose, A, b)


def _posterior_residuals(H: Array, y: Array, r: Array, P_pose: Array, A: Array, b: Array
                         ) -> tuple[Array, Array]:
    """:func:`posterior_residuals` from the measurement Jacobians ``H`` (n, 3, 6)."""
    sol = np.linalg.solve(_I6 + A @ P_pose, np.concatenate((b[:, None], A), axis=1))
    PX = P_pose @ sol
    delta = PX[:, 0]  # P X b
    Sigma = P_pose - PX[:, 1:] @ P_pose  # P - P X A P
    e = y - H @ delta  # y - H delta
    C = as_covariances(r) - H @ Sigma @ H.swapaxes(-1, -2)
    return e, C


def posterior_residual_passes(q: Array, y: Array, r: Array, P_pose: Array, A: Array, b: Array,
                              threshold: float) -> BoolArray:
    """Leave-one-out gate (n,): is each landmark within ``threshold`` of its prediction from the
    prior and all *other* landmarks? (:func:`posterior_residuals`.) A landmark that alone pins
    part of the pose (``C_i`` singular) passes: there is nothing to compare it with."""
    return posterior_residual_passes_from_jacobians(measurement_jacobians(q), y, r, P_pose, A, b, threshold)


def posterior_residual_passes_from_jacobians(H: Array, y: Array, r: Array, P_pose: Array,
                                             A: Array, b: Array, threshold: float) -> BoolArray:
    """:func:`posterior_residual_passes` from the measurement Jacobians ``H`` (n, 3, 6)."""
    e, C = _posterior_residuals(H, y, r, P_pose, A, b)
    d2, det = mahalanobis_sq(C, e)
    ok: BoolArray = (det <= 0.0) | (d2 < threshold * threshold)
    return ok


__all__ = [
    "as_covariances",
    "information_sums",
    "information_sums_from_jacobians",
    "log_likelihoods",
    "mahalanobis_sq",
    "measurement_jacobians",
    "posterior_residual_passes",
    "posterior_residual_passes_from_jacobians",
    "posterior_residuals",
    "predicted_points",
    "prior_gate_passes",
]
