"""Kabsch: the proper rigid motion that best aligns corresponding 3-D point sets.

``weighted_kabsch(src, dst, w)`` returns ``(R, t)`` minimising ``sum w_i |R src_i + t - dst_i|^2``
over rotations (reflections excluded) and translations; ``batched_kabsch`` does the same, with
uniform weights, for a stack of point sets at once. Points are rows (n, 3) in one frame, lengths
in any unit (``t`` comes out in the same unit). The one implementation for the tracker
(RANSAC hypotheses, refits, template alignment) and the evaluation baselines.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def _rotation_from_cross_covariance(C: Array) -> Array:
    """Proper rotations R maximising trace(R C') for a stack (..., 3, 3) of cross-covariances.

    ``C = sum w (dst - dst_bar)(src - src_bar)'``; the SVD ``C = U S V'`` gives
    ``R = U diag(1, 1, det(U V')) V'`` (Kabsch/Umeyama, reflection excluded).
    """
    U, _, Vt = np.linalg.svd(C)
    R: Array = U @ Vt
    if C.ndim == 2:  # one matrix: the sign of det(U V') on floats, a second product if negative
        (a, b, c), (d, e, f), (g, h, i) = R.tolist()
        if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0.0:
            U[:, 2] = -U[:, 2]
            R = U @ Vt
        return R
    d = np.sign(np.linalg.det(R))
    U[..., :, 2] *= np.where(d == 0.0, 1.0, d)[..., None]
    R = U @ Vt
    return R


def weighted_kabsch(src: Array, dst: Array, weights: Array) -> tuple[Array, Array]:
    """(R, t) minimising ``sum w_i |R src_i + t - dst_i|^2`` for (n, 3) points, n >= 3."""
    w = weights / weights.sum()
    src_bar = w @ src
    dst_bar = w @ dst
    C = ((dst - dst_bar) * w[:, None]).T @ (src - src_bar)
    R = _rotation_from_cross_covariance(C)
    return R, dst_bar - R @ src_bar


def batched_kabsch(src: Array, dst: Array) -> tuple[Array, Array]:
    """(R (k, 3, 3), t (k, 3)) for k sets of corresponding points (k, m, 3), uniform weights."""
    src_bar = src.mean(axis=1)
    dst_bar = dst.mean(axis=1)
    C = np.einsum("kmi,kmj->kij", dst - dst_bar[:, None], src - src_bar[:, None])
    R = _rotation_from_cross_covariance(C)
    return R, dst_bar - np.einsum("kij,kj->ki", R, src_bar)
