"""Landmark level: one constant-velocity Kalman filter per hand landmark, batched over landmarks.

Paper §III.A. Each filter has the state ``x = [l, m]`` (position in m, velocity in m/s, both in the
tracking frame), ``F = [[I, dt I], [0, I]]``, ``H = [I, 0]``, noise ``P0``, ``Q``, ``R`` from
:class:`TrackerConfig`. Every array is stacked over the N landmarks of all hand slots (21 per
hand), so a frame costs a fixed number of numpy calls with no Python loop over landmarks.

Isotropy: ``P0``, ``Q`` and ``R = r_lm I3`` are all multiples of ``I3`` per block, and rotating
``R`` into the world frame (``R_wc R R_wc'``) leaves it unchanged, so every filter's 6x6
covariance stays exactly ``kron(C, I3)`` with a 2x2 per-axis covariance
``C = [[pp, pv], [pv, vv]]``. The bank stores ``C`` (as three arrays) and runs the textbook
equations in that form; :meth:`LandmarkFilterBank.covariance` rebuilds the 6x6 ``P``.
The tests check it against a plain 6x6 Kalman filter.

Per frame, for each landmark: predict (every filter), then

- no measurement (NaN, or visibility below the threshold): the correction is skipped;
- Mahalanobis distance ``M = sqrt(y' S^-1 y) >= M_lm``: outlier, the correction is skipped;
- otherwise: Kalman correction, Joseph form;
- a filter whose position covariance trace reaches the loss threshold is dropped;
- a measured landmark without a filter (new, or dropped earlier) starts a filter at the
  measurement with ``P0`` and zero velocity. A landmark dropped in this frame waits for its next
  measurement (this frame's measurement was just judged an outlier, or was missing).

The body level uses the filtered positions with ``R_rb = s_k P_lm`` (saliency factor times the
position block of the filter covariance), an isotropic variance per landmark, see
:func:`body_measurement_variances`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from services.tracker.config import TrackerConfig

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

NUM_LANDMARKS = 21
WRIST = 0


@dataclass(frozen=True, eq=False)
class LandmarkUpdate:
    """What happened to each landmark row in one :meth:`LandmarkFilterBank.update` call.

    ``fresh``: the filter holds this frame's measurement (corrected or just started).
    ``rejected``: a measurement arrived but was gated out as an outlier (correction skipped).
    ``dropped``: the filter was removed this frame (covariance reached the loss threshold).
    ``mahalanobis``: ``sqrt(y' S^-1 y)`` of the measurement, NaN where none was gated.
    """

    fresh: BoolArray
    rejected: BoolArray
    dropped: BoolArray
    mahalanobis: Array


class LandmarkFilterBank:
    """N constant-velocity KFs, state ``x`` (N, 6) = [position, velocity] per landmark.

    Covariance per row: ``P = kron([[pp, pv], [pv, vv]], I3)`` with ``pp``, ``pv``, ``vv`` (N,)
    (m^2, m^2/s, m^2/s^2); ``alive`` (N,) marks rows that hold a filter.
    """

    def __init__(self, n: int, config: TrackerConfig) -> None:
        self.n = n
        self.config = config
        self.x: Array = np.zeros((n, 6))
        self.pp: Array = np.zeros(n)
        self.pv: Array = np.zeros(n)
        self.vv: Array = np.zeros(n)
        self.alive: BoolArray = np.zeros(n, dtype=bool)
        self._prior = (self.x.copy(), self.pp, self.pv, self.vv, self.alive.copy())
        self.reset()

    def reset(self) -> None:
        """Drop every filter."""
        self.x[:] = 0.0
        self.pp[:] = self.config.p0_lm_position_m2
        self.pv[:] = 0.0
        self.vv[:] = self.config.p0_lm_velocity_m2ps2
        self.alive[:] = False

    def predict(self, dt_s: float) -> None:
        """``x = F x``, ``P = F P F' + Q dt / dt_nominal`` for every row (dead rows are inert).

        Per axis, with ``F = [[1, dt], [0, 1]]``: ``pp += 2 dt pv + dt^2 vv + q_p``,
        ``pv += dt vv``, ``vv += q_v``.
        """
        scale = dt_s / self.config.nominal_dt_s
        self.x[:, :3] += dt_s * self.x[:, 3:]
        self.pp += (2.0 * dt_s) * self.pv + (dt_s * dt_s) * self.vv
        self.pp += self.config.q_lm_position_m2 * scale
        self.pv += dt_s * self.vv
        self.vv += self.config.q_lm_velocity_m2ps2 * scale

    def update(self, z: Array, r_m2: float, gate: bool = True,
               v_start: Array | None = None) -> LandmarkUpdate:
        """Correct with measurements ``z`` (N, 3), NaN rows = missing, noise ``R = r_m2 I3``.

        ``gate=False`` (the ablation) accepts every measurement. ``v_start`` (N, 3): initial
        velocities of filters started in this call (default 0).
        """
        measured: BoolArray = np.all(np.isfinite(z), axis=1)
        z0 = np.where(measured[:, None], z, 0.0)
        was_alive = self.alive.copy()
        active = measured & was_alive
        pp, pv, vv = self.pp, self.pv, self.vv
        self._prior = (self.x.copy(), pp, pv, vv, was_alive)

        y = z0 - self.x[:, :3]  # y = z - H x
        S = pp + r_m2  # S = H P H' + R (per axis)
        d = np.sqrt(np.einsum("ni,ni->n", y, y) / S)  # sqrt(y' S^-1 y)
        mahalanobis = np.where(active, d, np.nan)
        rejected: BoolArray = np.zeros_like(active)
        if gate:
            rejected = active & (d >= self.config.mahalanobis_lm)
        correct = active & ~rejected

        kp = np.where(correct, pp / S, 0.0)  # K = P H' S^-1 = [kp, kv] per axis
        kv = np.where(correct, pv / S, 0.0)
        self.x[:, :3] += kp[:, None] * y  # x = x + K y
        self.x[:, 3:] += kv[:, None] * y
        # Joseph form P = (I - K H) P (I - K H)' + K R K' with I - K H = [[1 - kp, 0], [-kv, 1]].
        a = 1.0 - kp
        pv_kv = pv - kv * pp
        self.vv = vv - kv * pv - kv * pv_kv + kv * kv * r_m2
        self.pv = a * pv_kv + kp * kv * r_m2
        self.pp = a * a * pp + kp * kp * r_m2

        dropped = was_alive & (3.0 * self.pp >= self.config.lm_loss_trace_m2)
        self.alive &= ~dropped

        start = measured & ~was_alive
        if start.any():
            self.x[start, :3] = z0[start]
            self.x[start, 3:] = 0.0 if v_start is None else v_start[start]
            self.pp[start] = self.config.p0_lm_position_m2
            self.pv[start] = 0.0
            self.vv[start] = self.config.p0_lm_velocity_m2ps2
            self.alive |= start
        return LandmarkUpdate(fresh=correct | start, rejected=rejected, dropped=dropped,
                              mahalanobis=mahalanobis)

    def reject(self, rows: BoolArray) -> BoolArray:
        """Undo this frame's correction of ``rows``, judged outliers by a higher level.

        The rows return to their predicted state, as if the landmark gate had rejected their
        measurement, and are dropped if that covariance reaches the loss threshold; a filter that
        this frame's (outlier) measurement had just started is removed. Returns the dropped rows.
        Call after :meth:`update`, before the next :meth:`predict`.
        """
        x_prior, pp, pv, vv, was_alive = self._prior
        self.x[rows] = x_prior[rows]
        self.pp = np.where(rows, pp, self.pp)
        self.pv = np.where(rows, pv, self.pv)
        self.vv = np.where(rows, vv, self.vv)
        lost = 3.0 * self.pp >= self.config.lm_loss_trace_m2
        dropped = rows & self.alive & (lost | ~was_alive)
        self.alive &= ~dropped
        return dropped

    def positions(self) -> Array:
        """Filtered positions (N, 3); NaN rows where no filter is alive."""
        return np.where(self.alive[:, None], self.x[:, :3], np.nan)

    def position_variances(self) -> Array:
        """Per-axis position variance ``pp`` (N,): ``P_lm = pp I3`` (meaningful where alive)."""
        return self.pp.copy()

    def covariance(self, row: int) -> Array:
        """The full 6x6 covariance of one row, ``kron([[pp, pv], [pv, vv]], I3)``."""
        C = np.array([[self.pp[row], self.pv[row]], [self.pv[row], self.vv[row]]])
        return np.kron(C, np.eye(3))


def missing_mask(points: Array, visibility: Array, visibility_threshold: float) -> BoolArray:
    """Landmarks without a usable measurement: any non-finite coordinate or B_vis < threshold."""
    return ~np.isfinite(points).all(axis=-1) | ~(visibility >= visibility_threshold)


def body_landmark_mask(config: TrackerConfig) -> BoolArray:
    """(21,) landmarks the body level may use: all but the wrist with the uncertainty models."""
    mask = np.ones(NUM_LANDMARKS, dtype=bool)
    if config.use_uncertainty_models:
        mask[WRIST] = False
    return mask


def body_measurement_variances(pp: Array, config: TrackerConfig) -> Array:
    """Per-axis variance ``r_i`` (21,) of ``R_rb,i = r_i I3`` for one hand's filtered landmarks.

    With the uncertainty models: ``R_rb,k = s_k P_lm,k`` (saliency factor times the filter's
    position covariance ``pp I3``; the wrist row carries ``P_lm`` unscaled but is excluded by
    :func:`body_landmark_mask`). Without (ablation): the detector noise ``r_lm`` for every
    landmark (uniform).
    """
    if not config.use_uncertainty_models:
        return np.full(NUM_LANDMARKS, config.r_lm_m2)
    factors: Array = _saliency_array(config) * pp
    return factors


@lru_cache(maxsize=8)
def _saliency_array(config: TrackerConfig) -> Array:
    s = np.asarray(config.saliency_factors(), dtype=float)
    s.flags.writeable = False
    return s


def inv_sym3(S: Array) -> tuple[Array, Array]:
    """Inverse and determinant of a stack of symmetric 3x3 matrices (..., 3, 3), by cofactors.

    Only the upper triangle is read; callers pass positive-definite matrices.
    """
    a, b, c = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    d, e, f = S[..., 1, 1], S[..., 1, 2], S[..., 2, 2]
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    det = a * c00 + b * c01 + c * c02
    inv = np.empty(S.shape)
    inv[..., 0, 0] = c00
    inv[..., 0, 1] = inv[..., 1, 0] = c01
    inv[..., 0, 2] = inv[..., 2, 0] = c02
    inv[..., 1, 1] = a * f - c * c
    inv[..., 1, 2] = inv[..., 2, 1] = b * c - a * e
    inv[..., 2, 2] = a * d - b * b
    inv /= det[..., None, None]
    return inv, det


__all__ = [
    "NUM_LANDMARKS",
    "WRIST",
    "LandmarkFilterBank",
    "LandmarkUpdate",
    "body_landmark_mask",
    "body_measurement_variances",
    "inv_sym3",
    "missing_mask",
]
