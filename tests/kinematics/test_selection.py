"""Model selection: bounded uniform history, the fused scores against the per-sample definition,
the rigid test, the tempered outlier-class likelihood, OMIP's mean, log-space robustness."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common import se3
from services.kinematics.config import KinematicsConfig
from services.kinematics.filters import (
    PrismaticJoint,
    RevoluteJoint,
    RigidJoint,
    excess_sigmas,
)
from services.kinematics.selection import (
    DeltaHistory,
    ModelSelector,
    log_density,
    log_normal_pdf,
    point_line_distance,
    softmax,
)
from tests.kinematics import unit

Array = np.ndarray


def test_history_decimation_keeps_uniform_coverage() -> None:
    h = DeltaHistory(16)
    for _ in range(1000):
        h.offer(np.zeros(3), np.eye(3), 0.0, 0.0)
        assert h.n <= 16
        frames = h.frame
        assert frames[0] == 0
        np.testing.assert_array_equal(np.diff(frames), h.stride)  # evenly spaced from frame 0
    assert h.frames_seen == 1000
    assert h.frame[-1] > 1000 - 2 * h.stride  # covers the whole stream up to now


def test_sample_indices_follow_omip() -> None:
    h = DeltaHistory(256)
    for _ in range(250):
        h.offer(np.zeros(3), np.eye(3), 0.0, 0.0)
    idx = h.sample_indices(100)
    expected = [round(j * 2.5 + 1e-9) for j in range(100)]  # round half up, like floor(x + .5)
    np.testing.assert_array_equal(idx, expected)
    assert idx.max() < h.n
    h2 = DeltaHistory(256)
    for _ in range(40):
        h2.offer(np.zeros(3), np.eye(3), 0.0, 0.0)
    np.testing.assert_array_equal(h2.sample_indices(100), np.arange(40))


def _random_history(rng: np.random.Generator, sel: ModelSelector, n: int,
                    ) -> tuple[Array, Array, Array]:
    """``n`` random samples; returns the reference position and the squared Mahalanobis
    distances (n, 2) of each frame's displacement and rotation (the rigid test's input)."""
    c0 = rng.normal(size=3)
    d2 = rng.chisquare(3, size=(n, 2)) * rng.choice([0.3, 1.0, 30.0], size=(n, 1))
    for k in range(n):
        T = se3.se3_exp(rng.normal(scale=0.2, size=6))
        d = T[:3, 3] + rng.normal(scale=0.01, size=3)
        sel.add(d, T[:3, :3], float(rng.normal(scale=0.1)), float(rng.normal(scale=2.0)),
                float(d2[k, 0]), float(d2[k, 1]))
    return c0, se3.so3_exp(rng.normal(size=3)), d2


def _reference_scores(sel: ModelSelector, pri: PrismaticJoint, rev: RevoluteJoint, hand: Array,
                      c0: Array, d2: Array, duration_s: float) -> Array:
    """Model selection (docs/estimation.md#model-selection) straight from the filters' per-sample
    errors: ``d2`` (frames, 2) the rigid test's squared Mahalanobis distances of every frame."""
    cfg = sel.config
    h = sel.history
    idx = h.sample_indices(cfg.likelihood_sample_num)
    d, Rf, tr = h.d[idx], h.R_flat[idx], h.trace[idx]
    d2t, d2r = d2[h.frame[idx].astype(int), 0], d2[h.frame[idx].astype(int), 1]
    st, sr = cfg.likelihood_sigma_translation_m, cfg.likelihood_sigma_rotation_rad
    k = cfg.rigid_test_sigmas
    m = len(idx)
    n_eff = min(m, max(1.0, duration_s / cfg.likelihood_correlation_time_s))

    def agg(log_n: Array) -> float:
        if cfg.likelihood_aggregation == "product":
            return float(log_n.sum())
        if cfg.likelihood_aggregation == "mean":
            return float(np.log(np.mean(np.exp(log_n))))
        eps = cfg.likelihood_outlier_weight
        mixture = (1.0 - eps) * np.exp(log_n) + eps * cfg.disconnected_density
        return float(np.log(mixture).sum() * n_eff / m)

    out = np.full(4, -math.inf)
    # Rigid's errors are standardised (sigmas beyond the rigid test), prismatic's rotation too.
    xt, xr = RigidJoint.history_errors(d2t, d2r, k)
    out[0] = math.log(0.25) + agg(log_density(xt * st, xr * sr, st, sr))
    et, xr_p = pri.history_errors(d, h.q_prismatic[idx], d2r, k)
    out[1] = math.log(0.25) + agg(log_density(et, xr_p * sr, st, sr))
    out[2] = (math.log(0.25) + agg(log_density(*rev.history_errors(d, Rf, tr, h.q_revolute[idx], c0),
                                               st, sr))
              + log_normal_pdf(point_line_distance(hand, rev.p, rev.u), 0.5))
    n_disc = {"product": m, "mean": 1.0, "tempered": n_eff}[cfg.likelihood_aggregation]
    out[3] = math.log(0.25) + n_disc * math.log(3.2)
    return out


@pytest.mark.parametrize("aggregation", ["tempered", "product", "mean"])
@pytest.mark.parametrize("n", [7, 100, 180, 600])
def test_fused_scores_equal_the_per_sample_definition(aggregation: str, n: int) -> None:
    rng = np.random.default_rng(n)
    cfg = KinematicsConfig(likelihood_aggregation=aggregation)
    sel = ModelSelector(cfg)
    c0, _, d2 = _random_history(rng, sel, n)
    pri = PrismaticJoint(cfg, unit(rng.normal(size=3)), 0.1, offset=rng.normal(scale=0.01, size=3))
    rev = RevoluteJoint(cfg, unit(rng.normal(size=3)), rng.normal(size=3) * 0.3, 1.0,
                        reference_correction=se3.se3_exp(rng.normal(scale=0.05, size=6)))
    hand = rng.normal(size=3)
    duration = n / 30.0
    got = sel.log_scores(pri, rev, hand, c0, duration)
    np.testing.assert_allclose(got, _reference_scores(sel, pri, rev, hand, c0, d2, duration),
                               rtol=1e-7, atol=1e-6)
    inactive = sel.log_scores(None, None, hand, c0, duration)
    assert inactive[1] == inactive[2] == -math.inf and math.isfinite(inactive[0])


def test_excess_sigmas_is_the_distance_beyond_the_rigid_test() -> None:
    got = excess_sigmas(np.array([0.0, 3.9, 6.25, 16.0, 64.0]), 2.5)
    np.testing.assert_allclose(got, [0.0, 0.0, 0.0, 1.5, 5.5])


def _still(sel: ModelSelector, n: int, d2: float = 2.0) -> None:
    """``n`` samples of a hand within its noise: mm and a degree off, inside the rigid test."""
    for _ in range(n):
        sel.add(np.array([0.002, -0.001, 0.0]), se3.so3_exp(np.array([0.0, 0.02, 0.0])), 0.0,
                0.0, d2, d2)


def test_rigid_test_forgives_noise_and_recovers_after_a_transient() -> None:
    """No permanent kill: a hand that jumps by 20 cm and 30 deg for 5 frames (a tracking
    transient) and is still before and after is rigid again once the stillness outweighs the
    transient, and a hand whose deltas stay within the noise is rigid however far the noise takes
    the delta beyond OMIP's 5 cm / 0.1 rad limits."""
    cfg = KinematicsConfig()
    sel = ModelSelector(cfg)
    _still(sel, 30)
    p_before = softmax(sel.log_scores(None, None, np.zeros(3), np.zeros(3), 1.0))
    assert p_before[0] > 0.99
    for _ in range(5):
        sel.add(np.array([0.2, 0.0, 0.0]), se3.so3_exp(np.array([0.0, 0.0, 0.5])), 0.0, 0.0,
                400.0, 400.0)
    during = softmax(sel.log_scores(None, None, np.zeros(3), np.zeros(3), 35 / 30))
    assert during[0] < p_before[0]  # the transient costs confidence ...
    _still(sel, 90)
    after = softmax(sel.log_scores(None, None, np.zeros(3), np.zeros(3), 125 / 30))
    assert after[0] > 0.99  # ... and the stillness restores it
    noisy = ModelSelector(cfg)
    for _ in range(60):  # 6 cm and 0.15 rad off, but within 2.5 sigmas of the covariance
        noisy.add(np.array([0.06, 0.0, 0.0]), se3.so3_exp(np.array([0.15, 0.0, 0.0])), 0.0, 0.0,
                  6.0, 6.0)
    assert softmax(noisy.log_scores(None, None, np.zeros(3), np.zeros(3), 2.0))[0] > 0.99


def test_heavy_tailed_errors_lower_confidence_without_flipping_the_verdict() -> None:
    """A prismatic history whose every 8th sample is a gross error (0.3 m, 1 rad off the joint):
    the product likelihood lets the outliers decide (disconnected), the tempered outlier-class
    likelihood keeps the verdict and loses only confidence."""
    u = unit(np.array([0.2, 1.0, 0.1]))
    ratios = {}
    for outliers in (False, True):
        for aggregation in ("product", "tempered"):
            cfg = KinematicsConfig(likelihood_aggregation=aggregation)
            sel = ModelSelector(cfg)
            for k in range(120):
                q = 0.3 * k / 120
                d, R = q * u, np.eye(3)
                if outliers and k % 8 == 7:
                    d, R = d + np.array([0.3, 0.0, 0.0]), se3.so3_exp(np.array([1.0, 0.0, 0.0]))
                sel.add(d, R, q, 0.0, 1e4, 400.0 if outliers and k % 8 == 7 else 1.0)
            scores = sel.log_scores(PrismaticJoint(cfg, u, 0.3), None, np.zeros(3), np.zeros(3),
                                    4.0)
            verdict = int(np.argmax(scores))
            ratios[outliers, aggregation] = (verdict, scores[1] - np.delete(scores, 1).max())
    assert ratios[False, "product"][0] == ratios[False, "tempered"][0] == 1  # clean: prismatic
    assert ratios[True, "product"][0] == 3  # the outliers flip the product to disconnected
    verdict, margin = ratios[True, "tempered"]
    assert verdict == 1 and 0.0 < margin < ratios[False, "tempered"][1]


def test_omip_mean_mode_scores() -> None:
    """With OMIP's arithmetic mean a perfect rigid fit scores 0.25 x 15.92 and disconnected 0.8."""
    sel = ModelSelector(KinematicsConfig(likelihood_aggregation="mean"))
    for _ in range(50):
        sel.add(np.zeros(3), np.eye(3), 0.0, 0.0)
    log_scores = sel.log_scores(None, None, np.zeros(3), np.zeros(3))
    scores = np.exp(log_scores)
    assert scores[0] == pytest.approx(0.25 / (2 * math.pi * 0.05 * 0.2))
    assert scores[3] == pytest.approx(0.8)
    p = softmax(log_scores)
    assert p[0] == pytest.approx(3.979 / (3.979 + 0.8), rel=1e-3)


def test_product_mode_is_sharp_and_log_space_never_underflows() -> None:
    sel = ModelSelector(KinematicsConfig(likelihood_aggregation="product"))
    for k in range(100):  # 1 m of motion, far beyond the rigid test
        sel.add(np.array([0.0, 0.0, 0.01 * k]), np.eye(3), 0.0, 0.0, 1e4 * k, 0.0)
    scores = sel.log_scores(None, None, np.zeros(3), np.zeros(3))
    assert scores[0] < scores[3] - 100.0  # rigid: every moved sample counts against it
    pri = PrismaticJoint(KinematicsConfig(), np.array([1.0, 0.0, 0.0]), 0.0)  # the wrong axis
    scores = sel.log_scores(pri, None, np.zeros(3), np.zeros(3))
    assert scores[1] < -1e3 and math.isfinite(scores[1])  # exp() of it would underflow to 0
    p = softmax(scores)
    assert p.sum() == pytest.approx(1.0) and p[3] == pytest.approx(1.0)


def test_softmax_and_helpers() -> None:
    p = softmax(np.array([-math.inf, 0.0, math.log(3.0), -math.inf]))
    np.testing.assert_allclose(p, [0.0, 0.25, 0.75, 0.0])
    assert log_normal_pdf(0.0, 0.5) == pytest.approx(math.log(0.7978845608), rel=1e-9)
    assert point_line_distance(np.array([1.0, 2.0, 5.0]), np.zeros(3),
                               np.array([0.0, 0.0, 1.0])) == pytest.approx(math.sqrt(5.0))
    assert float(log_density(np.zeros(1), np.zeros(1), 0.05, 0.2)[0]) == pytest.approx(
        math.log(15.9154943), rel=1e-7)


def test_backfill_projects_early_samples() -> None:
    h = DeltaHistory(64)
    u = unit(np.array([1.0, 2.0, 2.0]))
    for k in range(5):
        h.offer(0.001 * k * u, se3.so3_exp(0.005 * k * u), 0.0, 0.0)
    h.backfill_prismatic(u)
    h.backfill_revolute(u)
    np.testing.assert_allclose(h.q_prismatic, 0.001 * np.arange(5), atol=1e-15)
    np.testing.assert_allclose(h.q_revolute, 0.005 * np.arange(5), atol=1e-12)


def test_selector_state_round_trip() -> None:
    rng = np.random.default_rng(3)
    cfg = KinematicsConfig()
    sel = ModelSelector(cfg)
    c0, _, _ = _random_history(rng, sel, 300)
    sel2 = ModelSelector.from_state(cfg, sel.to_state())
    pri = PrismaticJoint(cfg, unit(rng.normal(size=3)), 0.1)
    np.testing.assert_array_equal(sel.log_scores(pri, None, c0, c0),
                                  sel2.log_scores(pri, None, c0, c0))
    assert sel2.history.stride == sel.history.stride and sel2.history.n == sel.history.n
