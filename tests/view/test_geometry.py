"""What the viewers draw (services/view/geometry.py): ellipsoids, cones, joint geometry, pixels."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from services.common import protocol as p
from services.common.se3 import se3_exp, so3_exp
from services.view import geometry as geo
from tests.common import samples


def _matrix_from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _random_covariance(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    A = rng.normal(size=(n, n)) * scale
    return A @ A.T


def test_ellipsoid_reproduces_its_covariance_with_a_right_handed_rotation() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        P = _random_covariance(rng, 3, 0.01)
        e = geo.ellipsoid_from_covariance(np.ones(3), P, n_sigma=2.0)
        assert np.linalg.det(e.rotation) == pytest.approx(1.0)
        back = e.rotation @ np.diag((e.half_sizes / 2.0) ** 2) @ e.rotation.T
        np.testing.assert_allclose(back, P, atol=1e-12)
        np.testing.assert_allclose(_matrix_from_quat_xyzw(e.quat_xyzw), e.rotation, atol=1e-12)
        np.testing.assert_array_equal(e.center, np.ones(3))


def test_a_singular_covariance_gives_a_flat_ellipsoid_and_a_bad_one_an_error() -> None:
    e = geo.ellipsoid_from_covariance(np.zeros(3), np.diag([4.0, 1.0, -1e-18]), n_sigma=1.0)
    np.testing.assert_allclose(np.sort(e.half_sizes), [0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="finite 3x3"):
        geo.ellipsoid_from_covariance(np.zeros(3), np.full((3, 3), np.nan))


def test_body_position_covariance_matches_sampled_left_perturbations() -> None:
    """The hand origin of ``Exp(delta) T`` for sampled ``delta`` has covariance ``G P G^T``."""
    rng = np.random.default_rng(2)
    T = se3_exp(np.array([0.1, -0.05, 0.6, 0.3, -0.2, 0.5]))
    P6 = _random_covariance(rng, 6, 1e-3)
    P = np.zeros((12, 12))
    P[:6, :6] = P6
    P[6:, 6:] = np.eye(6)  # the twist block must not matter
    deltas = rng.multivariate_normal(np.zeros(6), P6, size=20000)
    origins = np.array([(se3_exp(d) @ T)[:3, 3] for d in deltas])
    sampled = np.cov(origins.T)
    predicted = geo.body_position_covariance(T, P)
    np.testing.assert_allclose(predicted, sampled, rtol=0.1, atol=2e-7)
    # with the origin far from the frame origin the rotation part dominates the plain block
    assert np.linalg.norm(predicted - P6[:3, :3]) > 0.1 * np.linalg.norm(P6[:3, :3])


def test_cone_half_angle_is_n_sigma_of_the_largest_tilt_whatever_the_basis() -> None:
    P = np.diag([0.02**2, 0.05**2])
    assert geo.cone_half_angle(P, 2.0) == pytest.approx(0.1)
    c, s = math.cos(0.7), math.sin(0.7)
    R = np.array([[c, -s], [s, c]])
    assert geo.cone_half_angle(R @ P @ R.T, 2.0) == pytest.approx(0.1)
    assert geo.cone_half_angle(np.eye(2) * 100.0) == geo.MAX_CONE_HALF_ANGLE_RAD
    with pytest.raises(ValueError, match="2x2"):
        geo.cone_half_angle(np.eye(3))


def test_cone_lines_open_at_the_half_angle() -> None:
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    apex = np.array([0.1, 0.2, 0.3])
    strips = geo.cone_lines(apex, axis, 0.2, 0.5, rays=6, segments=48)
    rim, rays = strips[0], strips[1:]
    assert len(rays) == 6 and np.allclose(rim[0], rim[-1])
    directions = rim - apex
    cosines = directions @ axis / np.linalg.norm(directions, axis=1)
    np.testing.assert_allclose(np.arccos(cosines), 0.2, atol=1e-12)
    np.testing.assert_allclose(directions @ axis, 0.5, atol=1e-12)
    for ray in rays:
        np.testing.assert_array_equal(ray[0], apex)


def _revolute(q: float = 0.5, updates: int = 10) -> p.KinematicModel:
    m = samples.kinematic_model(3)
    return dataclasses.replace(m, type="revolute", updates=updates,
                               revolute=dataclasses.replace(m.revolute, q=q))


def test_revolute_geometry_axis_line_arc_and_point_ellipsoid() -> None:
    model = _revolute()
    r = model.revolute
    assert r is not None
    g = geo.joint_geometry(model, (-0.2, 0.9), axis_length_m=0.4, arc_points=50)
    assert g is not None and g.type == "revolute"
    direction = g.segment[1] - g.segment[0]
    assert np.linalg.norm(direction) == pytest.approx(0.4)
    np.testing.assert_allclose(direction / 0.4, r.axis, atol=1e-12)
    # the origin is the point of the axis nearest the reference hand position
    reference = model.reference_pose[:3, 3]
    np.testing.assert_allclose(np.cross(g.origin - r.point, r.axis), 0.0, atol=1e-12)
    assert float((reference - g.origin) @ r.axis) == pytest.approx(0.0, abs=1e-12)
    # the arc: the reference rotated about the axis from lo to hi, at a constant radius
    np.testing.assert_allclose(g.sweep[0], g.origin + so3_exp(r.axis * -0.2) @ (reference - g.origin),
                               atol=1e-12)
    np.testing.assert_allclose(g.sweep[-1], g.origin + so3_exp(r.axis * 0.9) @ (reference - g.origin),
                               atol=1e-12)
    radii = np.linalg.norm(np.cross(g.sweep - g.origin, r.axis), axis=1)
    np.testing.assert_allclose(radii, np.linalg.norm(reference - g.origin), rtol=1e-12)
    assert g.cone_half_angle_rad == pytest.approx(geo.cone_half_angle(r.covariance[:2, :2]))
    assert len(g.cone) == 2 * (1 + 8)  # a cone each way, rim + 8 rays
    e = g.point_ellipsoid
    assert e is not None
    np.testing.assert_array_equal(e.center, g.origin)
    # flat along the axis: the point's uncertainty across the axis only
    along = e.rotation.T @ r.axis
    assert float(np.abs(along) @ e.half_sizes) == pytest.approx(0.0, abs=1e-9)
    across = np.eye(3) - np.outer(r.axis, r.axis)
    back = e.rotation @ np.diag((e.half_sizes / 2.0) ** 2) @ e.rotation.T
    np.testing.assert_allclose(back, across @ r.covariance[2:5, 2:5] @ across, atol=1e-9)


def test_prismatic_geometry_arrow_from_the_reference_and_the_stroke() -> None:
    m = samples.kinematic_model(4)
    model = dataclasses.replace(m, type="prismatic")
    axis = m.prismatic.axis  # type: ignore[union-attr]
    g = geo.joint_geometry(model, (-0.01, 0.12), axis_length_m=0.2)
    assert g is not None and g.type == "prismatic" and g.point_ellipsoid is None
    reference = model.reference_pose[:3, 3]
    np.testing.assert_allclose(g.segment, [reference, reference + 0.1 * axis], atol=1e-12)
    np.testing.assert_allclose(g.sweep, [reference - 0.01 * axis, reference + 0.12 * axis],
                               atol=1e-12)


@pytest.mark.parametrize("joint_type", ["rigid", "disconnected", "unknown"])
def test_no_geometry_without_an_axis(joint_type: str) -> None:
    model = dataclasses.replace(samples.kinematic_model(), type=joint_type)
    assert geo.joint_geometry(model) is None
    assert geo.joint_value(model) is None


def test_joint_range_grows_and_starts_over_on_a_new_demonstration() -> None:
    joint_range = geo.JointRange()
    assert joint_range.update(_revolute(0.3, 5)) == (0.0, 0.3)
    assert joint_range.update(_revolute(-0.1, 6)) == (-0.1, 0.3)
    assert joint_range.update(_revolute(0.2, 7)) == (-0.1, 0.3)
    assert joint_range.update(_revolute(0.05, 2)) == (0.0, 0.05)  # updates went down: a reset
    prismatic = dataclasses.replace(samples.kinematic_model(3), type="prismatic", updates=3)
    q = prismatic.prismatic.q  # type: ignore[union-attr]
    assert joint_range.update(prismatic) == (min(q, 0.0), max(q, 0.0))  # another type
    moved = dataclasses.replace(_revolute(0.4, 9), reference_pose=se3_exp(np.full(6, 0.5)))
    joint_range.update(_revolute(0.5, 8))
    assert joint_range.update(moved) == (0.0, 0.4)  # the reference jumped


def test_projection_and_the_pixels_of_a_hand() -> None:
    k = p.CameraIntrinsics(fx=500.0, fy=400.0, cx=320.0, cy=240.0, width=640, height=480)
    uv = geo.project_points(np.array([[0.1, -0.2, 1.0], [0.0, 0.0, -1.0], [np.nan, 0, 1]]), k)
    np.testing.assert_allclose(uv[0], [370.0, 160.0])
    assert np.isnan(uv[1:]).all()
    hand = samples.hand_landmarks().hands[0]
    assert hand.pixels is not None
    np.testing.assert_array_equal(geo.hand_pixels(hand, k), hand.pixels)
    bare = dataclasses.replace(hand, pixels=None)
    assert geo.hand_pixels(bare, None) is None
    in_camera = geo.hand_pixels(bare, k)
    T_world_camera = se3_exp(np.array([0.2, 0.1, -0.3, 0.1, 0.4, -0.2]))
    points_world = hand.points.astype(float) @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
    in_world = dataclasses.replace(bare, points=points_world.astype("<f4"))
    np.testing.assert_allclose(geo.hand_pixels(in_world, k, T_world_camera), in_camera,
                               rtol=1e-4, atol=1e-3)


def test_landmark_points_drop_missing_depth_and_keep_ids_and_colours() -> None:
    hand = samples.hand_landmarks().hands[0]
    points = hand.points.copy()
    points[[0, 7]] = np.nan
    visibility = np.linspace(0, 1, 21).astype("<f4")
    lm = geo.detected_landmarks(dataclasses.replace(hand, points=points, visibility=visibility))
    finite = np.flatnonzero(np.isfinite(points).all(axis=1))
    assert lm.points.shape == (len(finite), 3) and 0 not in lm.ids and 7 not in lm.ids
    np.testing.assert_array_equal(lm.ids, finite)
    np.testing.assert_array_equal(lm.points, points[finite])
    np.testing.assert_array_equal(lm.colors[0], geo.visibility_colors(visibility[finite[:1]])[0])
    np.testing.assert_array_equal(geo.visibility_colors(np.array([1.0]))[0], [255, 215, 40, 255])
    body = samples.hand_body()
    tracked = geo.tracked_landmarks(body.landmarks)
    finite = np.isfinite(body.landmarks.points).all(axis=1)
    assert len(tracked.ids) == int(finite.sum())
    np.testing.assert_array_equal(tracked.colors, geo.STATUS_COLORS[body.landmarks.status[finite]])
