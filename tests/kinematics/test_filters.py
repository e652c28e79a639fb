"""Joint filters: every EKF Jacobian against central differences, fast geometry against se3, and
the filters' behaviour (group innovation past pi, axes at the poles, Joseph form)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest

from services.common import se3
from services.kinematics.config import KinematicsConfig
from services.kinematics.filters import (
    DisconnectedJoint,
    PrismaticJoint,
    RevoluteJoint,
    RigidJoint,
    axis_basis_change,
    inflated_noise,
    prismatic_noise_inflation,
    prismatic_twist_jacobian,
    revolute_delta,
    revolute_left_jacobian,
    revolute_noise_inflation,
    revolute_twist,
    revolute_twist_jacobian,
    rotate_axis,
    tangent_basis,
)
from services.kinematics.filters import geometry as g
from tests.kinematics import unit

Array = np.ndarray
CFG = KinematicsConfig()
EPS = 1e-6

POLES = [np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0]),
         np.array([0.0, -1.0, 0.0])]


def numeric_jacobian(f: Callable[[Array], Array], n: int, eps: float = EPS) -> Array:
    """Central differences of ``f`` at 0 (the error state of a filter)."""
    cols = []
    for i in range(n):
        e = np.zeros(n)
        e[i] = eps
        cols.append((f(e) - f(-e)) / (2.0 * eps))
    return np.stack(cols, axis=1)


def random_axes(rng: np.random.Generator, n: int) -> list[Array]:
    return [unit(rng.normal(size=3)) for _ in range(n)] + POLES


# --------------------------------------------------------------------------------------------
# Fast geometry == services.common.se3
# --------------------------------------------------------------------------------------------


def _test_twists(rng: np.random.Generator) -> list[Array]:
    xs = [rng.normal(size=6) for _ in range(20)]
    for angle in (0.0, 1e-9, 1e-5, 1e-3, math.pi - 1e-7, math.pi, 2.5):
        w = unit(rng.normal(size=3)) * angle
        xs.append(np.concatenate([rng.normal(size=3), w]))
    return xs


def test_fast_geometry_matches_se3() -> None:
    rng = np.random.default_rng(0)
    for xi in _test_twists(rng):
        T = se3.se3_exp(xi)
        np.testing.assert_allclose(g.se3_exp_fast(xi), T, atol=1e-12)
        np.testing.assert_allclose(g.so3_exp_fast(xi[3:]), se3.so3_exp(xi[3:]), atol=1e-12)
        np.testing.assert_allclose(g.so3_left_jacobian_fast(xi[3:]),
                                   se3.so3_left_jacobian(xi[3:]), atol=1e-12)
        np.testing.assert_allclose(g.se3_log_fast(T), se3.se3_log(T), atol=1e-9)
        np.testing.assert_allclose(g.so3_log_fast(T[:3, :3]), se3.so3_log(T[:3, :3]), atol=1e-9)
        np.testing.assert_allclose(g.se3_inverse_fast(T), se3.se3_inverse(T), atol=1e-12)
        np.testing.assert_allclose(g.adjoint_fast(T), se3.se3_adjoint(T), atol=1e-12)
        assert g.rotation_angle_fast(T[:3, :3]) == pytest.approx(se3.rotation_angle(T[:3, :3]),
                                                                 abs=1e-9)
        a, b = rng.normal(size=3), rng.normal(size=3)
        np.testing.assert_allclose(g.cross3(a, b), np.cross(a, b), atol=1e-15)


def test_revolute_left_jacobian_matches_se3() -> None:
    rng = np.random.default_rng(1)
    for u in random_axes(rng, 6):
        p = rng.normal(size=3)
        p -= (p @ u) * u
        for q in (0.0, 1e-6, 0.4, -2.0, math.pi, 5.0, -7.5):
            xi = revolute_twist(u, p, q)
            np.testing.assert_allclose(revolute_left_jacobian(u, p, q),
                                       se3.se3_left_jacobian(xi), atol=1e-10)
            np.testing.assert_allclose(revolute_delta(u, p, q), se3.se3_exp(xi), atol=1e-12)


# --------------------------------------------------------------------------------------------
# Axis parameterisation
# --------------------------------------------------------------------------------------------


def test_tangent_basis_orthonormal_right_handed() -> None:
    rng = np.random.default_rng(2)
    extra = [unit(np.array([1.0, 1.0, 1.0])), unit(np.array([1.0, -1.0, 0.0]))]
    for u in [*random_axes(rng, 30), *extra]:
        B = tangent_basis(u)
        M = np.column_stack([B, u])
        np.testing.assert_allclose(M.T @ M, np.eye(3), atol=1e-14)
        assert np.linalg.det(M) == pytest.approx(1.0)
        np.testing.assert_array_equal(tangent_basis(u), B)  # deterministic


def test_rotate_axis_keeps_unit_basis_and_derivative() -> None:
    rng = np.random.default_rng(3)
    for u in random_axes(rng, 10):
        B = tangent_basis(u)
        for _ in range(3):
            u2, B2 = rotate_axis(u, B, rng.normal(scale=0.3, size=2))
            M = np.column_stack([B2, u2])
            np.testing.assert_allclose(M.T @ M, np.eye(3), atol=1e-12)
            assert np.linalg.det(M) == pytest.approx(1.0)
        # du/db = B at b = 0
        J = numeric_jacobian(lambda b, u=u, B=B: rotate_axis(u, B, b)[0], 2)
        np.testing.assert_allclose(J, B, atol=1e-8)


def test_axis_basis_change_maps_tangent_coordinates() -> None:
    rng = np.random.default_rng(4)
    u = unit(rng.normal(size=3))
    B = rotate_axis(u, tangent_basis(u), np.zeros(2))[1] @ np.array(
        [[math.cos(0.7), -math.sin(0.7)], [math.sin(0.7), math.cos(0.7)]])
    for sign in (1.0, -1.0):
        Bo = tangent_basis(sign * u)
        T = axis_basis_change(B, Bo, sign)
        b = np.array([1e-7, -2e-7])
        du = rotate_axis(u, B, b)[0] - u
        np.testing.assert_allclose(sign * du, Bo @ (T @ b), atol=1e-13)


# --------------------------------------------------------------------------------------------
# Twist Jacobians
# --------------------------------------------------------------------------------------------


def test_prismatic_twist_jacobian() -> None:
    rng = np.random.default_rng(5)
    for u in random_axes(rng, 5):
        B = tangent_basis(u)
        q = float(rng.normal())

        def h(d: Array, u: Array = u, B: Array = B, q: float = q) -> Array:
            ud = rotate_axis(u, B, d[:2])[0]
            return np.concatenate([(q + d[2]) * ud, np.zeros(3)])

        np.testing.assert_allclose(prismatic_twist_jacobian(u, B, q), numeric_jacobian(h, 4),
                                   atol=1e-8)


def test_revolute_twist_jacobian() -> None:
    rng = np.random.default_rng(6)
    for u in random_axes(rng, 5):
        B = tangent_basis(u)
        p = rng.normal(size=3)
        q = float(rng.normal(scale=3.0))

        def h(d: Array, u: Array = u, B: Array = B, p: Array = p, q: float = q) -> Array:
            return revolute_twist(rotate_axis(u, B, d[:2])[0], p + d[2:5], q + d[5])

        np.testing.assert_allclose(revolute_twist_jacobian(u, p, B, q), numeric_jacobian(h, 7),
                                   atol=1e-7)


# --------------------------------------------------------------------------------------------
# Filter Jacobians (measurement, transition) and predicted-delta Jacobians
# --------------------------------------------------------------------------------------------


def _prismatic(rng: np.random.Generator, u: Array) -> PrismaticJoint:
    f = PrismaticJoint(CFG, u, float(rng.normal(scale=0.2)), qdot=float(rng.normal()),
                       offset=rng.normal(scale=0.01, size=3))
    f.B = tangent_basis(f.u) @ np.array([[0.6, -0.8], [0.8, 0.6]])  # any right-handed basis
    return f


def _prismatic_measurement(f: PrismaticJoint, d: Array) -> Array:
    u = rotate_axis(f.u, f.B, d[:2])[0]
    return (f.q + d[2]) * u + f.o + d[4:7]


def test_prismatic_measurement_jacobian() -> None:
    rng = np.random.default_rng(7)
    for u in random_axes(rng, 5):
        f = _prismatic(rng, u)
        J = numeric_jacobian(lambda d, f=f: _prismatic_measurement(f, d), 7)
        np.testing.assert_allclose(f.measurement_jacobian(), J, atol=1e-8)
        np.testing.assert_allclose(f.measurement(), _prismatic_measurement(f, np.zeros(7)))


def _revolute(rng: np.random.Generator, u: Array, q: float) -> RevoluteJoint:
    p = rng.normal(scale=0.5, size=3)
    f = RevoluteJoint(CFG, u, p, q, qdot=float(rng.normal()),
                      reference_correction=se3.se3_exp(rng.normal(scale=0.05, size=6)))
    f.B = tangent_basis(f.u) @ np.array([[0.6, 0.8], [-0.8, 0.6]])  # any right-handed basis
    return f


def _revolute_prediction(f: RevoluteJoint, d: Array) -> Array:
    """``Exp(h(x + d)) E(d)`` with the filter's retraction (axis, point in the plane, E)."""
    u = rotate_axis(f.u, f.B, d[0:2])[0]
    p = f.p + f.B @ d[2:4]
    p = p - (p @ u) * u
    E = se3.se3_exp(d[6:12]) @ f.E
    return revolute_delta(u, p, f.q + d[4]) @ E


