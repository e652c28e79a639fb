"""Landmark filter bank: batched = per-landmark textbook KF; gating, loss, re-init, saliency."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.tracker.config import TrackerConfig
from services.tracker.landmarks import (
    PALM,
    LandmarkFilterBank,
    articulation_variances,
    body_landmark_mask,
    body_measurement_covariances,
    body_measurement_variances,
    inv_sym3,
    missing_mask,
    ray_measurement_covariances,
)
from tests.tracker.handgen import HAND


class ReferenceKf:
    """One landmark's 6-state KF written the textbook way (full matrices, no batching)."""

    def __init__(self, config: TrackerConfig, z: np.ndarray) -> None:
        self.c = config
        self.x = np.concatenate([z, np.zeros(3)])
        self.P = np.diag([config.p0_lm_position_m2] * 3 + [config.p0_lm_velocity_m2ps2] * 3)
        self.corrections = 0

    @property
    def confirmed(self) -> bool:
        """Whether a loss of this filter gates the restart of its landmark."""
        return self.corrections >= self.c.lm_confirm_corrections

    def predict(self, dt: float) -> None:
        F = np.eye(6)
        F[:3, 3:] = dt * np.eye(3)
        Q = np.diag([self.c.q_lm_position_m2] * 3 + [self.c.q_lm_velocity_m2ps2] * 3)
        self.x = F @ self.x
        self.P = F @ self.P @ F.T + Q * dt / self.c.nominal_dt_s

    def passes(self, z: np.ndarray, R: np.ndarray | None = None) -> bool:
        """Whether ``z`` passes the landmark gate against this filter's prediction."""
        R = self.c.r_lm_m2 * np.eye(3) if R is None else R
        y = z - self.x[:3]
        return bool(np.sqrt(y @ np.linalg.solve(self.P[:3, :3] + R, y)) < self.c.mahalanobis_lm)

    def update(self, z: np.ndarray, gate: bool, R: np.ndarray | None = None) -> bool:
        """Returns False if gated out."""
        H = np.hstack([np.eye(3), np.zeros((3, 3))])
        R = self.c.r_lm_m2 * np.eye(3) if R is None else R
        y = z - H @ self.x
        S = H @ self.P @ H.T + R
        if gate and not self.passes(z, R):
            return False
        K = self.P @ H.T @ np.linalg.inv(S)
        self.x = self.x + K @ y
        IKH = np.eye(6) - K @ H
        self.P = IKH @ self.P @ IKH.T + K @ R @ K.T
        self.corrections += 1
        return True


def test_batched_bank_equals_per_landmark_reference_kf() -> None:
    """42 rows (two hands) through 200 frames of random motion, gaps, outliers and jitter in dt."""
    rng = np.random.default_rng(7)
    config = TrackerConfig()
    n = 42
    bank = LandmarkFilterBank(n, config)
    refs: list[ReferenceKf | None] = [None] * n
    lost: list[ReferenceKf | None] = [None] * n  # a dropped filter, still predicting
    truth = rng.normal(scale=0.1, size=(n, 3))
    vel = rng.normal(scale=0.1, size=(n, 3))
    refused = 0
    for k in range(200):
        dt = config.nominal_dt_s * (1 + (k % 7 == 0))  # a dropped frame now and then
        truth += vel * dt
        z = truth + rng.normal(scale=0.02, size=(n, 3))
        z[rng.random(n) < 0.1] += 0.3  # outliers beyond the gate
        z[rng.random(n) < 0.15] = np.nan  # missing
        if k:
            bank.predict(dt)
            for r in (*refs, *lost):
                if r is not None:
                    r.predict(dt)
        upd = bank.update(z, config.r_lm_m2)
        for i in range(n):
            r = refs[i]
            measured = bool(np.isfinite(z[i]).all())
            if r is None:
                if measured:
                    past = lost[i]
                    if past is not None and not past.passes(z[i]):  # a gated restart
                        refused += 1
                        assert upd.rejected[i] and not upd.fresh[i] and not bank.alive[i]
                        continue
                    refs[i], lost[i] = ReferenceKf(config, z[i]), None
                    assert upd.fresh[i]
                continue
            accepted = r.update(z[i], gate=True) if measured else False
            assert upd.rejected[i] == (measured and not accepted)
            assert upd.fresh[i] == accepted
            if 3 * r.P[0, 0] >= config.lm_loss_trace_m2:
                refs[i], lost[i] = None, (r if r.confirmed else None)
                assert upd.dropped[i] and not bank.alive[i]
                continue
            assert bank.alive[i]
            # The same filter in other algebra: round-off ~eps (2.2e-16) per step at |x| <~ 1,
            # not accumulated by the stable filter (observed ~2e-16 after every step).
            np.testing.assert_allclose(bank.x[i], r.x, atol=1e-12)
            np.testing.assert_allclose(bank.covariance(i), r.P, atol=1e-12)
    assert refused > 5  # outliers right after a loss were gated, not restarted on


