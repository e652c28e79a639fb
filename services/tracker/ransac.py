"""Probabilistic initialisation of the hand body: weighted RANSAC over landmark motion (§III.B).

The tracker keeps the last ``init_window_frames`` frames of filtered landmark positions and their
``R_rb`` covariances. :func:`rigid_ransac` looks for the rigid motion that carries the landmarks
from the first to the last frame of that window:

- minimal sets of 3 landmarks are drawn without replacement with probability proportional to
  ``trace(R_rb)^-1`` (Gumbel top-k, all iterations at once);
- each hypothesis (batched Kabsch) scores every landmark by the Mahalanobis residual
  ``d_i = sqrt(r_i' (R_end,i + R R_start,i R')^-1 r_i) = |r_i| / sqrt(r_end,i + r_start,i)``,
  ``r_i = x_end,i - (R x_start,i + t)`` (the ``R_rb`` are isotropic, ``r I3``), with a truncated
  quadratic (MSAC) cost ``sum min(d_i^2, thr^2)``;
- the best hypothesis is refit by weighted Kabsch on its inliers (weights ``trace^-1``).

With the ablation (uniform ``R_rb``) the sampling and the residual weights are uniform.

Hand body frame (:func:`initial_body`): origin at the centroid of the inlier landmarks at the
last window frame, axes parallel to the tracking frame (OMIP's convention;
docs/estimation.md#hand-body-frame). Why not a palm frame: it would need particular landmarks (the
wrist is excluded, MCPs can be occluded or outliers), while this one exists for any inlier set; the
joint parameters estimated downstream are expressed in the reference frame and do not depend on the
body frame (docs/estimation.md#joint-measurement); and a
centroid origin decorrelates the translation and rotation blocks of the pose covariance. Each
inlier's body-frame coordinates are fixed at initialisation (averaged over the window after
aligning every frame to the last one, which divides their noise by up to sqrt(window)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.kabsch import batched_kabsch, weighted_kabsch
from services.common.se3 import pose_from_rotation_translation, se3_log

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.intp]

# Minimal sets whose triangle is smaller than this (m^2) are degenerate (collinear) and skipped.
_MIN_TRIANGLE_AREA_M2 = 1e-8


@dataclass(frozen=True, eq=False)
class RansacResult:
    """Rigid motion ``x_end ~= rotation @ x_start + translation`` and its inliers (n,)."""

    rotation: Array
    translation: Array
    inliers: BoolArray
    cost: float

    @property
    def transform(self) -> Array:
        """The motion as a 4x4 pose (maps window-start positions to window-end positions)."""
        return pose_from_rotation_translation(self.rotation, self.translation)


def weighted_triplets(weights: Array, k: int, rng: np.random.Generator) -> IntArray:
    """k rows of 3 distinct indices, each row drawn without replacement with P ~ weights.

    Gumbel top-k: the 3 largest of ``log w + Gumbel noise`` are a weighted draw without replacement.
    """
    keys = np.log(weights)[None, :] + rng.gumbel(size=(k, weights.size))
    return np.argpartition(-keys, 2, axis=1)[:, :3]


def mahalanobis_residuals(R: Array, t: Array, src: Array, dst: Array, var_src: Array,
                          var_dst: Array) -> Array:
    """``d`` (k, n) of n correspondences under k motions (k, 3, 3), (k, 3).

    ``d_i = |dst_i - (R src_i + t)| / sqrt(var_src_i + var_dst_i)`` for isotropic point
    covariances ``var I3`` (a rotation leaves them unchanged).
    """
    res = dst[None] - (src @ np.swapaxes(R, 1, 2) + t[:, None, :])
    d: Array = np.sqrt(np.sum(res * res, axis=2) / (var_src + var_dst)[None])
    return d


def rigid_ransac(src: Array, dst: Array, var_src: Array, var_dst: Array, *, iterations: int,
                 threshold: float, refinements: int, rng: np.random.Generator
                 ) -> RansacResult | None:
    """Weighted RANSAC for the rigid motion carrying ``src`` (n, 3) onto ``dst`` (n, 3).

    ``var_src``/``var_dst`` (n,) are the points' per-axis variances (``R_rb = r I3``); the
    sampling weights ``trace(R_rb)^-1`` and the residual weights derive from them. Returns None
    with fewer than 3 points or when no non-degenerate hypothesis has 3 inliers.
    """
    n = src.shape[0]
    if n < 3:
        return None
    weights = 1.0 / (3.0 * var_dst)
    idx = weighted_triplets(weights, iterations, rng)
    a, b = src[idx], dst[idx]  # (k, 3, 3): k triplets of points
    area2 = np.minimum(
        np.sum(np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0]) ** 2, axis=1),
        np.sum(np.cross(b[:, 1] - b[:, 0], b[:, 2] - b[:, 0]) ** 2, axis=1))
    good = area2 > (2.0 * _MIN_TRIANGLE_AREA_M2) ** 2
    if not good.any():
        return None
    R, t = batched_kabsch(a[good], b[good])
    d = mahalanobis_residuals(R, t, src, dst, var_src, var_dst)
    cost = np.minimum(d * d, threshold * threshold).sum(axis=1)
    best = int(np.argmin(cost))
    R_best, t_best = R[best], t[best]
    inliers = d[best] < threshold
    if inliers.sum() < 3:
        return None
    d_best = d[best]
    refit_weights = 1.0 / (var_src + var_dst)
    for _ in range(refinements):
        R_new, t_new = weighted_kabsch(src[inliers], dst[inliers], refit_weights[inliers])
        d_new = mahalanobis_residuals(R_new[None], t_new[None], src, dst, var_src, var_dst)[0]
        inliers_new = d_new < threshold
        if inliers_new.sum() < 3:
            break
        converged = bool(np.array_equal(inliers_new, inliers))
        R_best, t_best, inliers, d_best = R_new, t_new, inliers_new, d_new
        if converged:
            break
    final_cost = float(np.minimum(d_best * d_best, threshold * threshold).sum())
    return RansacResult(rotation=R_best, translation=t_best, inliers=inliers, cost=final_cost)


@dataclass(frozen=True, eq=False)
class InitialBody:
    """A freshly initialised hand body.

    ``T_frame_body``: 4x4, identity rotation, origin at the inlier centroid (tracking frame).
    ``points_body``: (21, 3) body-frame coordinates of the inlier landmarks, NaN elsewhere.
    ``twist``: (6,) left (spatial) twist of the window's motion, linear first.
    """

    T_frame_body: Array
    points_body: Array
    twist: Array


def initial_body(positions: Array, variances: Array, valid: Array, stamps_s: Array,
                 inliers: BoolArray, motion: Array) -> InitialBody:
    """Body frame and landmark coordinates from a window of W frames.

    ``positions`` (W, 21, 3), per-axis ``variances`` (W, 21), ``valid`` (W, 21) over the window,
    ``stamps_s`` (W,) in seconds; ``inliers`` (21,) the RANSAC inliers (valid in the last frame);
    ``motion`` the 4x4 RANSAC motion from the first to the last frame.

    Each window frame with >= 3 valid inliers is aligned onto the last frame (weighted Kabsch
    over the inliers present in both), and every inlier's aligned positions are averaged.
    """
    last = positions[-1]
    weights = 1.0 / variances
    sums = np.zeros((positions.shape[1], 3))
    counts = np.zeros(positions.shape[1])
    for k in range(positions.shape[0]):
        common = inliers & valid[k] & valid[-1]
        if common.sum() < 3:
            continue
        R, t = weighted_kabsch(positions[k, common], last[common], weights[-1, common])
        mapped = positions[k] @ R.T + t
        use = inliers & valid[k]
        sums[use] += mapped[use]
        counts[use] += 1.0
    averaged = np.full_like(last, np.nan)
    have = inliers & (counts > 0)
    averaged[have] = sums[have] / counts[have, None]
    centroid = averaged[have].mean(axis=0)
    T = np.eye(4)
    T[:3, 3] = centroid
    points_body = np.where(have[:, None], averaged - centroid, np.nan)
    span = float(stamps_s[-1] - stamps_s[0])
    twist = se3_log(motion) / span if span > 0.0 else np.zeros(6)
    return InitialBody(T_frame_body=T, points_body=points_body, twist=twist)


__all__ = [
    "InitialBody",
    "RansacResult",
    "initial_body",
    "mahalanobis_residuals",
    "rigid_ransac",
    "weighted_triplets",
]
