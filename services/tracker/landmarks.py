"""Landmark level: one constant-velocity Kalman filter per hand landmark, batched over landmarks.

Paper §III.A. Each filter has the state ``x = [l, m]`` (position, velocity, both in the tracking
frame), ``F = [[I, dt I], [0, I]]``, ``H = [I, 0]``, noise ``P0``, ``Q``, ``R`` from
:class:`TrackerConfig` (covariances in Table-I units, see the config docstring). Every array is
stacked over the N landmarks of all hand slots (21 per hand), so a frame costs a fixed number of
numpy calls with no Python loop over landmarks.

Covariance: each filter keeps its full 6x6 ``P`` (``P`` (N, 6, 6)), because the measurement
noise need not be isotropic: a back-projected RGB-D landmark is located in the image far better
than along its viewing ray (the depth read at the detected pixel may be the background or an
occluder, see :func:`ray_measurement_covariances`). With an isotropic ``R = r I3`` every
``P`` stays ``kron(C, I3)`` with a 2x2 per-axis ``C = [[pp, pv], [pv, vv]]``; :attr:`pp`,
:attr:`pv`, :attr:`vv` report the per-axis mean of each block (exactly ``C`` in that case).
The tests check the bank against a plain 6x6 Kalman filter.

Per frame, for each landmark: predict (every filter), then

- no measurement (NaN, or visibility below the threshold): the correction is skipped;
- Mahalanobis distance ``M = sqrt(y' S^-1 y) >= M_lm`` (6.0 sigma of the innovation in the
  physical units of ``TrackerConfig.internal``, ~9 cm at 30 Hz): outlier, the correction is
  skipped;
- otherwise: Kalman correction, Joseph form;
- a filter whose position covariance trace reaches the loss threshold is dropped;
- a measured landmark without a filter starts a filter at the measurement with ``P0`` and zero
  velocity (or the caller's start velocity). A landmark dropped in this frame waits for its next
  measurement (this frame's measurement was just judged an outlier, or was missing).
- **Restart gate.** With Table I one skipped correction drops a filter; without a gate, an
  outlier that follows a miss would start a filter wherever it lies. A dropped filter that was
  *confirmed* (``lm_confirm_corrections`` corrections since it started) keeps predicting, its
  covariance growing by ``Q_lm`` every frame, and its landmark restarts only on a measurement
  within the landmark gate ``M_lm`` of that prediction; a landmark that really moved is
  re-acquired as the gate widens. An unconfirmed filter is no reference: one born from an
  outlier (a depth read on the background, tens of cm behind) refuses the correct measurements
  that follow and is lost, and gating its restart against its own prediction would lock the
  landmark out (measured: tuning-split mean 5.2 -> 6.4 deg with every filter gated, 5.2 with
  confirmed ones; the refused restarts are then outliers, a median 34 cm from the true landmark
  against 1.7 cm for the lost filter's prediction). Landmarks without a confirmed past (since
  :meth:`LandmarkFilterBank.reset` or :meth:`LandmarkFilterBank.forget`) start ungated, and so
  does every landmark in the ablation.

The body level uses the filtered positions with ``R_rb = s_k P_lm + a_k I3`` (saliency factor
times the position block of the filter covariance, plus the articulation variance of the
landmark), see :func:`body_measurement_covariances` and :func:`articulation_variances`.

With an anisotropic ``R`` the loss threshold scales with ``trace(R) / (3 r_lm)`` (at least 1), so
that a filter whose covariance is large only along the viewing ray is not taken for a lost one.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import NUM_LANDMARKS
from services.tracker.config import TrackerConfig

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

WRIST = 0

_I3 = np.eye(3)
_I6 = np.eye(6)

# Parent of each landmark in the MediaPipe hand skeleton (the wrist is the root).
PARENT: tuple[int, ...] = (0, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)
# Landmarks rigidly attached to the palm (wrist, thumb CMC, the four finger MCPs); every other
# landmark sits distal to at least one articulated joint.
PALM: tuple[int, ...] = (0, 1, 5, 9, 13, 17)


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

    ``P`` (N, 6, 6) covariance per row; ``alive`` (N,) marks rows that hold a filter;
    ``corrections`` (N,) the corrections of each filter since it started; ``has_past`` (N,) rows
    whose state is the prediction of a confirmed filter that was dropped (their restarts are
    gated, module docstring).
    """

    def __init__(self, n: int, config: TrackerConfig) -> None:
        self.n = n
        self.config = config
        self.x: Array = np.zeros((n, 6))
        self.P: Array = np.zeros((n, 6, 6))
        self.alive: BoolArray = np.zeros(n, dtype=bool)
        self.has_past: BoolArray = np.zeros(n, dtype=bool)
        self.corrections: NDArray[np.int64] = np.zeros(n, dtype=np.int64)
        self._P0 = np.diag([config.p0_lm_position_m2] * 3 + [config.p0_lm_velocity_m2ps2] * 3)
        self._Q = np.diag([config.q_lm_position_m2] * 3 + [config.q_lm_velocity_m2ps2] * 3)
        self._F = np.eye(6)  # the transition of the last predict() (its dt block is set there)
        self._prior = (self.x.copy(), self.P.copy(), self.alive.copy(), self.has_past.copy(),
                       self.corrections.copy())
        # (z, R, loss threshold) of the last update, for reject()
        self._last: tuple[Array, Array, Array] | None = None
        self.reset()

    def reset(self) -> None:
        """Drop every filter."""
        self.x[:] = 0.0
        self.P[:] = self._P0
        self.alive[:] = False
        self.has_past[:] = False
        self.corrections[:] = 0
        self._last = None

    def snapshot(self) -> tuple[Array, ...]:
        """A copy of every filter's state, for :meth:`restore`."""
        return (self.x.copy(), self.P.copy(), self.alive.copy(), self.has_past.copy(),
                self.corrections.copy())

    def restore(self, snapshot: tuple[Array, ...], rows: BoolArray) -> None:
        """Put the filters of ``rows`` back to their state in ``snapshot``."""
        x, P, alive, has_past, corrections = snapshot
        self.x[rows], self.P[rows], self.alive[rows] = x[rows], P[rows], alive[rows]
        self.has_past[rows], self.corrections[rows] = has_past[rows], corrections[rows]

    def forget(self, rows: BoolArray) -> None:
        """Drop the filters of ``rows`` and their past: their next measurements start new
        filters ungated (a new hand in those rows)."""
        self.x[rows] = 0.0
        self.P[rows] = self._P0
        self.alive &= ~rows
        self.has_past &= ~rows
        self.corrections[rows] = 0

    # Per-axis views for isotropic use (exact when P = kron(C, I3)).
    @property
    def pp(self) -> Array:
        """Per-axis position variance (N,): ``trace(P_position) / 3``."""
        return np.einsum("nii->n", self.P[:, :3, :3]) / 3.0

    @property
    def pv(self) -> Array:
        """Per-axis position-velocity covariance (N,): ``trace(P_pv) / 3``."""
        return np.einsum("nii->n", self.P[:, :3, 3:]) / 3.0

    @property
    def vv(self) -> Array:
        """Per-axis velocity variance (N,): ``trace(P_velocity) / 3``."""
        return np.einsum("nii->n", self.P[:, 3:, 3:]) / 3.0

    def predict(self, dt_s: float) -> None:
        """``x = F x``, ``P = F P F' + Q dt / dt_nominal`` for every row (dead rows are inert),
        with ``F = [[I, dt I], [0, I]]`` (one batched product: fewer numpy calls than the
        block-wise update)."""
        F = self._F
        F[0, 3] = F[1, 4] = F[2, 5] = dt_s
        self.x[:, :3] += dt_s * self.x[:, 3:]
        self.P = F @ self.P @ F.T + self._Q * (dt_s / self.config.nominal_dt_s)

    def update(self, z: Array, R: float | Array, gate: bool = True,
               v_start: Array | None = None) -> LandmarkUpdate:
        """Correct with measurements ``z`` (N, 3), NaN rows = missing, noise ``R``.

        ``R``: a scalar ``r`` (``R = r I3`` for every row) or per-row covariances (N, 3, 3).
        ``gate=False`` (the ablation) accepts every measurement. ``v_start`` (N, 3): initial
        velocities of filters started in this call (default 0).
        """
        measured: BoolArray = np.isfinite(z).all(axis=1)
        z0 = np.where(measured[:, None], z, 0.0)
        Rn = _as_covariances(R, self.n)
        x, P = self.x, self.P
        was_alive = self.alive.copy()
        active = measured & was_alive
        self._prior = (x.copy(), P.copy(), was_alive, self.has_past.copy(),
                       self.corrections.copy())

        y = z0 - x[:, :3]  # y = z - H x
        S_inv, _ = inv_sym3(P[:, :3, :3] + Rn)  # S = H P H' + R
        d = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", y, S_inv, y), 0.0))  # sqrt(y' S^-1 y)
        mahalanobis = np.where(active, d, np.nan)
        if gate:
            rejected: BoolArray = active & (d >= self.config.mahalanobis_lm)
            correct = active & ~rejected
        else:
            rejected, correct = np.zeros_like(active), active
        self._correct(correct, y, S_inv, Rn)
        self.corrections[correct] += 1

        threshold = self._loss_threshold(Rn)
        self._last = (z0, Rn, threshold)
        dropped = was_alive & (self._position_trace() >= threshold)
        if dropped.any():
            self.alive &= ~dropped
            self.has_past |= dropped & (self.corrections >= self.config.lm_confirm_corrections)
            correct = correct & ~dropped

        start = measured & ~was_alive
        if gate:  # the restart gate (module docstring)
            refused = start & self.has_past & (d >= self.config.mahalanobis_lm)
            if refused.any():
                start = start & ~refused
                rejected = rejected | refused
                mahalanobis = np.where(refused, d, mahalanobis)
        if start.any():
            self.corrections[start] = 0
            self.has_past[start] = False
            x[start, :3] = z0[start]
            x[start, 3:] = 0.0 if v_start is None else v_start[start]
            P[start] = self._P0
            self.alive |= start
            correct = correct | start
        return LandmarkUpdate(fresh=correct, rejected=rejected, dropped=dropped,
                              mahalanobis=mahalanobis)

    def _correct(self, rows: BoolArray, y: Array, S_inv: Array, R: Array) -> None:
        """Kalman correction of ``rows``: ``K = P H' S^-1``, ``x += K y``, Joseph form
        ``P = (I - K H) P (I - K H)' + K R K'``, with ``H = [I, 0]``: ``M = (I - K H) P =
        P - K P[:3]`` and ``M (I - K H)' + K R K' = M - (M[:, :3] - K R) K'``."""
        if not rows.any():
            return
        P = self.P[rows]
        K = P[:, :, :3] @ S_inv[rows]  # (n, 6, 3)
        self.x[rows] += (K @ y[rows, :, None])[:, :, 0]
        M = P - K @ P[:, :3, :]  # (I - K H) P
        P = M - (M[:, :, :3] - K @ R[rows]) @ K.transpose(0, 2, 1)
        self.P[rows] = 0.5 * (P + P.transpose(0, 2, 1))

    def _position_trace(self) -> Array:
        P = self.P
        out: Array = P[:, 0, 0] + P[:, 1, 1] + P[:, 2, 2]
        return out

    def _loss_threshold(self, R: Array) -> Array:
        """Loss threshold per row (N,): ``lm_loss_trace`` scaled by ``trace(R) / (3 r_lm)``, the
        size of the row's measurement noise relative to the isotropic ``r_lm I3`` the threshold
        was set for (1 for isotropic noise), so a filter that is merely anisotropic (a large
        variance along the viewing ray) is not mistaken for a lost one."""
        ratio = (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]) * (1.0 / (3.0 * self.config.r_lm_m2))
        out: Array = self.config.lm_loss_trace_m2 * np.maximum(ratio, 1.0)
        return out

    def reject(self, rows: BoolArray) -> BoolArray:
        """Undo this frame's correction of ``rows``, judged outliers by a higher level.

        The rows return to their predicted state, as if the landmark gate had rejected their
        measurement, and are dropped if that covariance reaches the loss threshold; a filter that
        this frame's (outlier) measurement had just started is removed. Returns the dropped rows.
        Call after :meth:`update`, before the next :meth:`predict`.
        """
        x_prior, P_prior, was_alive, past_prior, corrections_prior = self._prior
        self.x[rows] = x_prior[rows]
        self.P[rows] = P_prior[rows]
        self.has_past[rows] = past_prior[rows]
        self.corrections[rows] = corrections_prior[rows]
        threshold = self.config.lm_loss_trace_m2 if self._last is None else self._last[2]
        lost = self._position_trace() >= threshold
        dropped = rows & self.alive & (lost | ~was_alive)
        self.alive &= ~dropped
        confirmed = self.corrections >= self.config.lm_confirm_corrections
        self.has_past |= dropped & was_alive & confirmed
        return dropped

    def positions(self) -> Array:
        """Filtered positions (N, 3); NaN rows where no filter is alive."""
        return np.where(self.alive[:, None], self.x[:, :3], np.nan)

    def position_covariances(self) -> Array:
        """Position covariances ``P_lm`` (N, 3, 3) (meaningful where alive)."""
        return self.P[:, :3, :3].copy()

    def position_variances(self) -> Array:
        """Per-axis position variance (N,), ``trace(P_lm) / 3`` (meaningful where alive)."""
        return self.pp

    def covariance(self, row: int) -> Array:
        """The full 6x6 covariance of one row."""
        return self.P[row].copy()