def test_outlier_skips_correction_then_landmark_is_lost_and_restarts() -> None:
    config = TrackerConfig()
    bank = LandmarkFilterBank(2, config)
    z = np.zeros((2, 3))
    bank.update(z, config.r_lm_m2)
    for _ in range(30):
        bank.predict(config.nominal_dt_s)
        bank.update(z, config.r_lm_m2)
    bank.predict(config.nominal_dt_s)
    x_pred = bank.x.copy()
    jump = z.copy()
    jump[1] = [0.12, 0.0, 0.0]  # 12 cm: beyond the ~9 cm Table-I gate
    upd = bank.update(jump, config.r_lm_m2)
    assert upd.fresh.tolist() == [True, False]
    assert upd.rejected.tolist() == [False, True]
    assert upd.mahalanobis[1] >= config.mahalanobis_lm > upd.mahalanobis[0]
    # Correction skipped: the covariance grew by one frame of Q and crossed the loss threshold.
    assert upd.dropped.tolist() == [False, True]
    assert np.isnan(bank.positions()[1]).all()
    # z == prediction: nothing moves, bit-exactly on any machine (x + K 0 = x).
    np.testing.assert_array_equal(bank.x[0], x_pred[0])
    # The next measurement restarts the filter there, with P0 and the given start velocity.
    bank.predict(config.nominal_dt_s)
    restart = np.array([[0.0, 0.0, 0.0], [0.01, 0.02, 0.03]])
    upd = bank.update(restart, config.r_lm_m2, v_start=np.full((2, 3), 0.5))
    assert upd.fresh.all() and bank.alive.all()
    np.testing.assert_array_equal(bank.x[1], [0.01, 0.02, 0.03, 0.5, 0.5, 0.5])  # copied in
    np.testing.assert_allclose(bank.covariance(1), np.diag([0.09] * 3 + [0.06] * 3))


def test_a_small_jump_inside_the_gate_is_absorbed() -> None:
    config = TrackerConfig()
    bank = LandmarkFilterBank(1, config)
    bank.update(np.zeros((1, 3)), config.r_lm_m2)
    for _ in range(30):
        bank.predict(config.nominal_dt_s)
        bank.update(np.zeros((1, 3)), config.r_lm_m2)
    bank.predict(config.nominal_dt_s)
    upd = bank.update(np.array([[0.05, 0.0, 0.0]]), config.r_lm_m2)
    assert upd.fresh[0] and not upd.rejected[0]
    assert bank.x[0, 0] == pytest.approx(0.05 * 0.776, abs=1e-3)  # steady-state gain


def test_ablation_accepts_everything() -> None:
    config = TrackerConfig()
    bank = LandmarkFilterBank(1, config)
    bank.update(np.zeros((1, 3)), config.r_lm_m2)
    bank.predict(config.nominal_dt_s)
    upd = bank.update(np.array([[1.0, 0.0, 0.0]]), config.r_lm_m2, gate=False)
    assert upd.fresh[0] and not upd.rejected[0]


