"""Weighted RANSAC initialisation and the body frame."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.kabsch import weighted_kabsch
from services.common.se3 import se3_exp, se3_inverse, se3_log, transform_points
from services.tracker.ransac import (
    initial_body,
    rigid_ransac,
    weighted_triplets,
)
from tests.tracker.handgen import HAND


def random_pose(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return se3_exp(rng.normal(scale=scale, size=6))


def test_triplets_are_distinct_and_drawn_in_proportion_to_weight() -> None:
    rng = np.random.default_rng(3)
    weights = np.ones(10)
    weights[0] = 20.0
    idx = weighted_triplets(weights, 4000, rng)
    assert all(len(set(row)) == 3 for row in idx[:200])
    counts = np.bincount(idx.ravel(), minlength=10)
    # Index 0 is in almost every triplet, the others share the rest evenly.
    assert counts[0] > 0.9 * 4000
    assert counts[1:].std() < 0.1 * counts[1:].mean()
    uniform = np.bincount(weighted_triplets(np.ones(10), 4000, rng).ravel(), minlength=10)
    assert uniform.min() > 0.85 * uniform.mean()


@pytest.mark.parametrize("seed", range(5))
def test_ransac_finds_the_motion_with_thirty_percent_outliers(seed: int) -> None:
    rng = np.random.default_rng(seed)
    src = transform_points(random_pose(rng, 0.3), HAND[1:])  # 20 landmarks, wrist excluded
    motion = se3_exp(np.array([0.04, -0.02, 0.03, 0.2, -0.3, 0.1]))
    dst = transform_points(motion, src)
    var_src = rng.uniform(0.5, 1.5, size=20) * 1e-5  # ~3 mm
    var_dst = rng.uniform(0.5, 1.5, size=20) * 1e-5
    src = src + rng.normal(size=src.shape) * np.sqrt(var_src)[:, None]
    dst = dst + rng.normal(size=dst.shape) * np.sqrt(var_dst)[:, None]
    outliers = rng.choice(20, size=6, replace=False)
    d = rng.normal(size=(6, 3))
    dst[outliers] += d / np.linalg.norm(d, axis=1)[:, None] * rng.uniform(0.05, 0.3, (6, 1))
    result = rigid_ransac(src, dst, var_src, var_dst, iterations=100, threshold=4.0,
                          refinements=2, rng=rng)
    assert result is not None
    truth = np.ones(20, dtype=bool)
    truth[outliers] = False
    np.testing.assert_array_equal(result.inliers, truth)
    # The result is the weighted fit on exactly the true inliers (the best one can do) ...
    R, t = weighted_kabsch(src[truth], dst[truth], 1.0 / (var_src + var_dst)[truth])
    np.testing.assert_allclose(result.rotation, R, atol=1e-12)
    np.testing.assert_allclose(result.translation, t, atol=1e-12)
    # ... which is near the true motion (the flat hand pins in-plane rotations least).
    err = se3_log(motion @ se3_inverse(result.transform))
    assert np.linalg.norm(err[3:]) < 0.1
    assert np.linalg.norm(transform_points(motion, src) - transform_points(result.transform, src),
                          axis=1).max() < 0.01


def test_ransac_is_deterministic_for_a_seed_and_refuses_too_few_points() -> None:
    rng = np.random.default_rng(0)
    src = HAND[1:] + rng.normal(scale=0.003, size=(20, 3))
    dst = HAND[1:] + rng.normal(scale=0.003, size=(20, 3))
    var = np.full(20, 1e-5)
    runs = [rigid_ransac(src, dst, var, var, iterations=50, threshold=4.0, refinements=1,
                         rng=np.random.default_rng(42)) for _ in range(2)]
    assert runs[0] is not None and runs[1] is not None
    np.testing.assert_array_equal(runs[0].transform, runs[1].transform)
    assert rigid_ransac(src[:2], dst[:2], var[:2], var[:2], iterations=5, threshold=4.0,
                        refinements=0, rng=rng) is None


def test_initial_body_frame_is_the_inlier_centroid_with_reference_axes() -> None:
    rng = np.random.default_rng(4)
    T0 = random_pose(rng, 0.3)
    step = np.array([0.01, 0.0, -0.005, 0.02, 0.01, 0.0])  # per frame, left twist * dt
    W, dt = 5, 1.0 / 30.0
    poses = [se3_exp(k * step) @ T0 for k in range(W)]
    positions = np.stack([transform_points(T, HAND) for T in poses])
    valid = np.ones((W, 21), dtype=bool)
    valid[2, 7] = False  # a gap inside the window is fine
    inliers = np.ones(21, dtype=bool)
    inliers[0] = False  # the wrist is never part of the body
    motion = poses[-1] @ se3_inverse(poses[0])
    body = initial_body(positions, np.full((W, 21), 1e-4), valid,
                        np.arange(W, dtype=float) * dt, inliers, motion)
    centroid = positions[-1, 1:].mean(axis=0)
    np.testing.assert_allclose(body.T_frame_body[:3, :3], np.eye(3))
    np.testing.assert_allclose(body.T_frame_body[:3, 3], centroid, atol=1e-12)
    np.testing.assert_allclose(body.points_body[1:], positions[-1, 1:] - centroid, atol=1e-12)
    assert np.isnan(body.points_body[0]).all()
    np.testing.assert_allclose(body.twist, step / dt, atol=1e-9)