@pytest.mark.parametrize("q", [0.3, -1.2, math.pi - 1e-3, math.pi + 0.2, 5.5, 2 * math.pi + 0.3])
def test_revolute_measurement_jacobian_on_the_group(q: float) -> None:
    """H is the derivative of log(Exp(h(x + d)) E(d) (Exp(h(x)) E)^-1) at d = 0."""
    rng = np.random.default_rng(8)
    for u in random_axes(rng, 4):
        f = _revolute(rng, u, q)
        M0_inv = se3.se3_inverse(f.measurement())

        def r(d: Array, f: RevoluteJoint = f, M0_inv: Array = M0_inv) -> Array:
            return se3.se3_log(_revolute_prediction(f, d) @ M0_inv)

        np.testing.assert_allclose(f.measurement_jacobian(), numeric_jacobian(r, 12), atol=2e-7)
        np.testing.assert_allclose(f.measurement(), _revolute_prediction(f, np.zeros(12)),
                                   atol=1e-12)


@pytest.mark.parametrize("joint", ["prismatic", "revolute"])
def test_transition_jacobian_and_in_place_predict(joint: str) -> None:
    rng = np.random.default_rng(9)
    u = unit(rng.normal(size=3))
    f: PrismaticJoint | RevoluteJoint = (_prismatic(rng, u) if joint == "prismatic"
                                         else _revolute(rng, u, 0.7))
    A = rng.normal(size=(f.dim, f.dim))
    f.P = A @ A.T
    dt = 0.04
    iq, iqd = (2, 3) if joint == "prismatic" else (4, 5)

    def step(d: Array) -> Array:  # the state map on the (q, qdot) part; the rest is identity
        x = d.copy()
        x[iq] += dt * d[iqd]
        return x

    F = f.transition_matrix(dt)
    np.testing.assert_allclose(F, numeric_jacobian(step, f.dim), atol=1e-9)
    expected = F @ f.P @ F.T + f.process_noise(dt)
    q0, qd0 = f.q, f.qdot
    f.predict(dt)
    np.testing.assert_allclose(f.P, expected, atol=1e-12)
    np.testing.assert_array_equal(f.P, f.P.T)
    assert f.q == pytest.approx(q0 + dt * qd0)