def test_missing_measurements_grow_the_covariance_linearly_in_dt() -> None:
    config = dataclasses.replace(TrackerConfig(), lm_loss_trace_m2=100.0)
    one, two = LandmarkFilterBank(1, config), LandmarkFilterBank(1, config)
    for bank in (one, two):
        bank.update(np.zeros((1, 3)), config.r_lm_m2)
    missing = np.full((1, 3), np.nan)
    one.predict(config.nominal_dt_s)
    one.update(missing, config.r_lm_m2)
    one.predict(config.nominal_dt_s)
    one.update(missing, config.r_lm_m2)
    two.predict(2 * config.nominal_dt_s)  # the same interval in one step
    two.update(missing, config.r_lm_m2)
    # Velocity noise adds q_v dt either way; position noise differs only by the q_v dt^3 term.
    assert two.vv[0] == pytest.approx(one.vv[0])
    assert two.pp[0] == pytest.approx(one.pp[0], rel=1e-3)
    assert one.alive[0] and two.alive[0]


def test_reject_rolls_back_to_the_prediction() -> None:
    config = TrackerConfig()
    bank = LandmarkFilterBank(2, config)
    bank.update(np.zeros((2, 3)), config.r_lm_m2)
    for _ in range(10):
        bank.predict(config.nominal_dt_s)
        bank.update(np.zeros((2, 3)), config.r_lm_m2)
    bank.predict(config.nominal_dt_s)
    x_pred, pp_pred = bank.x.copy(), bank.pp.copy()
    bank.update(np.full((2, 3), 0.02), config.r_lm_m2)
    dropped = bank.reject(np.array([False, True]))
    np.testing.assert_array_equal(bank.x[1], x_pred[1])  # bit-exact: the prediction is restored
    assert bank.pp[1] == pp_pred[1]
    assert dropped[1] and not bank.alive[1]  # skipping one Table-I correction loses it
    assert bank.alive[0] and bank.x[0, 0] > 0.0
    # A filter started by the rejected measurement itself is removed, whatever the threshold.
    lenient = LandmarkFilterBank(1, dataclasses.replace(config, lm_loss_trace_m2=1e9))
    lenient.update(np.zeros((1, 3)), config.r_lm_m2)
    assert lenient.reject(np.array([True]))[0] and not lenient.alive[0]


def test_visibility_and_nan_make_landmarks_missing() -> None:
    pts = np.zeros((21, 3))
    pts[3, 1] = np.nan
    pts[4, 2] = np.inf
    vis = np.ones(21)
    vis[5] = 0.005
    vis[6] = 0.006
    vis[7] = np.nan
    assert np.flatnonzero(missing_mask(pts, vis, 0.006)).tolist() == [3, 4, 5, 7]


def test_saliency_scales_filter_covariance_and_ablation_is_uniform() -> None:
    config = TrackerConfig()
    pp = np.linspace(0.01, 0.05, 21)
    r = body_measurement_variances(pp, config)
    np.testing.assert_allclose(r, np.asarray(config.saliency_factors()) * pp)
    # Bit-exact on any machine: one correctly rounded IEEE multiplication each.
    assert r[8] == 0.5 * pp[8] and r[2] == 1.5 * pp[2] and r[6] == pp[6]
    assert not body_landmark_mask(config)[0] and body_landmark_mask(config)[1:].all()
    ablation = dataclasses.replace(config, use_uncertainty_models=False)
    np.testing.assert_array_equal(body_measurement_variances(pp, ablation), 0.05)  # a constant
    assert body_landmark_mask(ablation).all()