def _as_covariances(R: float | Array, n: int) -> Array:
    """``R`` as per-row covariances (n, 3, 3): a scalar is ``R I3`` for every row."""
    R_arr = np.asarray(R, dtype=float)
    if R_arr.ndim == 0:
        return np.broadcast_to(float(R_arr) * _I3, (n, 3, 3))
    if R_arr.shape != (n, 3, 3):
        raise ValueError(f"R must be a scalar or ({n}, 3, 3), got shape {R_arr.shape}")
    return R_arr


def ray_measurement_covariances(points: Array, r_m2: float, depth_factor: float) -> Array:
    """Measurement covariances (N, 3, 3) of back-projected landmarks in the camera frame.

    ``R_i = r (I - u_i u_i') + depth_factor r u_i u_i'`` with ``u_i`` the unit viewing ray of
    ``points`` (N, 3) (camera at the origin; rows with a NaN point get ``r I3``).

    Why: a landmark is a 2-D detection back-projected with the depth read at that pixel, so its
    error has two independent parts. Across the ray it is the 2-D error times depth over focal
    length; along the ray it is the depth error, which for thin fingers is heavy-tailed: a
    detection a few pixels off the digit reads the background behind it or the occluder in front,
    centimetres away, while the lateral error stays at the 2-D level. ``depth_factor = 1`` is
    the paper's isotropic ``R_lm = r I3``.
    """
    norm_sq = (points * points).sum(axis=1)
    ok = (norm_sq > 0.0) & (norm_sq < np.inf)  # False for NaN
    u = np.where(ok[:, None], points, 0.0) / np.sqrt(np.where(ok, norm_sq, 1.0))[:, None]
    R: Array = r_m2 * _I3 + ((depth_factor - 1.0) * r_m2) * (u[:, :, None] * u[:, None, :])
    return R


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
    """Per-axis variance ``r_i`` (21,) of an isotropic ``R_rb,i = r_i I3`` (Table-I units).

    With the uncertainty models: ``R_rb,k = s_k P_lm,k`` (saliency factor times the filter's
    per-axis position variance ``pp``; the wrist row carries ``P_lm`` unscaled but is excluded by
    :func:`body_landmark_mask`). Without (ablation): the detector noise ``r_lm`` for every
    landmark (uniform).
    """
    if not config.use_uncertainty_models:
        return np.full(NUM_LANDMARKS, config.r_lm_m2)
    factors: Array = _saliency_array(config) * pp
    return factors