def test_process_noise_is_table_one_dt_scaled() -> None:
    # Table I's values (the defaults lower the axis and point noise; config docstring).
    table_one = dataclasses.replace(CFG, prismatic_axis_noise_rad2_per_s3=2.55,
                                    revolute_axis_noise_rad2_per_s3=2.55,
                                    revolute_point_noise_m2_per_s3=0.3)
    dt = 1.0 / 30.0
    c = dt**3 / 3.0
    pq = np.diag(PrismaticJoint(table_one, np.array([0.0, 0.0, 1.0]), 0.1).process_noise(dt))
    np.testing.assert_allclose(pq, [2.55 * c, 2.55 * c, 0.7 * c, 75.0 * dt, 0, 0, 0])
    rq = np.diag(RevoluteJoint(table_one, np.array([0.0, 0.0, 1.0]), np.zeros(3),
                               0.1).process_noise(dt))
    np.testing.assert_allclose(rq, [2.55 * c, 2.55 * c, 0.3 * c, 0.3 * c, 5.1 * c, 75.0 * dt]
                               + [0.0] * 6)
    P0 = PrismaticJoint(CFG, np.array([0.0, 0.0, 1.0]), 0.1).P
    np.testing.assert_allclose(np.diag(P0)[:4], 3.0)
    R0 = RevoluteJoint(CFG, np.array([0.0, 0.0, 1.0]), np.zeros(3), 0.1).P
    np.testing.assert_allclose(np.diag(R0)[:6], 1.0)


