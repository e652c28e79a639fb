"""SO(3)/SE(3) maps: round trips, adjoint identities, Jacobians, rotations near pi.

Tolerances (docs/testing.md#tolerances): closed forms on O(1) arguments, a few dozen flops each
rounding by eps = 2.2e-16, agree to ~1e-14, so 1e-12 (a single map) and 1e-9 (a composition or a
log near pi, where the rotation angle is ill-conditioned) leave margins of 100x or more on any BLAS;
finite-difference Jacobians are compared at 1e-6 (truncation error of the h = 1e-6 central
difference), and bit-exact comparisons only where the same code computes both sides.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from services.common import se3

finite = st.floats(-3.0, 3.0, allow_nan=False)
vec3 = arrays(np.float64, 3, elements=finite)


@st.composite
def twists(draw: st.DrawFn, max_angle: float = np.pi - 1e-9) -> np.ndarray:
    v = draw(vec3)
    axis = draw(vec3)
    n = np.linalg.norm(axis)
    axis = axis / n if n > 1e-3 else np.array([0.0, 0.0, 1.0])
    angle = draw(st.one_of(st.floats(0.0, max_angle), st.floats(max_angle - 1e-6, max_angle),
                           st.floats(0.0, 1e-7)))
    return np.concatenate([v, angle * axis])


@given(twists())
@settings(max_examples=400, deadline=None)
def test_exp_log_round_trip(xi: np.ndarray) -> None:
    out = se3.se3_log(se3.se3_exp(xi))
    assert np.allclose(out, xi, atol=1e-6 * max(1.0, np.abs(xi).max()))


@given(twists(max_angle=np.pi))
@settings(max_examples=200, deadline=None)
def test_log_exp_round_trip_on_the_group(xi: np.ndarray) -> None:
    T = se3.se3_exp(xi)
    assert np.allclose(se3.se3_exp(se3.se3_log(T)), T, atol=1e-9)


def test_rotations_within_1e6_of_pi() -> None:
    rng = np.random.default_rng(1)
    for _ in range(500):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = np.pi - rng.uniform(0, 1e-6)
        w = se3.so3_log(se3.so3_exp(angle * axis))
        assert abs(np.linalg.norm(w) - angle) < 1e-9
        assert np.allclose(w, angle * axis, atol=1e-8) or np.allclose(w, -angle * axis, atol=1e-6)
        # exactly pi: either sign of the axis is a valid logarithm
        R = se3.so3_exp(np.pi * axis)
        assert np.allclose(se3.so3_exp(se3.so3_log(R)), R, atol=1e-12)


@given(twists(), twists())
@settings(max_examples=200, deadline=None)
def test_adjoint_identities(xi: np.ndarray, eta: np.ndarray) -> None:
    T = se3.se3_exp(xi)
    Ad = se3.se3_adjoint(T)
    # T Exp(eta) T^-1 == Exp(Ad(T) eta)
    assert np.allclose(T @ se3.se3_exp(eta) @ se3.se3_inverse(T), se3.se3_exp(Ad @ eta),
                       atol=1e-8)
    # Ad(T^-1) == Ad(T)^-1 and Ad(AB) == Ad(A) Ad(B)
    assert np.allclose(se3.se3_adjoint(se3.se3_inverse(T)) @ Ad, np.eye(6), atol=1e-9)
    S = se3.se3_exp(eta)
    assert np.allclose(se3.se3_adjoint(T @ S), Ad @ se3.se3_adjoint(S), atol=1e-9)


@given(twists(max_angle=3.0))
@settings(max_examples=200, deadline=None)
def test_left_jacobian_matches_finite_differences(xi: np.ndarray) -> None:
    J = se3.se3_left_jacobian(xi)
    T = se3.se3_exp(xi)
    eps = 1e-6
    num = np.zeros((6, 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        plus = se3.se3_log(se3.se3_exp(xi + d) @ se3.se3_inverse(T))
        minus = se3.se3_log(se3.se3_exp(xi - d) @ se3.se3_inverse(T))
        num[:, i] = (plus - minus) / (2 * eps)
    assert np.allclose(J, num, atol=1e-6 * max(1.0, np.abs(xi).max()))
    assert np.allclose(se3.se3_left_jacobian_inv(xi) @ J, np.eye(6), atol=1e-8)


@given(vec3)
@settings(max_examples=200, deadline=None)
def test_so3_left_jacobian_inverse(w: np.ndarray) -> None:
    if np.linalg.norm(w) >= np.pi:
        w = w / np.linalg.norm(w) * 3.0
    assert np.allclose(se3.so3_left_jacobian_inv(w) @ se3.so3_left_jacobian(w), np.eye(3),
                       atol=1e-9)


def test_small_angle_branches_are_continuous() -> None:
    for theta in (0.0, 1e-12, 1e-8, 0.99e-4, 1.01e-4, 1e-3):
        xi = np.array([0.3, -0.2, 0.1, theta, 0.0, 0.0])
        assert np.allclose(se3.se3_log(se3.se3_exp(xi)), xi, atol=1e-12)
        assert np.all(np.isfinite(se3.se3_left_jacobian(xi)))


def test_transform_points_and_quaternion() -> None:
    rng = np.random.default_rng(0)
    T = se3.se3_exp(rng.normal(size=6))
    P = rng.normal(size=(5, 3))
    homo = (T @ np.c_[P, np.ones(5)].T).T[:, :3]
    assert np.allclose(se3.transform_points(T, P), homo)
    q = se3.quat_wxyz_from_matrix(T[:3, :3])
    assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12


@settings(max_examples=200, deadline=None)
@given(twists())
def test_float_kernels_agree_with_the_numpy_maps(xi: np.ndarray) -> None:
    """The ``*_fast`` kernels are the same maps as their numpy namesakes, to round-off."""
    T = se3.se3_exp(xi)
    np.testing.assert_allclose(se3.se3_exp_fast(xi), T, atol=1e-12)
    np.testing.assert_allclose(se3.se3_log_fast(T), se3.se3_log(T), atol=1e-9)
    np.testing.assert_allclose(se3.se3_inverse_fast(T), se3.se3_inverse(T), atol=1e-12)
    np.testing.assert_allclose(se3.se3_adjoint_fast(T), se3.se3_adjoint(T), atol=1e-12)
    np.testing.assert_allclose(se3.se3_left_jacobian_fast(xi), se3.se3_left_jacobian(xi),
                               atol=1e-9)
    np.testing.assert_allclose(se3.so3_exp_fast(xi[3:]), se3.so3_exp(xi[3:]), atol=1e-12)
    np.testing.assert_allclose(se3.so3_log_fast(T[:3, :3]), se3.so3_log(T[:3, :3]), atol=1e-9)
    np.testing.assert_allclose(se3.so3_left_jacobian_fast(xi[3:]),
                               se3.so3_left_jacobian(xi[3:]), atol=1e-12)
    assert abs(se3.rotation_angle_fast(T[:3, :3]) - se3.rotation_angle(T[:3, :3])) < 1e-9


def test_stacks_of_rotation_vectors_and_skews_match_one_at_a_time() -> None:
    rng = np.random.default_rng(7)
    # angles from 0 through the small-angle branch (1e-4) to past pi, in a (2, 5, 3) stack
    scales = np.array([0.0, 1e-9, 5e-5, 2e-4, 0.7, 2.0, np.pi, 3.5, 6.0, 9.0])
    axes = rng.normal(size=(10, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    w = (axes * scales[:, None]).reshape(2, 5, 3)
    R = se3.so3_exp(w)
    K = se3.skew_batch(w)
    assert R.shape == K.shape == (2, 5, 3, 3)
    for i in np.ndindex(2, 5):
        # same formula, terms summed in another order: agreement to a few ulps of |R| = 1
        np.testing.assert_allclose(R[i], se3.so3_exp(w[i]), rtol=0, atol=1e-14)
        np.testing.assert_array_equal(K[i], se3.skew(w[i]))
        np.testing.assert_allclose(R[i] @ R[i].T, np.eye(3), rtol=0, atol=1e-14)
@settings(max_examples=100, deadline=None)
@given(twists())
def test_check_pose_accepts_every_rigid_transform(xi: np.ndarray) -> None:
    assert se3.check_pose(se3.se3_exp(xi)) is None


def test_check_pose_names_the_problem() -> None:
    T = se3.se3_exp(np.array([0.1, -0.2, 0.3, 0.4, 0.5, -0.6]))
    skewed, reflected, bottom, nan = T.copy(), T.copy(), T.copy(), T.copy()
    skewed[:3, :3] *= 1.01
    reflected[:3, 0] *= -1.0
    bottom[3, 0] = 1e-12
    nan[1, 2] = np.nan
    cases: list[tuple[object, str]] = [
        (skewed, "not orthonormal"), (reflected, "determinant -1"), (bottom, "bottom row"),
        (nan, "NaN"), (T[:3], "shape"), ("pose", "not a numeric array")]
    for bad, words in cases:
        problem = se3.check_pose(bad)
        assert problem is not None and words in problem, (words, problem)


def test_check_pose_tolerance() -> None:
    """A diagonal entry 1 + e gives |R^T R - I| = 2e + e^2 and det 1 + e: 0.4 tol passes, 0.6
    tol fails, and a tighter ``tol`` argument applies."""
    tol = se3.POSE_TOLERANCE
    near, far = np.eye(4), np.eye(4)
    near[0, 0] = 1.0 + 0.4 * tol
    far[0, 0] = 1.0 + 0.6 * tol
    assert se3.check_pose(near) is None
    assert se3.check_pose(far) is not None
    assert se3.check_pose(near, tol=0.5 * tol) is not None