def body_measurement_covariances(P_lm: Array, config: TrackerConfig,
                                 articulation: Array | None = None) -> Array:
    """``R_rb`` (21, 3, 3) of one hand's filtered landmarks (Table-I units).

    With the uncertainty models: ``R_rb,k = s_k P_lm,k + a_k I3``: the paper's saliency factor
    times the filter's position covariance, plus the articulation variance ``a_k`` (21,)
    (:func:`articulation_variances`, converted to Table-I units by the caller), the error of
    the rigid-hand assumption at that landmark. Without (ablation): ``r_lm I3`` for every
    landmark (uniform, isotropic).
    """
    if not config.use_uncertainty_models:
        return np.broadcast_to(config.r_lm_m2 * _I3, (NUM_LANDMARKS, 3, 3)).copy()
    R = _saliency_array(config)[:, None, None] * P_lm
    if articulation is not None:
        R = R + articulation[:, None, None] * _I3
    out: Array = R
    return out


def articulation_variances(points_body: Array, std_rad: float) -> Array:
    """Variance (21,) [m^2] of each landmark's position in the hand body from finger flexion.

    The body model holds the hand rigid, but only the palm is (wrist, thumb CMC and finger MCP
    landmarks, :data:`PALM`): each joint distal to the palm flexes a little while the hand holds
    an object (grip adjustments, tightening with effort). With an independent flexion of standard
    deviation ``std_rad`` at every articulated joint on the chain from the palm to landmark ``j``,
    ``j`` moves by ``theta |p_j - p_joint|`` per joint, so (isotropically, to first order)
    ``a_j = std_rad^2 sum_joints |p_j - p_joint|^2 / 3`` per axis, with the joint positions taken
    from the body model ``points_body`` (21, 3) (NaN rows: the chain is followed through the
    skeleton's nominal parent; a missing joint contributes nothing). Palm landmarks get 0.
    """
    var = np.zeros(NUM_LANDMARKS)
    if std_rad <= 0.0:
        return var
    for j in range(NUM_LANDMARKS):
        if j in PALM or not np.isfinite(points_body[j]).all():
            continue
        a = PARENT[j]
        total = 0.0
        while True:
            if np.isfinite(points_body[a]).all():
                d = points_body[j] - points_body[a]
                total += float(d @ d)
            if a in PALM:
                break
            a = PARENT[a]
        var[j] = std_rad * std_rad * total / 3.0
    return var