def test_inv_sym3_matches_numpy() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 3, 3))
    S = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(3)
    inv, det = inv_sym3(S)
    # Cofactors vs LU: both off by ~eps (2.2e-16) * cond(S) (S = A A' + 0.1 I: cond <~ 1e3).
    np.testing.assert_allclose(inv, np.linalg.inv(S), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(det, np.linalg.det(S), rtol=1e-10)


def test_anisotropic_bank_equals_per_landmark_reference_kf() -> None:
    """Per-row measurement covariances about the viewing ray (depth variance 4x the lateral):
    the batched bank still equals the textbook 6x6 filter, gating and loss included (the loss
    threshold scales with trace(R) / (3 r_lm))."""
    rng = np.random.default_rng(8)
    config = TrackerConfig()
    n = 21
    bank = LandmarkFilterBank(n, config)
    refs: list[ReferenceKf | None] = [None] * n
    lost: list[ReferenceKf | None] = [None] * n  # a dropped filter, still predicting
    truth = rng.normal(scale=0.1, size=(n, 3)) + np.array([0.0, 0.0, 0.7])
    vel = rng.normal(scale=0.1, size=(n, 3))
    dropped = 0
    for k in range(120):
        dt = config.nominal_dt_s
        truth += vel * dt
        z = truth + rng.normal(scale=0.02, size=(n, 3))
        z[rng.random(n) < 0.1] += 0.3
        z[rng.random(n) < 0.1] = np.nan
        R = ray_measurement_covariances(np.nan_to_num(z), config.r_lm_m2, 4.0)
        if k:
            bank.predict(dt)
            for r in (*refs, *lost):
                if r is not None:
                    r.predict(dt)
        upd = bank.update(z, R)
        for i in range(n):
            r = refs[i]
            if r is None:
                if np.isfinite(z[i]).all():
                    past = lost[i]
                    if past is not None and not past.passes(z[i], R[i]):  # a gated restart
                        assert upd.rejected[i] and not bank.alive[i]
                        continue
                    refs[i], lost[i] = ReferenceKf(config, z[i]), None
                continue
            accepted = r.update(z[i], gate=True, R=R[i]) if np.isfinite(z[i]).all() else False
            assert upd.fresh[i] == accepted
            ratio = max(float(np.trace(R[i])) / (3 * config.r_lm_m2), 1.0)
            if np.trace(r.P[:3, :3]) >= config.lm_loss_trace_m2 * ratio:
                refs[i], lost[i] = None, (r if r.confirmed else None)
                dropped += 1
                assert not bank.alive[i]
                continue
            assert bank.alive[i]
            np.testing.assert_allclose(bank.x[i], r.x, atol=1e-12)  # round-off as above
            np.testing.assert_allclose(bank.covariance(i), r.P, atol=1e-12)
    assert dropped > 10  # the outliers exercised the gate and the loss threshold


def test_ray_covariances_are_lateral_r_and_depth_factor_r() -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(5, 3)) + np.array([0.0, 0.0, 1.0])
    points[2] = np.nan
    R = ray_measurement_covariances(points, 2e-5, 4.0)
    for i in (0, 1, 3, 4):
        u = points[i] / np.linalg.norm(points[i])
        # Round-off ~eps (2.2e-16) of |R| ~ 8e-5: ~2e-20, the tolerance 50x that.
        np.testing.assert_allclose(R[i] @ u, 8e-5 * u, atol=1e-18)  # along the ray: 4 r
        lateral = np.cross(u, [1.0, 0.0, 0.0])
        np.testing.assert_allclose(R[i] @ lateral, 2e-5 * lateral, atol=1e-18)
    np.testing.assert_allclose(R[2], 2e-5 * np.eye(3))  # no ray: isotropic
    np.testing.assert_allclose(ray_measurement_covariances(points[:2], 2e-5, 1.0),
                               np.broadcast_to(2e-5 * np.eye(3), (2, 3, 3)))