def test_prismatic_predicted_delta_jacobian() -> None:
    rng = np.random.default_rng(10)
    f = _prismatic(rng, unit(rng.normal(size=3)))
    A = rng.normal(size=(7, 7))
    f.P = A @ A.T
    T, cov = f.predicted_delta()
    np.testing.assert_allclose(T[:3, 3], f.measurement(), atol=1e-15)
    T0_inv = se3.se3_inverse(T)

    def r(d: Array) -> Array:
        D = np.eye(4)
        D[:3, 3] = _prismatic_measurement(f, d)
        return se3.se3_log(D @ T0_inv)

    J = numeric_jacobian(r, 7)
    np.testing.assert_allclose(cov, J @ f.P @ J.T, atol=1e-8)
    J[:, 2] = 0.0  # explicit q: no q variance
    np.testing.assert_allclose(f.predicted_delta(f.q)[1], J @ f.P @ J.T, atol=1e-8)


def test_revolute_predicted_delta_jacobian() -> None:
    rng = np.random.default_rng(11)
    f = _revolute(rng, unit(rng.normal(size=3)), 2.0)
    A = rng.normal(size=(12, 12))
    f.P = A @ A.T * 0.01
    T, cov = f.predicted_delta()
    np.testing.assert_allclose(T, f.measurement(), atol=1e-12)
    T0_inv = se3.se3_inverse(T)
    J = numeric_jacobian(lambda d: se3.se3_log(_revolute_prediction(f, d) @ T0_inv), 12)
    np.testing.assert_allclose(cov, J @ f.P @ J.T, atol=1e-7)


# --------------------------------------------------------------------------------------------
# Filter behaviour
# --------------------------------------------------------------------------------------------


