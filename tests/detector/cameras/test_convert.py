"""Camera buffers to frames without an SDK: colour formats, depth units, intrinsics, lens."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from services.common.protocol import RgbdFrame
from services.detector.cameras.convert import (
    bgr_from_color,
    captured_frame,
    float32_value,
    intrinsics_from_matrix,
)
from services.detector.cameras.lens import NO_DISTORTION, LensDistortion, Undistorter
from services.detector.sources import decode_frame, encode_frame
from tests.detector.cameras.images import (
    block_image,
    nv12_from_bgr,
    smooth_image,
    yuv422_from_bgr,
)

K = np.array([[600.0, 0.0, 319.5], [0.0, 601.0, 239.5], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(("units", "scale_m"), [(1000, 0.001), (10000, 0.0001)])
def test_depth_units_and_intrinsics_arrive_as_sent(units: int, scale_m: float) -> None:
    """Arrays in, RgbdFrame on the wire out: metres = raw units x scale, intrinsics as given."""
    color = smooth_image(480, 640)
    depth = np.full((480, 640), units, np.uint16)
    depth[:20] = 0  # no reading
    intrinsics = intrinsics_from_matrix(K, 640, 480)
    frame = captured_frame(stamp_ns=1_754_000_000_123_456_789, color_bgr=color, depth=depth,
                           depth_scale_m=scale_m, intrinsics=intrinsics)
    wire = RgbdFrame.from_msgpack(encode_frame(frame, seq=3).to_msgpack())
    assert wire.stamp_ns == 1_754_000_000_123_456_789
    assert (wire.intrinsics.fx, wire.intrinsics.fy, wire.intrinsics.cx, wire.intrinsics.cy) == (
        600.0, 601.0, 319.5, 239.5)
    assert (wire.intrinsics.width, wire.intrinsics.height) == (640, 480)
    back = decode_frame(wire)
    metres = back.depth.astype(np.float64) * back.depth_scale_m
    np.testing.assert_allclose(metres[20:], 1.0, rtol=1e-12)
    assert not back.depth[:20].any()
    assert np.abs(back.color_bgr.astype(int) - color).mean() < 3.0  # JPEG on the wire


def _formats(bgr: np.ndarray) -> dict[str, np.ndarray]:
    ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    return {"bgr8": bgr, "rgb8": bgr[:, :, ::-1],
            "bgra8": cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA),
            "rgba8": cv2.cvtColor(bgr, cv2.COLOR_BGR2RGBA),
            "yuyv": yuv422_from_bgr(bgr, "yuyv"), "uyvy": yuv422_from_bgr(bgr, "uyvy"),
            "nv12": nv12_from_bgr(bgr), "mjpeg": jpeg.reshape(-1)}


@pytest.mark.parametrize("fmt", ["bgr8", "rgb8", "bgra8", "rgba8", "yuyv", "uyvy", "nv12",
                                 "mjpeg"])
def test_every_colour_format_becomes_the_same_bgr(fmt: str) -> None:
    # 2x2 blocks of random colours for the subsampled YUV formats; JPEG needs smooth content
    bgr = smooth_image(48, 64) if fmt == "mjpeg" else block_image(np.random.default_rng(2), 48, 64)
    out = bgr_from_color(_formats(bgr)[fmt], fmt, 64, 48)
    assert out.shape == (48, 64, 3) and out.dtype == np.uint8 and out.flags.c_contiguous
    error = np.abs(out.astype(int) - bgr)
    if fmt.endswith("8"):
        np.testing.assert_array_equal(out, bgr)  # lossless channel orders
    else:  # 8-bit YUV (limited range) and JPEG: a few levels
        assert error.mean() < 2.5 and error.max() <= 12, (error.mean(), error.max())


def test_bgr_output_is_a_copy_of_the_sdk_buffer() -> None:
    buffer = block_image(np.random.default_rng(3), 8, 8)
    out = bgr_from_color(buffer, "bgr8", 8, 8)
    buffer[:] = 0  # the SDK reuses its frame buffers
    assert out.any()


def test_bad_colour_buffers_name_the_problem() -> None:
    with pytest.raises(ValueError, match=r"rgb8 colour frame has 100 bytes, 8x8 needs 192"):
        bgr_from_color(np.zeros(100, np.uint8), "rgb8", 8, 8)
    with pytest.raises(ValueError, match="not supported"):
        bgr_from_color(np.zeros(64, np.uint8), "y16", 8, 8)
    with pytest.raises(ValueError, match="MJPEG colour frame does not decode"):
        bgr_from_color(np.frombuffer(b"\xff\xd8 not a jpeg", np.uint8), "mjpeg", 8, 8)
    ok, jpeg = cv2.imencode(".jpg", np.zeros((8, 16, 3), np.uint8))
    assert ok
    with pytest.raises(ValueError, match="is 16x8, expected 8x8"):
        bgr_from_color(jpeg, "mjpeg", 8, 8)
    with pytest.raises(ValueError, match="even width and height"):
        bgr_from_color(np.zeros(7 * 9 * 3 // 2, np.uint8), "nv12", 7, 6)


def test_frames_whose_parts_disagree_are_refused() -> None:
    intrinsics = intrinsics_from_matrix(K, 640, 480)
    color = np.zeros((480, 640, 3), np.uint8)
    depth = np.zeros((480, 640), np.uint16)
    ok = {"stamp_ns": 1, "color_bgr": color, "depth": depth, "depth_scale_m": 0.001,
          "intrinsics": intrinsics}
    cases = [({"color_bgr": np.zeros((480, 600, 3), np.uint8)}, "intrinsics say 640x480"),
             ({"color_bgr": np.zeros((480, 640), np.uint8)}, r"colour must be \(H, W, 3\)"),
             ({"depth": np.zeros((240, 320), np.uint16)}, "registered to the colour image"),
             ({"depth": depth.astype(np.float32)}, "uint16"),
             ({"depth_scale_m": 0.0}, "positive number of metres"),
             ({"depth_scale_m": float("nan")}, "positive number of metres")]
    for change, message in cases:
        with pytest.raises(ValueError, match=message):
            captured_frame(**{**ok, **change})
    assert captured_frame(**ok).depth_scale_m == 0.001


def test_intrinsics_need_a_camera_matrix() -> None:
    with pytest.raises(ValueError, match="3x3"):
        intrinsics_from_matrix(np.eye(4), 640, 480)


def _dot_images(points_px: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Colour with a white 5x5 square and depth with a 700-unit square at each point."""
    w, h = size
    color = np.zeros((h, w, 3), np.uint8)
    depth = np.zeros((h, w), np.uint16)
    for u, v in np.rint(points_px).astype(int):
        color[v - 2:v + 3, u - 2:u + 3] = 255
        depth[v - 2:v + 3, u - 2:u + 3] = 700
    return color, depth


