"""The hand body model: body-frame landmark coordinates, refined and completed while tracking.

The body-frame coordinates ``p_i`` (21, 3) fixed at initialisation (``ransac.initial_body``)
come from a few frames of noisy landmarks and from the RANSAC inliers only.
:meth:`BodyTemplate.refine` averages every well-fitting landmark's observation into its
coordinates, lets landmarks outside the model join it at the :func:`robust_centre` of their
observations, and keeps the body frame where it was.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from services.common.kabsch import weighted_kabsch
from services.tracker.config import TrackerConfig
from services.tracker.landmarks import NUM_LANDMARKS

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_CHI2_3_99 = 11.345  # 99 % point of the chi-square distribution with 3 degrees of freedom


def robust_centre(points: Array) -> Array:
    """A robust, rotation-equivariant centre (3,) of observations ``points`` (k, 3): the mean of
    the half closest to the medoid (the observation with the least summed distance to the
    others). Breakdown point 50 %, unlike the mean; unlike a coordinate-wise median it does not
    depend on the orientation of the frame, so the body model does not either."""
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2)
    medoid = points[int(np.argmin(d.sum(axis=1)))]
    near = np.argsort(np.linalg.norm(points - medoid, axis=1))[:max(1, (len(points) + 1) // 2)]
    out: Array = points[near].mean(axis=0)
    return out


class BodyTemplate:
    """The body model of one initialised hand body.

    ``points`` (21, 3): body-frame coordinates ``p_i`` (m), NaN for landmarks not in the model;
    ``in_model`` (21,): its finite rows. ``counts`` (21,): frames averaged into each landmark so
    far (the initialisation window's frames for its inliers, 0 elsewhere). ``config``: the
    tracker's config in physical units (``TrackerConfig.internal``).
    """

    def __init__(self, points_body: Array, counts: Array, config: TrackerConfig) -> None:
        self._cfg = config
        self.points = points_body
        self.in_model: BoolArray = np.isfinite(points_body).all(axis=1)
        self._count = counts
        self._candidates = np.full((NUM_LANDMARKS, max(1, config.template_candidate_frames), 3),
                                   np.nan)
        self._candidate_count = np.zeros(NUM_LANDMARKS, dtype=np.intp)

    def refine(self, T_frame_body: Array, positions: Array, accepted: NDArray[np.intp],
               d2: Array, newcomers: BoolArray) -> bool:
        """Refine the model with this frame's landmarks (after the body correction); True when a
        landmark joined it (``in_model`` then changed).

        ``T_frame_body`` (4, 4): the corrected body pose; ``positions`` (21, 3): the filtered
        landmarks in the tracking frame; ``accepted``: indices of the landmarks the body
        accepted, ``d2`` (n,) their posterior ``r' R_rb^-1 r``
        (:func:`~services.tracker.calibration.fit_residuals`); ``newcomers`` (21,): measured
        landmarks outside the model.

        Each frame, every landmark the body accepted whose posterior residual is also well inside
        its modelled noise (``r' R_rb^-1 r`` below the chi-square 99 % point for 3 DOF: the model
        is a long-term average and takes no borderline outlier that slipped through the wider
        Table-I gates) adds its observation ``T^-1 z_i`` to a running mean of up to
        ``template_memory_frames`` frames; a measured landmark outside the model collects
        observations, and joins the model at their :func:`robust_centre` (robust to the depth
        outliers among them) after ``template_candidate_frames``. The refined model is then
        aligned to the previous one (weighted Kabsch over the previous model's landmarks), so
        only its shape changes: the body frame, and with it the published poses, does not drift
        with the refinement.
        """
        cfg = self._cfg
        if cfg.template_memory_frames <= 0:
            return False
        old = self.points
        R_T, t_T = T_frame_body[:3, :3], T_frame_body[:3, 3]
        obs = (positions - t_T) @ R_T  # T^-1 z, row-wise
        new = old.copy()
        if accepted.size and cfg.outlier_gates:  # an outlier gate (TrackerConfig.outlier_gates)
            accepted = accepted[d2 < _CHI2_3_99]
        if accepted.size:
            n = np.minimum(self._count[accepted] + 1.0, cfg.template_memory_frames)
            new[accepted] += (obs[accepted] - old[accepted]) / n[:, None]
            self._count[accepted] = n
        joined = False
        k = cfg.template_candidate_frames
        if k > 0 and newcomers.any():
            for j in np.flatnonzero(newcomers & np.isfinite(obs).all(axis=1)):
                self._candidates[j, self._candidate_count[j] % k] = obs[j]
                self._candidate_count[j] += 1
                if self._candidate_count[j] >= k:
                    new[j] = robust_centre(self._candidates[j])
                    self._count[j] = float(k)
                    joined = True
        model = self.in_model
        count = int(model.sum())
        if count >= 3:
            R, t = weighted_kabsch(new[model], old[model], np.ones(count))
            new = new @ R.T + t
        self.points = new
        if joined:
            self.in_model = np.isfinite(new).all(axis=1)
        return joined


__all__ = ["BodyTemplate", "robust_centre"]