def test_ekf_correct_is_joseph_and_matches_textbook() -> None:
    rng = np.random.default_rng(12)
    A = rng.normal(size=(7, 7))
    P = A @ A.T
    H = rng.normal(size=(3, 7))
    R = np.diag([0.1, 0.2, 0.3])
    y = rng.normal(size=3)
    dx, P_post, S, K = g.ekf_correct(P, H, R, y)
    S_ref = H @ P @ H.T + R
    K_ref = P @ H.T @ np.linalg.inv(S_ref)
    np.testing.assert_allclose(S, S_ref, atol=1e-10)
    np.testing.assert_allclose(K, K_ref, atol=1e-10)
    np.testing.assert_allclose(dx, K_ref @ y, atol=1e-10)
    np.testing.assert_allclose(P_post, (np.eye(7) - K_ref @ H) @ P, atol=1e-9)
    np.testing.assert_array_equal(P_post, P_post.T)
    assert np.linalg.eigvalsh(P_post).min() > -1e-12


def test_noise_inflation_factors() -> None:
    assert prismatic_noise_inflation(0.03, CFG) == pytest.approx(1.0 / (1.0 - math.exp(-1.0)))
    assert prismatic_noise_inflation(0.0, CFG) == CFG.max_inflation_factor
    omip = dataclasses.replace(CFG, revolute_inflation_scale=1.0)  # OMIP's scale
    assert revolute_noise_inflation(math.pi, omip) == pytest.approx(1.0 / (1.0 - math.exp(-1.0)))
    assert revolute_noise_inflation(math.pi, CFG) == pytest.approx(
        1.0 / (1.0 - math.exp(-1.0 / CFG.revolute_inflation_scale)))
    assert revolute_noise_inflation(0.0, CFG) == CFG.max_inflation_factor
    assert revolute_noise_inflation(1e-9, CFG) == CFG.max_inflation_factor
    R = inflated_noise(np.zeros((3, 3)), 5.0, 1e-6)
    np.testing.assert_array_equal(R, 1e-6 * np.eye(3))  # the floor keeps R invertible


@pytest.mark.parametrize("axis", [np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]),
                                  unit(np.array([0.3, -0.4, 0.2]))])
def test_revolute_group_innovation_tracks_past_two_pi(axis: Array) -> None:
    """q is unbounded: it passes pi and 2 pi continuously and qdot keeps its sign."""
    p = np.array([0.1, -0.2, 0.3])
    p -= (p @ axis) * axis
    rate = 2.0  # rad/s, 30 Hz -> 0.067 rad per frame
    dt = 1.0 / 30.0
    q0 = 0.1
    f = RevoluteJoint.from_twist(CFG, revolute_twist(axis, p, q0), 1e-8 * np.eye(6))
    qs, qdots = [], []
    for k in range(1, 150):  # up to 0.1 + 9.9 rad ~ 1.6 turns
        q = q0 + rate * k * dt
        f.predict(dt)
        f.update(revolute_delta(axis, p, q), 1e-8 * np.eye(6))
        assert np.isfinite(f.P).all() and np.isfinite(f.u).all()
        qs.append(f.q)
        qdots.append(f.qdot)
    assert qs[-1] == pytest.approx(q0 + rate * 149 * dt, abs=1e-6)
    assert np.all(np.diff(qs) > 0.0)  # no fold at pi, no jump at 2 pi
    assert min(qdots[5:]) > 0.0
    assert qdots[-1] == pytest.approx(rate, rel=1e-3)
    np.testing.assert_allclose(f.u, axis, atol=1e-6)
    np.testing.assert_allclose(f.p, p, atol=1e-6)


@pytest.mark.parametrize("axis", [np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])])
def test_prismatic_axis_at_the_poles(axis: Array) -> None:
    f = PrismaticJoint.from_displacement(CFG, 0.02 * axis, 1e-8 * np.eye(3))
    for k in range(1, 60):
        f.predict(1.0 / 30.0)
        f.update((0.02 + 0.002 * k) * axis + np.array([1e-4, -1e-4, 0.0]) * (k % 2),
                 1e-6 * np.eye(3))
        assert np.isfinite(f.P).all()
    assert abs(float(f.u @ axis)) > 1.0 - 1e-4


