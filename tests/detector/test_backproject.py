"""Back-projection with registered depth: exactness, holes, depth edges, resolution.

Tolerances (docs/testing.md#tolerances): back-projecting a pixel is three multiplications and a
division on values below 1e3, so 1e-12 m holds on any BLAS (~100 eps); the round trip through
projection divides by depth once more (1e-9 px).
"""

from __future__ import annotations

import numpy as np
import pytest

from services.common.protocol import CameraIntrinsics
from services.detector.backproject import backproject, landmark_depths, project, to_world

K = CameraIntrinsics(fx=608.0, fy=607.0, cx=641.5, cy=362.25, width=1280, height=720)


def _pixels(rng: np.random.Generator, n: int = 21, margin: int = 20) -> np.ndarray:
    return np.column_stack([rng.uniform(margin, K.width - margin, n),
                            rng.uniform(margin, K.height - margin, n)])


def test_points_on_a_plane_are_exact() -> None:
    rng = np.random.default_rng(0)
    depth = np.full((720, 1280), 812, np.uint16)  # 0.812 m in mm units
    pixels = _pixels(rng)
    z = landmark_depths(depth, 0.001, pixels, (1280, 720))
    np.testing.assert_allclose(z, 0.812, rtol=0, atol=1e-12)
    points = backproject(pixels, z, K)
    expected = np.column_stack([(pixels[:, 0] - K.cx) / K.fx * 0.812,
                                (pixels[:, 1] - K.cy) / K.fy * 0.812, np.full(21, 0.812)])
    np.testing.assert_allclose(points, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(project(points, K), pixels, atol=1e-9)  # round trip


def test_a_tilted_surface_gives_the_depth_at_the_landmark() -> None:
    rng = np.random.default_rng(1)
    v, u = np.mgrid[0:720, 0:1280]
    z_true = 0.6 + 0.0002 * (u - 640) + 0.0001 * (v - 360)  # ~0.2 mm per pixel slope
    depth = np.rint(z_true / 0.0001).astype(np.uint16)  # 0.1 mm units
    pixels = np.rint(_pixels(rng))
    z = landmark_depths(depth, 0.0001, pixels, (1280, 720))
    expected = 0.6 + 0.0002 * (pixels[:, 0] - 640) + 0.0001 * (pixels[:, 1] - 360)
    np.testing.assert_allclose(z, expected, atol=1e-4)


def test_holes_give_nan_and_sparse_readings_are_used() -> None:
    depth = np.zeros((720, 1280), np.uint16)
    depth[100, 100] = depth[101, 101] = 700  # 2 readings < min_valid
    depth[300:303, 400:402] = 650  # 6 readings around (401, 301)
    z = landmark_depths(depth, 0.001, np.array([[100.0, 100.0], [401.0, 301.0], [900.0, 500.0]]),
                        (1280, 720))
    assert np.isnan(z[0]) and np.isnan(z[2])
    assert z[1] == pytest.approx(0.65)
    points = backproject(np.array([[100.0, 100.0]]), z[:1], K)
    assert np.isnan(points).all()
    # readings outside the working range are holes too
    far = np.full((720, 1280), 9000, np.uint16)
    assert np.isnan(landmark_depths(far, 0.001, np.array([[640.0, 360.0]]), (1280, 720))).all()


def test_depth_edges_take_the_hand_not_the_background_or_flying_pixels() -> None:
    depth = np.full((720, 1280), 1200, np.uint16)  # background at 1.2 m
    depth[:, :600] = 500  # a finger (foreground) left of column 600
    depth[:, 600] = 850  # flying pixels on the edge, between both surfaces
    pixels = np.array([[599.0, 300.0], [600.0, 310.0], [601.0, 320.0], [598.4, 330.0]])
    z = landmark_depths(depth, 0.001, pixels, (1280, 720))
    # on the foreground side: foreground; on the flying pixel: the nearest clean surface
    assert z[0] == pytest.approx(0.5)
    assert z[1] == pytest.approx(0.5)
    assert z[3] == pytest.approx(0.5)
    # just across the edge the landmark sees the background (never the 0.85 m mix)
    assert z[2] in (pytest.approx(0.5), pytest.approx(1.2))
    assert not np.any(np.isclose(z, 0.85))


def test_depth_at_a_lower_resolution_is_sampled_at_the_scaled_pixel() -> None:
    v, u = np.mgrid[0:360, 0:640]
    depth = (500 + u + 1000 * (v > 180)).astype(np.uint16)  # half resolution, 1 mm per pixel
    pixels = np.array([[201.0, 101.0], [1001.0, 501.0]])  # colour pixels
    z = landmark_depths(depth, 0.001, pixels, (1280, 720), window=1, min_valid=1,
                        edge_jump_m=0.5)
    np.testing.assert_allclose(z, [(500 + 100) / 1000, (1500 + 500) / 1000])


def test_points_move_to_the_world_frame() -> None:
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [1.0, 2.0, 3.0]
    pts = np.array([[1.0, 0.0, 0.5], [np.nan, np.nan, np.nan]])
    out = to_world(pts, T)
    np.testing.assert_allclose(out[0], [1.0, 3.0, 3.5])
    assert np.isnan(out[1]).all()