def _centroid(mask: np.ndarray, u: float, v: float) -> np.ndarray:
    """(u, v) centroid of the mask's pixels within 6 px of (u, v)."""
    x0, y0 = int(u) - 6, int(v) - 6
    ys, xs = np.nonzero(mask[y0:y0 + 13, x0:x0 + 13])
    assert len(xs) > 0, (u, v)
    return np.array([xs.mean() + x0, ys.mean() + y0])


def test_opencv_distortion_is_removed_from_colour_and_depth_alike() -> None:
    """Squares drawn where a distorted lens images known points move to their pinhole
    projections, in colour and depth identically, and depth keeps only measured values."""
    dist = (-0.28, 0.09, 0.0008, -0.0005, -0.012)
    intrinsics = intrinsics_from_matrix(K, 640, 480)
    grid = np.array([[x, y, 1.0] for x in np.linspace(-0.42, 0.42, 5)
                     for y in np.linspace(-0.3, 0.3, 4)])
    distorted, _ = cv2.projectPoints(grid, np.zeros(3), np.zeros(3), K, np.array(dist))
    pinhole, _ = cv2.projectPoints(grid, np.zeros(3), np.zeros(3), K, None)
    distorted, pinhole = distorted.reshape(-1, 2), pinhole.reshape(-1, 2)
    assert np.abs(distorted - pinhole).max() > 15.0  # the lens moves the corners visibly
    color, depth = _dot_images(distorted, (640, 480))
    undistorter = Undistorter(intrinsics, LensDistortion("opencv", dist))
    assert undistorter.active
    out_color, out_depth = undistorter.apply(color, depth)
    for u, v in pinhole:
        centre = _centroid(out_color[:, :, 0] > 127, u, v)
        assert np.linalg.norm(centre - (u, v)) < 1.0, (centre, (u, v))
        depth_centre = _centroid(out_depth > 0, u, v)
        assert np.linalg.norm(depth_centre - centre) < 0.5, (depth_centre, centre)
    assert set(np.unique(out_depth)) <= {0, 700}  # nearest neighbour: no invented depths


def test_no_distortion_or_an_unknown_model_leaves_the_images(
        caplog: pytest.LogCaptureFixture) -> None:
    intrinsics = intrinsics_from_matrix(K, 640, 480)
    color, depth = _dot_images(np.array([[320.0, 240.0]]), (640, 480))
    for distortion in (NO_DISTORTION, LensDistortion("opencv", (0.0,) * 5)):
        assert not Undistorter(intrinsics, distortion).active
    assert not Undistorter(intrinsics, LensDistortion("opencv", (0.1,) * 5),
                           enabled=False).active
    with caplog.at_level(logging.WARNING):
        unknown = Undistorter(intrinsics, LensDistortion("inverse_brown_conrady", (0.1,) * 5))
    assert not unknown.active and "inverse_brown_conrady" in caplog.text
    out_color, out_depth = unknown.apply(color, depth)
    assert out_color is color and out_depth is depth


def test_float32_scales_read_as_the_decimal_meant() -> None:
    assert float32_value(float(np.float32(0.001))) == 0.001
    assert float32_value(float(np.float32(0.0001))) == 0.0001