def test_filters_expose_innovation_and_s() -> None:
    rng = np.random.default_rng(13)
    D = se3.se3_exp(rng.normal(scale=0.1, size=6))
    rigid, disc = RigidJoint(), DisconnectedJoint()
    rigid.update(D, np.eye(6) * 1e-4)
    disc.update(D, np.eye(6) * 1e-4)
    np.testing.assert_allclose(rigid.y, se3.se3_log(D), atol=1e-12)
    assert rigid.S.shape == disc.S.shape == (6, 6)
    assert np.isfinite(rigid.log_likelihood()) and np.isfinite(disc.log_likelihood())
    np.testing.assert_array_equal(rigid.predicted_delta()[0], np.eye(4))
    assert disc.predicted_delta()[1][0, 0] == 1e6
    rev = _revolute(rng, unit(rng.normal(size=3)), 0.5)
    z = rev.measurement()
    rev.update(se3.se3_exp(np.full(6, 1e-3)) @ z, np.eye(6) * 1e-4)
    assert rev.y.shape == (6,) and rev.S.shape == (6, 6) and rev.K.shape == (12, 6)
    assert np.isfinite(rev.log_likelihood())
    pri = _prismatic(rng, unit(rng.normal(size=3)))
    pri.update(pri.measurement() + 1e-3, np.eye(3) * 1e-4)
    assert pri.y.shape == (3,) and pri.S.shape == (3, 3) and pri.K.shape == (7, 3)


def test_revolute_point_stays_closest_to_origin() -> None:
    rng = np.random.default_rng(14)
    f = _revolute(rng, unit(rng.normal(size=3)), 0.8)
    for _ in range(20):
        f.predict(1.0 / 30.0)
        f.update(se3.se3_exp(rng.normal(scale=0.01, size=6)) @ f.measurement(), 1e-4 * np.eye(6))
        assert abs(float(f.p @ f.u)) < 1e-12
        assert abs(float(f.u @ f.u) - 1.0) < 1e-12


def test_history_errors_vanish_for_the_true_hypothesis() -> None:
    rng = np.random.default_rng(15)
    u = unit(rng.normal(size=3))
    c0 = rng.normal(size=3)
    R0 = se3.so3_exp(rng.normal(size=3))
    T0 = se3.pose_from_rotation_translation(R0, c0)
    qs = np.linspace(0.0, 2.5, 7)
    rev = _revolute(rng, u, 1.0)
    pri = _prismatic(rng, u)
    for f in (rev, pri):
        Ts = []
        for q in qs:
            if isinstance(f, RevoluteJoint):
                Ts.append(revolute_delta(f.u, f.p, q) @ f.E @ T0)
            else:
                D = np.eye(4)
                D[:3, 3] = q * f.u + f.o
                Ts.append(D @ T0)
        d = np.array([T[:3, 3] - c0 for T in Ts])
        Rf = np.array([(T[:3, :3] @ R0.T).ravel() for T in Ts])
        trace = Rf[:, 0] + Rf[:, 4] + Rf[:, 8]
        if isinstance(f, RevoluteJoint):
            e_t, e_r = f.history_errors(d, Rf, trace, qs, c0)
        else:  # the prismatic rotation error is rigid's: beyond the rigid test (inside here)
            e_t, e_r = f.history_errors(d, qs, np.full(len(qs), 3.0), 2.5)
        np.testing.assert_allclose(e_t, 0.0, atol=1e-12)
        np.testing.assert_allclose(e_r, 0.0, atol=2e-7)  # arccos near 1
    # Rigid: deltas within the rigid test have no error; beyond it, the excess in sigmas.
    e_t, e_r = RigidJoint.history_errors(np.array([0.0, 6.0, 25.0]), np.array([1.0, 49.0, 0.0]),
                                         2.5)
    np.testing.assert_allclose(e_t, [0.0, 0.0, 2.5])
    np.testing.assert_allclose(e_r, [0.0, 4.5, 0.0])


