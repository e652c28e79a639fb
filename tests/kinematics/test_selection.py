"""Model selection: bounded uniform history, the fused scores against the per-sample definition,
OMIP's rules (rigid motion memory, disconnected constant), log-space robustness."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common import se3
from services.kinematics.config import KinematicsConfig
from services.kinematics.filters import PrismaticJoint, RevoluteJoint, RigidJoint
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


def _random_history(rng: np.random.Generator, sel: ModelSelector, n: int) -> tuple[Array, Array]:
    c0 = rng.normal(size=3)
    R0 = se3.so3_exp(rng.normal(size=3))
    for _ in range(n):
        T = se3.se3_exp(rng.normal(scale=0.2, size=6))
        d = T[:3, 3] + rng.normal(scale=0.01, size=3)
        sel.add(d, T[:3, :3], float(rng.normal(scale=0.1)), float(rng.normal(scale=2.0)))
    return c0, R0


def _reference_scores(sel: ModelSelector, pri: PrismaticJoint, rev: RevoluteJoint, hand: Array,
                      c0: Array) -> Array:
    """Model selection (docs/estimation.md#model-selection) straight from the filters' per-sample errors."""
    cfg = sel.config
    h = sel.history
    idx = h.sample_indices(cfg.likelihood_sample_num)
    d, Rf, tr = h.d[idx], h.R_flat[idx], h.trace[idx]
    st, sr = cfg.likelihood_sigma_translation_m, cfg.likelihood_sigma_rotation_rad

    def agg(log_l: Array) -> float:
        if cfg.likelihood_aggregation == "product":
            return float(log_l.sum())
        return float(np.log(np.mean(np.exp(log_l))))

    out = np.full(4, -math.inf)
    if sel.rigid_memory:
        out[0] = math.log(0.25) + agg(log_density(*RigidJoint.history_errors(d, Rf, tr), st, sr))
    out[1] = math.log(0.25) + agg(log_density(*pri.history_errors(d, Rf, tr, h.q_prismatic[idx]),
                                              st, sr))
    out[2] = (math.log(0.25) + agg(log_density(*rev.history_errors(d, Rf, tr, h.q_revolute[idx], c0),
                                               st, sr))
              + log_normal_pdf(point_line_distance(hand, rev.p, rev.u), 0.5))
    k = len(idx) if cfg.likelihood_aggregation == "product" else 1
    out[3] = math.log(0.25) + k * math.log(3.2)
    return out


@pytest.mark.parametrize("aggregation", ["product", "mean"])
@pytest.mark.parametrize("n", [7, 100, 180, 600])
def test_fused_scores_equal_the_per_sample_definition(aggregation: str, n: int) -> None:
    rng = np.random.default_rng(n)
    cfg = KinematicsConfig(likelihood_aggregation=aggregation)
    sel = ModelSelector(cfg)
    c0, _ = _random_history(rng, sel, n)
    sel.rigid_memory = True
    pri = PrismaticJoint(cfg, unit(rng.normal(size=3)), 0.1, offset=rng.normal(scale=0.01, size=3))
    rev = RevoluteJoint(cfg, unit(rng.normal(size=3)), rng.normal(size=3) * 0.3, 1.0,
                        reference_correction=se3.se3_exp(rng.normal(scale=0.05, size=6)))
    hand = rng.normal(size=3)
    got = sel.log_scores(pri, rev, hand, c0)
    np.testing.assert_allclose(got, _reference_scores(sel, pri, rev, hand, c0), rtol=1e-7,
                               atol=1e-6)
    inactive = sel.log_scores(None, None, hand, c0)
    assert inactive[1] == inactive[2] == -math.inf and math.isfinite(inactive[0])


def test_rigid_motion_memory_is_permanent() -> None:
    sel = ModelSelector(KinematicsConfig())
    sel.add(np.zeros(3), np.eye(3), 0.0, 0.0)
    sel.add(np.array([0.0, 0.0, 0.049]), np.eye(3), 0.0, 0.0)
    assert sel.rigid_memory
    sel.add(np.array([0.0, 0.0, 0.051]), np.eye(3), 0.0, 0.0)  # beyond rig_max_translation
    assert not sel.rigid_memory
    sel.add(np.zeros(3), np.eye(3), 0.0, 0.0)  # back at the start: still not rigid
    assert not sel.rigid_memory
    assert sel.log_scores(None, None, np.zeros(3), np.zeros(3))[0] == -math.inf
    sel2 = ModelSelector(KinematicsConfig())
    sel2.add(np.zeros(3), se3.so3_exp(np.array([0.0, 0.101, 0.0])), 0.0, 0.0)
    assert not sel2.rigid_memory


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
    sel = ModelSelector(KinematicsConfig())
    for k in range(100):
        sel.add(np.array([0.0, 0.0, 0.01 * k]), np.eye(3), 0.0, 0.0)  # 1 m of motion
    scores = sel.log_scores(None, None, np.zeros(3), np.zeros(3))
    assert scores[0] == -math.inf  # rigid ruled out by the motion memory
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
    c0, _ = _random_history(rng, sel, 300)
    sel2 = ModelSelector.from_state(cfg, sel.to_state())
    pri = PrismaticJoint(cfg, unit(rng.normal(size=3)), 0.1)
    np.testing.assert_array_equal(sel.log_scores(pri, None, c0, c0),
                                  sel2.log_scores(pri, None, c0, c0))
    assert sel2.history.stride == sel.history.stride and sel2.history.n == sel.history.n
