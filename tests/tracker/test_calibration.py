"""The variance factor of the published hand-body covariance stays within its bound
(services/tracker/calibration.py, docs/estimation.md#covariance-calibration)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2, norm  # type: ignore[import-untyped]

from services.tracker.calibration import CovarianceCalibration, WindowFrame
from services.tracker.config import TrackerConfig
from services.tracker.landmarks import NUM_LANDMARKS

# Without the correlation factor, ``variance_factor`` is the variance of unit weight alone.
CONFIG = TrackerConfig(max_correlation_factor=1.0)
CAP = float(chi2.isf(2.0 * norm.sf(CONFIG.variance_factor_residual_sigmas), 3))


def test_the_cap_is_the_three_sigma_chi_square_quantile() -> None:
    assert pytest.approx(14.156, abs=1e-3) == CAP


def test_a_gross_residual_cannot_inflate_the_variance_factor_beyond_its_bound() -> None:
    """Frames of 12 landmarks whose residuals are right (d2 = 3 each) except one landmark 100
    sigmas off: the variance factor stays below ``c n / (3n - 6)``; uncapped it would be ~330."""
    rng = np.random.default_rng(0)
    cal = CovarianceCalibration(CONFIG)
    n = 12
    used = np.arange(n)
    W = np.tile(np.eye(3), (n, 1, 1))
    for _ in range(60):
        residual = rng.normal(size=(n, 3))
        residual[0] = (100.0, 0.0, 0.0)
        d2 = np.einsum("ij,ij->i", residual, residual)
        cal.update(used, residual, d2, W)
    uncapped = (1e4 + 3.0 * (n - 1)) / (3 * n - 6)
    bound = CAP * n / (3 * n - 6)
    assert cal.variance_factor <= bound < uncapped / 50.0
    assert cal.variance_factor > 1.0  # the outlier still counts, up to the cap


def test_an_outlier_in_the_initialisation_window_cannot_seed_a_huge_factor() -> None:
    """The window fit has no gate: one landmark 40 cm off in one of five frames (3 mm noise
    modelled as such) seeds a variance factor of 61 without the cap; with it, at most
    c n / (3n - 6)."""
    rng = np.random.default_rng(1)
    template = rng.normal(scale=0.05, size=(NUM_LANDMARKS, 3)) + np.array([0.0, 0.0, 0.6])
    model = np.ones(NUM_LANDMARKS, dtype=bool)
    variances = np.full(NUM_LANDMARKS, 0.003**2)
    frames = []
    for k in range(5):
        positions = template + rng.normal(scale=0.003, size=template.shape)
        if k == 2:
            positions[4] += (0.4, 0.0, 0.0)
        frames.append(WindowFrame(stamp_ns=k, positions=positions, variances=variances,
                                  usable=np.ones(NUM_LANDMARKS, dtype=bool)))
    cal = CovarianceCalibration(CONFIG)
    cal.seed(template, model, frames)
    n = NUM_LANDMARKS
    assert 0.5 < cal.variance_factor <= CAP * n / (3 * n - 6)
    assert cal.variance_factor < 3.0  # four clean frames of right noise and one capped outlier
    uncapped = CovarianceCalibration(TrackerConfig(max_correlation_factor=1.0,
                                                   variance_factor_residual_sigmas=1e3))
    uncapped.seed(template, model, frames)
    assert uncapped.variance_factor > 20 * cal.variance_factor
