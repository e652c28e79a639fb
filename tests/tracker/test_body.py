"""Body EKF: Jacobians by finite differences, information form = textbook stacked update,
likelihoods, gates, model choice."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal  # type: ignore[import-untyped]

from services.common.se3 import se3_exp, se3_inverse, se3_log, transform_points
from services.tracker.body import (
    HandBodyEkf,
    Prediction,
    body_noise_matrices,
    informative,
    innovation_covariance,
    merge_pose,
    select_and_gate,
)
from services.tracker.body_measurement import (
    information_sums,
    log_likelihoods,
    measurement_jacobians,
    posterior_residual_passes,
    predicted_points,
    prior_gate_passes,
)
from services.tracker.landmarks import inv_sym3
from tests.tracker.handgen import HAND

RNG_SEED = 11


def random_spd(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(n, n))
    spd: np.ndarray = scale * (A @ A.T / n + 0.1 * np.eye(n))
    return spd


def make_ekf(rng: np.random.Generator) -> HandBodyEkf:
    T = se3_exp(np.array([0.1, -0.05, 0.6, 0.3, -0.2, 0.4]))
    P0, Q = body_noise_matrices((0.05, 0.2, 0.1, 0.2), (0.75, 3.0, 2.4, 4.8))
    ekf = HandBodyEkf(T, np.array([0.2, -0.1, 0.05, 0.8, -1.5, 0.4]), P0, Q, 1.0 / 30.0)
    ekf.P = random_spd(rng, 12, 0.05)
    return ekf


def test_measurement_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(RNG_SEED)
    T = se3_exp(rng.normal(size=6))
    p = rng.normal(size=3)

    def h(delta: np.ndarray) -> np.ndarray:
        point: np.ndarray = transform_points(se3_exp(delta) @ T, p[None])[0]
        return point

    H = measurement_jacobians(h(np.zeros(6))[None])[0]
    eps = 1e-6
    J = np.column_stack([(h(eps * e) - h(-eps * e)) / (2 * eps) for e in np.eye(6)])
    # Central differences: round-off 2.2e-16 |h| / eps (|h| ~ 2) ~ 4e-10 over a 1e-12 truncation.
    np.testing.assert_allclose(H, J, atol=1e-9)


def test_constant_velocity_transition_matches_finite_differences() -> None:
    rng = np.random.default_rng(RNG_SEED)
    ekf = make_ekf(rng)
    dt = 0.1  # large enough for Ad(Exp(dt xi)) and J_l(dt xi) to differ from I
    T_hat, xi_hat = ekf.T.copy(), ekf.xi.copy()
    _, F = ekf.transition(dt)

    def propagate(dx: np.ndarray) -> np.ndarray:
        T = se3_exp(dx[:6]) @ T_hat
        xi = xi_hat + dx[6:]
        T_next = se3_exp(dt * xi) @ T
        T_ref = se3_exp(dt * xi_hat) @ T_hat
        return np.concatenate([se3_log(T_next @ se3_inverse(T_ref)), xi - xi_hat])

    eps = 1e-6
    J = np.column_stack([(propagate(eps * e) - propagate(-eps * e)) / (2 * eps)
                         for e in np.eye(12)])
    # Central differences through exp/log of poses: round-off ~eps (2.2e-16) |log| (~1) / 1e-6
    # ~ 2e-10 plus a truncation ~1e-12 times the third derivative of log(Exp(dt xi) ...).
    np.testing.assert_allclose(F, J, atol=1e-7)


def test_information_form_update_equals_textbook_stacked_update() -> None:
    rng = np.random.default_rng(RNG_SEED)
    ekf = make_ekf(rng)
    prior = ekf.predict(1.0 / 30.0)[1]
    pb = HAND[1:] - HAND[1:].mean(axis=0)
    T_true = se3_exp(rng.normal(scale=0.02, size=6)) @ prior.T
    z = transform_points(T_true, pb) + rng.normal(scale=0.01, size=pb.shape)
    r = rng.uniform(0.01, 0.06, size=20)

    ekf.update(prior, z, pb, r)

    n = pb.shape[0]
    q = predicted_points(prior.T, pb)
    H = np.zeros((3 * n, 12))
    H[:, :6] = measurement_jacobians(q).reshape(3 * n, 6)
    R = np.diag(np.repeat(r, 3))
    S = H @ prior.P @ H.T + R
    # The same products in the same order: equal to ~12 eps (2.2e-16) of |S| <= 1, < 1e-14.
    np.testing.assert_allclose(S, innovation_covariance(prior, pb, r), atol=1e-14)
    K = np.linalg.solve(S, H @ prior.P).T  # K = P H' S^-1
    dx = K @ (z - q).ravel()
    I_KH = np.eye(12) - K @ H
    P_post = I_KH @ prior.P @ I_KH.T + K @ R @ K.T
    # Two exact forms, so round-off only: the textbook one solves S (cond ~1e3), bounded by
    # ~eps (2.2e-16) * 1e3 * |P| (~5) ~ 1e-12 (observed ~1e-13).
    np.testing.assert_allclose(ekf.T, se3_exp(dx[:6]) @ prior.T, atol=1e-12)
    np.testing.assert_allclose(ekf.xi, prior.xi + dx[6:], atol=1e-12)
    np.testing.assert_allclose(ekf.P, P_post, atol=1e-12)
    assert np.linalg.eigvalsh(ekf.P).min() > 0.0


def test_stacked_log_likelihood_matches_dense_gaussian() -> None:
    rng = np.random.default_rng(RNG_SEED)
    ekf = make_ekf(rng)
    preds = ekf.predict(1.0 / 30.0)
    pb = HAND[1:] - HAND[1:].mean(axis=0)
    z = transform_points(preds[0].T, pb) + rng.normal(scale=0.05, size=pb.shape)
    r = rng.uniform(0.01, 0.06, size=20)
    T = np.stack([p.T for p in preds])
    q = predicted_points(T, pb)
    A, b, c = information_sums(q, z[None] - q, 1.0 / r)
    P = np.stack([p.P[:6, :6] for p in preds])
    ll = log_likelihoods(P, A, b, c, float(3 * np.log(r).sum()), 20)
    for m, p in enumerate(preds):
        S = innovation_covariance(p, pb, r)
        dense = multivariate_normal(mean=np.zeros(60), cov=S).logpdf((z - q[m]).ravel())
        # Round-off of a 60-D quadratic form and log-det: ~eps (2.2e-16) * cond(S) (~1.5e3)
        # * 60 terms ~ 2e-11 on a log-likelihood of ~40.
        assert ll[m] == pytest.approx(dense, rel=1e-10, abs=1e-8)


def test_leave_one_out_gate_equals_brute_force_refits() -> None:
    rng = np.random.default_rng(RNG_SEED)
    ekf = make_ekf(rng)
    prior = ekf.predict(1.0 / 30.0)[0]
    P = prior.P[:6, :6]
    pb = HAND[1:] - HAND[1:].mean(axis=0)
    z = transform_points(se3_exp(rng.normal(scale=0.01, size=6)) @ prior.T, pb)
    z += rng.normal(scale=0.004, size=z.shape)
    z[4] += [0.0, 0.05, 0.0]
    r = np.full(20, 1e-4)
    q = predicted_points(prior.T, pb)
    y = z - q
    H = measurement_jacobians(q)
    A_all, b_all, _ = information_sums(q[None], y[None], 1.0 / r)
    dist = np.empty(20)
    for i in range(20):  # refit without landmark i, predict it, Mahalanobis distance
        w = 1.0 / r
        w[i] = 0.0
        A, b, _ = information_sums(q[None], y[None], w)
        Lam = np.linalg.inv(P) + A[0]
        delta = np.linalg.solve(Lam, b[0])
        S = H[i] @ np.linalg.inv(Lam) @ H[i].T + r[i] * np.eye(3)
        e = y[i] - H[i] @ delta
        dist[i] = np.sqrt(e @ np.linalg.solve(S, e))
    assert dist[4] > 4.0  # the injected 5 cm jump stands out ...
    assert np.delete(dist, 4).max() < 2.0  # ... from 4 mm noise against a 1 cm sigma
    # Exact booleans: the two distances agree to ~1e-13 relative (round-off), and none lies
    # closer than 4e-4 relative to a threshold, so no decision can flip.
    for thr in (1.0, 2.0, 3.0, 5.0):
        passes = posterior_residual_passes(q, y, r, P, A_all[0], b_all[0], thr)
        np.testing.assert_array_equal(passes, dist < thr)


def test_prior_gate_equals_explicit_distances() -> None:
    rng = np.random.default_rng(RNG_SEED)
    ekf = make_ekf(rng)
    preds = ekf.predict(1.0 / 30.0)
    pb = HAND[1:] - HAND[1:].mean(axis=0)
    z = transform_points(preds[0].T, pb) + rng.normal(scale=0.3, size=pb.shape)
    r = rng.uniform(0.01, 0.06, size=20)
    T = np.stack([p.T for p in preds])
    P = np.stack([p.P[:6, :6] for p in preds])
    q = predicted_points(T, pb)
    y = z[None] - q
    H = measurement_jacobians(q)
    S = H @ P[:, None] @ H.transpose(0, 1, 3, 2) + r[:, None, None] * np.eye(3)
    d = np.sqrt(np.einsum("mni,mni->mn", y, np.linalg.solve(S, y[..., None])[..., 0]))
    for thr in (0.1, 0.25, 0.5):  # exact booleans: no distance within 1 % of a threshold
        np.testing.assert_array_equal(prior_gate_passes(q, y, P, r, thr), d < thr)


def test_merge_pose_keeps_blocks_and_stays_positive_definite() -> None:
    rng = np.random.default_rng(RNG_SEED)
    Pv = random_spd(rng, 12, 1.0)
    Pp = random_spd(rng, 6, 0.01)
    P, repaired = merge_pose(Pv, Pp)
    assert not repaired
    np.testing.assert_allclose(P[:6, :6], Pp)
    np.testing.assert_allclose(P[6:, 6:], Pv[6:, 6:])
    np.testing.assert_allclose(P, P.T)
    assert np.linalg.eigvalsh(P).min() > 0.0


def test_merge_pose_repairs_blocks_without_a_cholesky_factor() -> None:
    """Issue 13: under a flood of frames microseconds apart merge_pose raised LinAlgError (a
    pose block with no Cholesky factor) and a negative variance was published. Now the inputs
    are repaired, the result is positive definite, and the repair is reported."""
    rng = np.random.default_rng(RNG_SEED)
    Pv = random_spd(rng, 12, 1.0)
    Pp = random_spd(rng, 6, 0.01)
    w, V = np.linalg.eigh(Pp)
    w[0] = -1e-9 * w[-1]  # round-off made the pose block indefinite
    Pp_bad = (V * w) @ V.T
    Pp_bad = 0.5 * (Pp_bad + Pp_bad.T)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.cholesky(Pp_bad)
    P, repaired = merge_pose(Pv, Pp_bad)
    assert repaired
    assert np.linalg.eigvalsh(P).min() > 0.0
    # Only the eigenvalue that round-off broke moved: ~1e-9 of the block.
    np.testing.assert_allclose(P[:6, :6], Pp_bad, atol=1e-8 * np.abs(Pp).max())
    P_nan, repaired = merge_pose(Pv, np.full((6, 6), np.nan))
    assert repaired and np.isfinite(P_nan[6:, 6:]).all()
    np.testing.assert_array_equal(P_nan[:6, 6:], 0.0)  # no cross-covariance from garbage


def test_repeated_exact_updates_converge_to_the_truth() -> None:
    rng = np.random.default_rng(RNG_SEED)
    ekf = make_ekf(rng)
    pb = HAND[1:] - HAND[1:].mean(axis=0)
    T_true = se3_exp(np.array([0.03, -0.02, 0.01, 0.2, 0.1, -0.15])) @ ekf.T
    for _ in range(30):
        prior = ekf.predict(1.0 / 30.0)[0]
        ekf.update(prior, transform_points(T_true, pb), pb, np.full(20, 0.04))
    # Noise-free Gauss-Newton steps reach the round-off floor, ~eps (2.2e-16) at |T| ~ 1.
    assert np.linalg.norm(se3_log(T_true @ se3_inverse(ekf.T))) < 1e-10


def _predictions_and_landmarks(rng: np.random.Generator, move: np.ndarray
                               ) -> tuple[list[Prediction], np.ndarray, np.ndarray, np.ndarray]:
    """A moving body (twist ``move`` per frame, known to the filter) and its landmarks."""
    T = se3_exp(np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0]))
    _, Q = body_noise_matrices((1e-6, 1e-5, 1e-2, 1e-1), (1e-6, 1e-5, 1e-2, 1e-1))
    dt = 1.0 / 30.0
    ekf = HandBodyEkf(T, move / dt, 1e-6 * np.eye(12), Q, dt)
    preds = ekf.predict(dt)
    pb = HAND[1:] - HAND[1:].mean(axis=0)
    r = np.full(20, 1e-5)
    return preds, pb, r, T


def test_the_model_whose_mean_explains_the_landmarks_wins() -> None:
    rng = np.random.default_rng(RNG_SEED)
    move = np.array([0.01, 0.0, 0.0, 0.0, 0.05, 0.0])  # 1 cm and 3 deg in one frame
    preds, pb, r, T = _predictions_and_landmarks(rng, move)
    noise = rng.normal(scale=0.002, size=pb.shape)
    moved = transform_points(se3_exp(move) @ T, pb) + noise
    still = transform_points(T, pb) + noise
    step = select_and_gate(preds, moved, pb, r, threshold=4.0, gate=True)
    assert preds[step.model].model == "constant_velocity" and step.accepted.all()
    step = select_and_gate(preds, still, pb, r, threshold=4.0, gate=True)
    assert preds[step.model].model == "static" and step.accepted.all()


def test_kinematic_prediction_wins_when_right_and_loses_when_wrong() -> None:
    rng = np.random.default_rng(RNG_SEED)
    move = np.array([0.01, 0.0, 0.0, 0.0, 0.05, 0.0])
    _, pb, r, T = _predictions_and_landmarks(rng, np.zeros(6))
    _, Q = body_noise_matrices((1e-6, 1e-5, 1e-2, 1e-1), (1e-6, 1e-5, 1e-2, 1e-1))
    dt = 1.0 / 30.0
    ekf = HandBodyEkf(T, np.zeros(6), 1e-6 * np.eye(12), Q, dt)
    z = transform_points(se3_exp(move) @ T, pb) + rng.normal(scale=0.002, size=pb.shape)
    right = ekf.predict(dt, (se3_exp(move) @ T, 1e-6 * np.eye(6)))
    # displacement / dt: log of a pose product, ~eps (2.2e-16) at |T| ~ 1, times 1 / dt = 30.
    np.testing.assert_allclose(right[2].xi, move / dt, atol=1e-12)
    step = select_and_gate(right, z, pb, r, threshold=4.0, gate=True)
    assert right[step.model].model == "kinematic"
    wrong = ekf.predict(dt, (se3_exp(-move) @ T, 1e-6 * np.eye(6)))
    step = select_and_gate(wrong, z, pb, r, threshold=4.0, gate=True)
    assert wrong[step.model].model != "kinematic"


def test_gates_reject_a_jumped_landmark_and_ablation_keeps_it() -> None:
    rng = np.random.default_rng(RNG_SEED)
    preds, pb, r, T = _predictions_and_landmarks(rng, np.zeros(6))
    z = transform_points(T, pb) + rng.normal(scale=0.003, size=pb.shape)
    z[7] += [0.05, 0.0, 0.0]
    step = select_and_gate(preds, z, pb, r, threshold=4.0, gate=True)
    assert np.flatnonzero(step.rejected).tolist() == [7]
    step = select_and_gate(preds, z, pb, r, threshold=4.0, gate=False)
    assert step.accepted.all()


def random_covariances(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    """n random SPD 3x3 matrices, strongly anisotropic (like ray-aligned landmark noise)."""
    A = rng.normal(size=(n, 3, 3))
    out: np.ndarray = scale * (A @ A.transpose(0, 2, 1) + 0.05 * np.eye(3))
    return out


def test_full_covariance_update_and_likelihood_equal_the_dense_forms() -> None:
    """Per-landmark 3x3 R_i (anisotropic): the information-form update and log-likelihood equal
    the textbook stacked update and the dense Gaussian."""
    rng = np.random.default_rng(RNG_SEED)
    ekf = make_ekf(rng)
    preds = ekf.predict(1.0 / 30.0)
    prior = preds[1]
    pb = HAND[1:] - HAND[1:].mean(axis=0)
    R = random_covariances(rng, 20, 1e-3)
    z = transform_points(se3_exp(rng.normal(scale=0.02, size=6)) @ prior.T, pb)
    z += rng.normal(scale=0.01, size=pb.shape)
    n = pb.shape[0]
    q = predicted_points(prior.T, pb)
    H = np.zeros((3 * n, 12))
    H[:, :6] = measurement_jacobians(q).reshape(3 * n, 6)
    R_dense = np.zeros((3 * n, 3 * n))
    for i in range(n):
        R_dense[3 * i:3 * i + 3, 3 * i:3 * i + 3] = R[i]
    S = H @ prior.P @ H.T + R_dense
    np.testing.assert_allclose(S, innovation_covariance(prior, pb, R), atol=1e-14)  # as above
    W, _ = inv_sym3(R)
    A, b, c = information_sums(q[None], (z - q)[None], W)
    # R_i^-1 by cofactors vs an LU solve: ~eps (2.2e-16) * cond(R_i) (<= ~1.4e2) per term, more
    # in entries that cancel; 1e-9 relative stays well above.
    np.testing.assert_allclose(A[0], H[:, :6].T @ np.linalg.solve(R_dense, H[:, :6]), rtol=1e-9)
    np.testing.assert_allclose(b[0], H[:, :6].T @ np.linalg.solve(R_dense, (z - q).ravel()),
                               rtol=1e-9)
    ll = log_likelihoods(prior.P[None, :6, :6], A, b, c, float(np.log(np.linalg.det(R)).sum()), n)
    dense = multivariate_normal(mean=np.zeros(3 * n), cov=S).logpdf((z - q).ravel())
    assert ll[0] == pytest.approx(dense, rel=1e-10, abs=1e-8)  # round-off as in the isotropic test
    ekf.update(prior, z, pb, R)
    K = np.linalg.solve(S, H @ prior.P).T
    dx = K @ (z - q).ravel()
    I_KH = np.eye(12) - K @ H
    # cond(S) ~3e5 here, but the error is relative to the small corrections (|dx| ~ 1e-2) and
    # gains: ~eps (2.2e-16) * 3e5 * 1e-2 ~ 7e-13 (observed ~3e-13).
    np.testing.assert_allclose(ekf.T, se3_exp(dx[:6]) @ prior.T, atol=1e-12)
    np.testing.assert_allclose(ekf.P, I_KH @ prior.P @ I_KH.T + K @ R_dense @ K.T, atol=1e-12)


def test_gates_with_full_covariances_equal_explicit_distances() -> None:
    rng = np.random.default_rng(RNG_SEED)
    ekf = make_ekf(rng)
    prior = ekf.predict(1.0 / 30.0)[0]
    P = prior.P[:6, :6]
    pb = HAND[1:] - HAND[1:].mean(axis=0)
    R = random_covariances(rng, 20, 2e-5)
    z = transform_points(se3_exp(rng.normal(scale=0.01, size=6)) @ prior.T, pb)
    z += np.einsum("nij,nj->ni", np.linalg.cholesky(R), rng.normal(size=(20, 3)))
    z[4] += [0.0, 0.05, 0.0]
    q = predicted_points(prior.T, pb)
    y = z - q
    H = measurement_jacobians(q)
    W, _ = inv_sym3(R)
    A_all, b_all, _ = information_sums(q[None], y[None], W)
    loo = np.empty(20)
    prior_d = np.empty(20)
    for i in range(20):
        Wi = W.copy()
        Wi[i] = 0.0
        A, b, _ = information_sums(q[None], y[None], Wi)
        Lam = np.linalg.inv(P) + A[0]
        e = y[i] - H[i] @ np.linalg.solve(Lam, b[0])
        loo[i] = np.sqrt(e @ np.linalg.solve(H[i] @ np.linalg.inv(Lam) @ H[i].T + R[i], e))
        prior_d[i] = np.sqrt(y[i] @ np.linalg.solve(H[i] @ P @ H[i].T + R[i], y[i]))
    assert loo[4] > 4.0
    for thr in (1.0, 2.0, 3.0, 5.0):  # exact booleans: no distance within 3 % of a threshold
        np.testing.assert_array_equal(
            posterior_residual_passes(q, y, R, P, A_all[0], b_all[0], thr), loo < thr)
        np.testing.assert_array_equal(prior_gate_passes(q[None], y[None], P[None], R, thr)[0],
                                      prior_d < thr)


def test_only_an_informative_kinematic_prediction_is_offered() -> None:
    """A kinematic prediction vaguer than the constant-velocity one in any direction (a joint
    filter that has just started) is left out of the model choice."""
    T = se3_exp(np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0]))
    _, Q = body_noise_matrices((1e-6, 1e-5, 1e-2, 1e-1), (1e-6, 1e-5, 1e-2, 1e-1))
    ekf = HandBodyEkf(T, np.zeros(6), 1e-6 * np.eye(12), Q, 1.0 / 30.0)
    precise = ekf.predict(1.0 / 30.0, (T, 1e-7 * np.eye(6)))
    assert [p.model for p in precise] == ["static", "constant_velocity", "kinematic"]
    vague = np.diag([1e-7] * 5 + [1.0])  # one direction (a rotation) is unknown
    assert [p.model for p in ekf.predict(1.0 / 30.0, (T, vague))] == ["static",
                                                                       "constant_velocity"]
    P_cv = precise[1].P[:6, :6]
    assert informative(0.5 * P_cv, P_cv) and informative(P_cv, P_cv)
    assert not informative(P_cv + 1e-9 * np.eye(6), P_cv)
