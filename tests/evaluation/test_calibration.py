"""Coverage of the published covariance's 90 % intervals and the times to a usable model
(docs/evaluation.md#calibration, #times)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.evaluation.metrics import (
    CHI2_2DOF_90,
    axis_direction_d2,
    axis_position_d2,
    coverage,
    summarise_times,
    time_held_from,
    time_to_converge,
)
from services.kinematics.filters.geometry import tangent_basis


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _spd(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(n, n)) * scale
    return A @ A.T + np.eye(n) * (0.1 * scale) ** 2


def _turned(u: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``Exp(u x (B b)) u``: u turned by the tangent coordinates b (exact)."""
    B = tangent_basis(u)
    n = float(np.linalg.norm(b))
    return u if n == 0 else math.cos(n) * u + math.sin(n) * (B @ b) / n


def test_chi2_quantile() -> None:
    # 2-dof chi-square CDF is 1 - exp(-x/2)
    assert 1.0 - math.exp(-CHI2_2DOF_90 / 2.0) == pytest.approx(0.9, abs=1e-12)


def test_axis_direction_gaussian_sample_covers_ninety_percent() -> None:
    rng = np.random.default_rng(0)
    d2, d2_overconfident = [], []
    for _ in range(4000):
        u = _unit(rng.normal(size=3))
        cov = _spd(rng, 2, 0.04)
        b = rng.multivariate_normal(np.zeros(2), cov)
        a = _turned(u, b) * rng.choice([-1.0, 1.0])  # the sign of a line's direction is free
        d2.append(axis_direction_d2(a, u, cov))
        d2_overconfident.append(axis_direction_d2(a, u, cov / 4.0))
    k, n = coverage(d2)
    assert n == 4000 and 0.88 < k / n < 0.92
    k, n = coverage(d2_overconfident)  # an interval half as wide covers 1 - exp(-4.6 / 8)
    assert k / n == pytest.approx(1.0 - math.exp(-CHI2_2DOF_90 / 8.0), abs=0.03)


def test_axis_direction_d2_is_the_angle_in_sigmas() -> None:
    u = np.array([0.0, 0.0, 1.0])
    t1 = tangent_basis(u)[:, 0]
    theta = 0.05
    a = math.cos(theta) * u + math.sin(theta) * t1
    cov = np.diag([0.02**2, 0.5**2])
    assert axis_direction_d2(a, u, cov) == pytest.approx((theta / 0.02) ** 2, rel=1e-9)
    assert axis_direction_d2(-a, u, cov) == pytest.approx((theta / 0.02) ** 2, rel=1e-9)
    assert axis_direction_d2(u, u, cov) == 0.0
    assert axis_direction_d2(a, u, np.zeros((2, 2))) == math.inf  # claims certainty
    assert axis_direction_d2(a, u, np.full((2, 2), np.nan)) == math.inf


def test_axis_position_gaussian_sample_covers_ninety_percent() -> None:
    rng = np.random.default_rng(1)
    d2 = []
    for _ in range(4000):
        u = _unit(rng.normal(size=3))
        p = rng.normal(size=3) * 0.5
        cov = _spd(rng, 3, 0.01)
        delta = rng.multivariate_normal(np.zeros(3), cov)
        # the true axis, parallel, through p + delta, given by another of its points
        q = p + delta + rng.normal() * 0.3 * u
        d2.append(axis_position_d2(u, q, u, p, cov))
    k, n = coverage(d2)
    assert 0.88 < k / n < 0.92


def test_axis_position_d2_meets_the_plane_normal_to_the_axis() -> None:
    u = np.array([0.0, 0.0, 1.0])
    p = np.array([0.1, 0.2, 0.0])
    r = np.array([0.03, -0.04, 0.0])  # 5 cm off in the plane z = 0
    tilted = _unit(np.array([0.2, 0.1, 1.0]))
    q = p + r + 0.4 * tilted  # the true axis crosses z = 0 at p + r
    sigma = 0.01
    assert axis_position_d2(tilted, q, u, p, np.eye(3) * sigma**2) == pytest.approx(
        (0.05 / sigma) ** 2, rel=1e-9)
    # a covariance along the axis itself does not widen the interval in the plane
    along = np.eye(3) * sigma**2 + 10.0 * np.outer(u, u)
    assert axis_position_d2(tilted, q, u, p, along) == pytest.approx((0.05 / sigma) ** 2,
                                                                     rel=1e-9)
    # a true axis in the plane never meets it
    assert axis_position_d2(np.array([1.0, 0.0, 0.0]), q, u, p, np.eye(3)) == math.inf


def test_coverage_counts_inf_as_outside_and_nan_as_undefined() -> None:
    assert coverage([0.0, 1.0, CHI2_2DOF_90, 5.0, math.inf, math.nan]) == (3, 5)
    assert coverage([]) == (0, 0)


def test_time_held_from_counts_from_the_start_and_only_for_good() -> None:
    stamps = np.arange(10, dtype=np.int64) * 100_000_000 + 5_000_000_000  # 10 Hz from 5 s
    ok = np.array([0, 1, 1, 0, 1, 1, 1, 1, 1, 1], dtype=bool)
    assert time_held_from(stamps, ok) == pytest.approx(0.4)
    assert time_held_from(stamps, ok, start_ns=5_200_000_000) == pytest.approx(0.2)
    assert time_held_from(stamps, ok, start_ns=6_000_000_000) == 0.0  # right before the grasp
    assert time_held_from(stamps, ~ok) is None
    assert time_held_from(stamps, np.ones(10, bool)) == 0.0
    errors = np.where(ok, 0.01, 1.0)
    assert time_to_converge(stamps, errors, 10.0, 5_100_000_000) == pytest.approx(0.3)
    with pytest.raises(ValueError, match="equal length"):
        time_held_from(stamps, ok[:3])


def test_summarise_times() -> None:
    s = summarise_times([1.0, None, 3.0, 2.0, math.nan])
    assert (s.median_s, s.reached, s.never) == (2.0, 3, 2)
    assert s.p90_s == pytest.approx(2.8)
    none = summarise_times([None, None])
    assert math.isnan(none.median_s) and none.never == 2 and none.reached == 0