def test_snapshot_state_round_trip() -> None:
    rng = np.random.default_rng(16)
    for f in (_prismatic(rng, unit(rng.normal(size=3))), _revolute(rng, POLES[1], 4.0)):
        g2 = type(f).from_state(CFG, f.to_state())
        z = f.measurement()
        for filt in (f, g2):
            filt.predict(0.03)
            if isinstance(filt, RevoluteJoint):
                filt.update(se3.se3_exp(np.full(6, 1e-3)) @ z, 1e-4 * np.eye(6))
            else:
                filt.update(z + 1e-3, 1e-4 * np.eye(3))
        np.testing.assert_array_equal(f.P, g2.P)
        np.testing.assert_array_equal(f.u, g2.u)
        assert f.q == g2.q


def test_mahalanobis2_3_matches_a_linear_solve() -> None:
    from services.kinematics.filters.geometry import mahalanobis2_3

    rng = np.random.default_rng(21)
    for _ in range(20):
        A = rng.normal(size=(3, 3))
        S = A @ A.T + 1e-3 * np.eye(3)
        v = rng.normal(size=3)
        assert mahalanobis2_3(v, S) == pytest.approx(float(v @ np.linalg.solve(S, v)), rel=1e-9)
    assert mahalanobis2_3(np.ones(3), np.diag([1.0, 0.0, 1.0])) == math.inf  # not definite


def test_innovation_whiteness_and_the_covariance_inflation() -> None:
    """White innovations give rho ~ 0 and no inflation; AR(1) innovations with correlation 0.8
    give rho ~ 0.8 and the factor scale (1 + rho) / (1 - rho); a snapshot keeps the sums."""
    from services.common.snapshot import SnapshotReader
    from services.kinematics.filters.whiteness import InnovationCorrelation

    rng = np.random.default_rng(33)
    L = np.array([[2.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.1, -0.3, 0.5]])
    S = L @ L.T
    white, ar1 = InnovationCorrelation(3), InnovationCorrelation(3)
    x = rng.normal(size=3)
    for _ in range(4000):
        white.add(L @ rng.normal(size=3), S)
        x = 0.8 * x + math.sqrt(1.0 - 0.64) * rng.normal(size=3)
        ar1.add(L @ x, S)
    assert abs(white.rho) < 0.05
    assert white.inflation(0.5, 30.0) == 1.0  # never below the filter's own covariance
    assert ar1.rho == pytest.approx(0.8, abs=0.03)
    expected = 0.5 * (1.0 + ar1.rho) / (1.0 - ar1.rho)
    assert ar1.inflation(0.5, 30.0) == pytest.approx(expected)
    assert ar1.inflation(0.5, 3.0) == 3.0  # capped
    back = InnovationCorrelation.from_state(3, SnapshotReader(ar1.to_state(), "w"))
    assert (back.rho, back.inflation(0.5, 30.0)) == (ar1.rho, ar1.inflation(0.5, 30.0))


def test_the_published_covariance_is_the_filters_times_its_inflation() -> None:
    from services.kinematics.published import prismatic_params, revolute_params

    rng = np.random.default_rng(34)
    f = _revolute(rng, POLES[1], 4.0)
    z = f.measurement()
    for _ in range(30):  # a constant error, absorbed slowly: correlated innovations
        f.predict(0.03)
        f.update(se3.se3_exp(np.full(6, 0.02)) @ z, 1e-2 * np.eye(6))
    inflation = f.covariance_inflation()
    assert f.whiteness.rho > 0.5 and inflation > 1.0
    bare = revolute_params(f).covariance / inflation
    assert np.linalg.eigvalsh(bare[2:5, 2:5]).max() == pytest.approx(
        np.linalg.eigvalsh(f.parameter_covariance()[2:5, 2:5]).max(), rel=1e-9)
    p = _prismatic(rng, unit(rng.normal(size=3)))
    assert np.trace(prismatic_params(p).covariance[:2, :2]) == pytest.approx(
        p.covariance_inflation() * np.trace(p.P[:2, :2]), rel=1e-9)