@lru_cache(maxsize=8)
def _saliency_array(config: TrackerConfig) -> Array:
    s = np.asarray(config.saliency_factors(), dtype=float)
    s.flags.writeable = False
    return s


# Cofactor products of a symmetric 3x3 matrix flattened row-major (entries 0 1 2 / 4 5 / 8 of
# its upper triangle): adj[k] = s[i0] s[i1] - s[i2] s[i3] with (i0, i1, i2, i3) = column k.
_ADJ_SYM3 = np.array([[4, 2, 1, 2, 0, 1, 1, 1, 0],
                      [8, 5, 5, 5, 8, 2, 5, 2, 4],
                      [5, 1, 2, 1, 2, 0, 2, 0, 1],
                      [5, 8, 4, 8, 2, 5, 4, 5, 1]])


def adjugate_sym3(S: Array) -> tuple[Array, Array]:
    """Adjugate (..., 3, 3) and determinant (...) of a stack of symmetric 3x3 matrices.

    Cofactor formula (one gather of the upper triangle, no per-entry numpy calls); only the
    upper triangle of ``S`` is read.
    """
    s = S.reshape(*S.shape[:-2], 9)
    f = s[..., _ADJ_SYM3]  # (..., 4, 9)
    adj = f[..., 0, :] * f[..., 1, :] - f[..., 2, :] * f[..., 3, :]
    det = s[..., 0] * adj[..., 0] + s[..., 1] * adj[..., 1] + s[..., 2] * adj[..., 2]
    return adj.reshape(S.shape), det


def inv_sym3(S: Array) -> tuple[Array, Array]:
    """Inverse and determinant of a stack of symmetric 3x3 matrices (..., 3, 3), by cofactors
    (:func:`adjugate_sym3`).

    Only the upper triangle is read; callers pass positive-definite matrices.
    """
    adj, det = adjugate_sym3(S)
    inv: Array = adj / det[..., None, None]
    return inv, det


__all__ = [
    "NUM_LANDMARKS",
    "PALM",
    "PARENT",
    "WRIST",
    "LandmarkFilterBank",
    "LandmarkUpdate",
    "adjugate_sym3",
    "articulation_variances",
    "body_landmark_mask",
    "body_measurement_covariances",
    "body_measurement_variances",
    "inv_sym3",
    "missing_mask",
    "ray_measurement_covariances",
]
