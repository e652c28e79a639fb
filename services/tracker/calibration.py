"""Calibration of the published hand-body covariance from the body fit's residuals.

The filter's covariances follow Table I (in the physical units of ``TrackerConfig.internal``),
not the data. The tracker publishes the filter covariance times
:attr:`CovarianceCalibration.variance_factor`: the smoothed a-posteriori variance factor of the
body fit (how far the modelled noise is off from the residuals) times the correlation factor of
the residuals from frame to frame (successive poses are not independent measurements). A new
body is calibrated from its initialisation window (:meth:`CovarianceCalibration.seed`,
:func:`window_fit_covariance`), so that its first published covariance is already honest.

Residuals are in the tracking frame (m); ``W_i = R_i^-1`` are the inverse body-level measurement
covariances ``R_rb`` (m^-2).

Bound (docs/estimation.md#covariance-calibration): each landmark's squared standardised residual
``r_i' R_i^-1 r_i`` enters the variance factor at most as ``c``, the 3-dof chi-square quantile of
``variance_factor_residual_sigmas`` sigmas (14.16 for 3). A landmark that far off is an outlier
the gates let through (the initialisation window's fit has no gate at all), not evidence that
every landmark is noisier: uncapped, one such landmark in a window of 5 frames seeded factors of
12-28 on the tuning partition where the steady state is 1-2. With every term at most ``c``, the
variance of unit weight is at most ``c n / (3n - 6) <= c / 2`` (``n >= 6`` landmarks, as
``min_inliers`` requires), 7.08 for 3 sigmas, and the published factor at most that times
``max_correlation_factor``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2, norm

from services.common.kabsch import weighted_kabsch
from services.tracker.body_measurement import information_sums
from services.tracker.config import TrackerConfig
from services.tracker.landmarks import NUM_LANDMARKS

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class WindowFrame:
    """One frame of the initialisation window of the tracked hand, in the tracking frame:
    filtered ``positions`` (21, 3) (m), per-axis ``R_rb`` ``variances`` (21,) (``trace / 3``,
    m^2) and the ``usable`` (21,) landmarks."""

    stamp_ns: int
    positions: Array
    variances: Array
    usable: BoolArray


def fit_residuals(T_frame_body: Array, points_body: Array, used: NDArray[np.intp],
                  positions: Array, W: Array) -> tuple[Array, Array]:
    """Posterior residuals ``r_i = z_i - T p_i`` (n, 3) of the ``used`` landmarks after the
    body correction and ``r_i' R_i^-1 r_i`` (n,), with ``W`` (n, 3, 3) ``= R_i^-1``;
    ``T_frame_body`` (4, 4) the corrected pose, ``points_body`` (21, 3) the body model
    ``p_i``, ``positions`` (21, 3) the landmarks ``z_i``."""
    residual = positions[used] - (points_body[used] @ T_frame_body[:3, :3].T
                                  + T_frame_body[:3, 3])
    d2 = (residual[:, None, :] @ W @ residual[:, :, None])[:, 0, 0]
    return residual, d2


def window_fit_covariance(template: Array, model: BoolArray, final: WindowFrame) -> Array | None:
    """The covariance (6, 6) of a new body's initial pose fit, to add to the pose block of its
    ``P0``; None when it cannot be computed.

    The initial pose is a fit of the body model (``template`` (21, 3): its landmarks placed by the
    initial pose, in the tracking frame; ``model`` (21,) its finite rows) to the landmarks of the
    ``final`` window frame; its information there, ``A = sum H_i' R_i^-1 H_i``, gives the fit's
    covariance ``A^-1``. Table I's ``P0`` alone (a few mm and a degree) would claim more than a
    single frame of landmarks knows.
    """
    use = model & final.usable
    if use.sum() < 3:
        return None
    q = template[use][None]
    A, _, _ = information_sums(q, np.zeros_like(q), 1.0 / final.variances[use])
    try:
        P_fit = np.linalg.inv(A[0])
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(P_fit).all():
        return None
    out: Array = 0.5 * (P_fit + P_fit.T)
    return out


class CovarianceCalibration:
    """The a-posteriori variance factor and the lag-one residual correlation of the body fit,
    smoothed over frames (``config.variance_factor_smoothing``: the weight of a new frame);
    ``config``: the tracker's (``calibrate_covariance``, ``max_correlation_factor``)."""

    def __init__(self, config: TrackerConfig) -> None:
        self._cfg = config
        # The cap of each landmark's term (see the module docstring).
        self._term_cap = float(chi2.isf(2.0 * norm.sf(config.variance_factor_residual_sigmas), 3))
        self.reset()

    def reset(self) -> None:
        """Forget every residual seen."""
        self._variance_factor: float | None = None
        self._last_residuals: Array | None = None
        self._residual_cross: float | None = None
        self._residual_power = 0.0

    def forget_last_residuals(self) -> None:
        """The next frame's residuals follow no previous ones (the body was dropped)."""
        self._last_residuals = None

    def seed(self, template: Array, model: BoolArray, frames: Sequence[WindowFrame]) -> None:
        """Restart the calibration from a new body's initialisation window.

        The body model (``template`` (21, 3): its landmarks placed by the initial pose, in the
        tracking frame; ``model`` (21,) its finite rows) is fitted (weighted Kabsch) to every
        window frame; the residuals seed the variance factor and the residual correlation
        (:meth:`update`).
        """
        a = self._cfg.variance_factor_smoothing
        self._variance_factor = None
        self._residual_cross = None
        self._last_residuals = None
        samples = []
        for f in frames:
            common = model & f.usable
            if common.sum() < 3:
                self._last_residuals = None
                continue
            w = 1.0 / f.variances[common]
            R, t = weighted_kabsch(template[common], f.positions[common], w)
            fitted = np.full_like(template, np.nan)
            fitted[common] = template[common] @ R.T + t
            residual = np.where(common[:, None], f.positions - fitted, np.nan)
            W = np.where(common, 1.0 / f.variances, 0.0)
            n = int(common.sum())
            if 3 * n > 6:
                terms = W[common] * np.einsum("ij,ij->i", residual[common], residual[common])
                samples.append(float(np.minimum(terms, self._term_cap).sum()) / (3 * n - 6))
            last = self._last_residuals
            if last is not None:
                both = common & np.isfinite(last).all(axis=1)
                if both.any():
                    cross = float(np.sum(W[both, None] * residual[both] * last[both]))
                    power = 0.5 * float(np.sum(W[both, None] * (residual[both] ** 2
                                                                + last[both] ** 2)))
                    if self._residual_cross is None:
                        self._residual_cross, self._residual_power = cross, power
                    else:
                        self._residual_cross += a * (cross - self._residual_cross)
                        self._residual_power += a * (power - self._residual_power)
            self._last_residuals = residual
        if samples:
            self._variance_factor = float(np.mean(samples))

    def update(self, used: NDArray[np.intp], residual: Array, d2: Array, W: Array) -> None:
        """Track the a-posteriori variance of unit weight of the body fit and the frame-to-frame
        correlation of its residuals.

        ``sum(min(r_i' R_i^-1 r_i, c)) / (3n - 6)`` (``c``: the cap of the module docstring) over
        the posterior residuals ``r_i = z_i - T p_i`` of
        the ``used`` landmarks (indices into the 21 rows; ``residual`` (n, 3), their ``d2``
        (n,) ``= r_i' R_i^-1 r_i`` and ``W`` (n, 3, 3) ``= R_i^-1``, from
        :func:`fit_residuals`) estimates how far the filter's covariances are off from
        the data (1 when the noise model is right); it is smoothed over frames. The lag-one
        correlation ``rho = sum r_i(t)' W_i r_i(t-1) / sum r_i' W_i r_i`` of the residuals of
        landmarks used in both frames is smoothed the same way: detector errors and grip
        adjustments persist over many frames (the landmark filters add some more), so
        successive poses are not independent measurements (see :attr:`correlation_factor`).
        """
        n = used.size
        if n * 3 <= 6:
            self._last_residuals = None
            return
        sample = float(np.minimum(d2, self._term_cap).sum()) / (3 * n - 6)
        if not math.isfinite(sample) or sample <= 0.0:
            return
        a = self._cfg.variance_factor_smoothing
        if self._variance_factor is None:
            self._variance_factor = sample
        else:
            self._variance_factor += a * (sample - self._variance_factor)
        last = self._last_residuals
        if last is not None:
            prev = last[used]
            both = np.isfinite(prev).all(axis=1)
            if both.any():
                now, now_d2 = residual, d2
                if not both.all():
                    prev, now, now_d2, W = prev[both], now[both], now_d2[both], W[both]
                W_prev = (W @ prev[:, :, None])[:, :, 0]
                cross = float((now * W_prev).sum())  # sum r(t)' W r(t-1), W symmetric
                power = 0.5 * (float(now_d2.sum()) + float((prev * W_prev).sum()))
                if self._residual_cross is None:
                    self._residual_cross, self._residual_power = cross, power
                else:
                    self._residual_cross += a * (cross - self._residual_cross)
                    self._residual_power += a * (power - self._residual_power)
        full = np.full((NUM_LANDMARKS, 3), np.nan)
        full[used] = residual
        self._last_residuals = full

    @property
    def variance_factor(self) -> float:
        """Scale applied to the filter covariance for publication (1 when disabled or before any
        measurement): the a-posteriori variance factor times :attr:`correlation_factor`."""
        if not self._cfg.calibrate_covariance or self._variance_factor is None:
            return 1.0
        return self._variance_factor * self.correlation_factor

    @property
    def correlation_factor(self) -> float:
        """``(1 + rho) / (1 - rho)`` for the smoothed lag-one residual correlation ``rho``
        (clipped to [0, 1) and the factor to ``max_correlation_factor``); 1 when disabled.

        For errors with an AR(1) correlation ``rho`` between frames, ``(1 + rho) / (1 - rho)``
        is the integrated autocorrelation time in frames: averaging N such poses is worth
        ``N (1 - rho) / (1 + rho)`` independent ones. A consumer that treats successive poses as
        independent (the kinematic filters do) gets the right posterior uncertainty from
        covariances inflated by this factor.
        """
        cfg = self._cfg
        if (not cfg.calibrate_covariance or cfg.max_correlation_factor <= 1.0
                or self._residual_cross is None or not self._residual_power > 0.0):
            return 1.0
        rho = min(max(self._residual_cross / self._residual_power, 0.0), 1.0)
        if rho >= 1.0:
            return cfg.max_correlation_factor
        return min((1.0 + rho) / (1.0 - rho), cfg.max_correlation_factor)


__all__ = ["CovarianceCalibration", "WindowFrame", "fit_residuals", "window_fit_covariance"]
