"""Kabsch fits: exact without noise, weights respected, the batch equal to one at a time."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.kabsch import batched_kabsch, weighted_kabsch
from services.common.se3 import se3_exp, transform_points
from tests.tracker.handgen import HAND


def random_pose(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return se3_exp(rng.normal(scale=scale, size=6))


def test_weighted_kabsch_is_exact_without_noise_and_follows_the_weights() -> None:
    rng = np.random.default_rng(1)
    T = random_pose(rng)
    dst = transform_points(T, HAND)
    R, t = weighted_kabsch(HAND, dst, rng.uniform(0.1, 5.0, size=21))
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(t, T[:3, 3], atol=1e-12)
    bad = dst.copy()
    bad[3] += 0.1
    w = np.ones(21)
    w[3] = 1e-9  # a (near) zero weight makes the corrupted point irrelevant
    R, t = weighted_kabsch(HAND, bad, w)
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-8)


def test_batched_kabsch_matches_one_at_a_time() -> None:
    rng = np.random.default_rng(2)
    src = rng.normal(size=(10, 4, 3))
    dst = src + rng.normal(scale=0.3, size=src.shape)
    R, t = batched_kabsch(src, dst)
    for k in range(10):
        Rk, tk = weighted_kabsch(src[k], dst[k], np.ones(4))
        np.testing.assert_allclose(R[k], Rk, atol=1e-12)
        np.testing.assert_allclose(t[k], tk, atol=1e-12)
        assert np.linalg.det(R[k]) == pytest.approx(1.0)