def test_articulation_variance_grows_along_each_finger_from_the_palm() -> None:
    pb = HAND - HAND[1:].mean(axis=0)
    var = articulation_variances(pb, 0.1)
    assert (var[list(PALM)] == 0.0).all()  # bit-exact: no joint between them and the palm
    for base in (5, 9, 13, 17):  # MCP, PIP, DIP, tip
        assert 0.0 < var[base + 1] < var[base + 2] < var[base + 3]
    # Index tip: flexion at MCP, PIP and DIP moves it by theta times its distance to each.
    expected = sum(float(np.sum((pb[8] - pb[j]) ** 2)) for j in (5, 6, 7)) * 0.01 / 3.0
    assert var[8] == pytest.approx(expected)
    assert var[2] == pytest.approx(float(np.sum((pb[2] - pb[1]) ** 2)) * 0.01 / 3.0)  # thumb MCP
    assert (articulation_variances(pb, 0.0) == 0.0).all()  # bit-exact: times 0
    missing = pb.copy()
    missing[6] = np.nan  # a joint outside the model contributes nothing
    assert articulation_variances(missing, 0.1)[7] == pytest.approx(
        float(np.sum((pb[7] - pb[5]) ** 2)) * 0.01 / 3.0)


def test_body_covariances_add_articulation_and_ablation_is_uniform() -> None:
    config = TrackerConfig()
    rng = np.random.default_rng(1)
    A = rng.normal(size=(21, 3, 3))
    P = A @ A.transpose(0, 2, 1) * 1e-5
    art = np.linspace(0.0, 1e-4, 21)
    R = body_measurement_covariances(P, config, art)
    s = np.asarray(config.saliency_factors())
    np.testing.assert_allclose(R, s[:, None, None] * P + art[:, None, None] * np.eye(3))
    ablation = dataclasses.replace(config, use_uncertainty_models=False)
    np.testing.assert_array_equal(body_measurement_covariances(P, ablation, art),  # constant
                                  np.broadcast_to(0.05 * np.eye(3), (21, 3, 3)))


def test_a_lost_landmark_restarts_only_within_the_gate() -> None:
    """One skipped correction drops a Table-I filter; a confirmed one (lm_confirm_corrections)
    keeps predicting, and its landmark restarts only on a measurement within M_lm of that
    prediction: an outlier that follows the miss starts nothing, the landmark where it belongs
    does. An unconfirmed filter (one born from an outlier, say) is no reference: its landmark
    restarts anywhere. So does every landmark in the ablation (no gates)."""
    config = TrackerConfig()
    assert config.lm_confirm_corrections == 3
    for corrections, gated in ((30, True), (1, False)):
        for gate in (True, False):
            bank = LandmarkFilterBank(1, config)
            z = np.zeros((1, 3))
            bank.update(z, config.r_lm_m2, gate=gate)
            for _ in range(corrections):
                bank.predict(config.nominal_dt_s)
                bank.update(z, config.r_lm_m2, gate=gate)
            bank.predict(config.nominal_dt_s)
            lost = bank.update(np.full((1, 3), np.nan), config.r_lm_m2, gate=gate)  # a miss
            assert lost.dropped[0] and not bank.alive[0]
            bank.predict(config.nominal_dt_s)
            outlier = bank.update(np.array([[0.3, 0.0, 0.0]]), config.r_lm_m2, gate=gate)
            if gated and gate:
                assert outlier.rejected[0] and not outlier.fresh[0] and not bank.alive[0]
                assert outlier.mahalanobis[0] >= config.mahalanobis_lm
                bank.predict(config.nominal_dt_s)
                back = bank.update(np.array([[0.01, 0.0, 0.0]]), config.r_lm_m2, gate=gate)
                assert back.fresh[0] and bank.alive[0]
                np.testing.assert_array_equal(bank.x[0, :3], [0.01, 0.0, 0.0])
            else:
                assert outlier.fresh[0] and bank.alive[0]  # started at the outlier
                np.testing.assert_array_equal(bank.x[0, :3], [0.3, 0.0, 0.0])
    # forget() drops the past too: a new hand in these rows starts ungated.
    bank = LandmarkFilterBank(1, config)
    for _ in range(10):
        bank.update(np.zeros((1, 3)), config.r_lm_m2)
        bank.predict(config.nominal_dt_s)
    bank.update(np.full((1, 3), np.nan), config.r_lm_m2)
    assert bank.has_past[0]
    bank.forget(np.array([True]))
    bank.predict(config.nominal_dt_s)
    assert bank.update(np.array([[0.5, 0.0, 0.0]]), config.r_lm_m2).fresh[0]
