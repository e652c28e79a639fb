"""Hand ROIs (rotated crops) and the tracking ROI from landmarks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.detector.landmarks import (
    Roi,
    box_iou,
    crop,
    handedness_from_score,
    roi_from_landmarks,
    rotation_towards,
)

CENTRE = np.array([400.0, 300.0])


def _hand(rng: np.random.Generator) -> np.ndarray:
    """An upright synthetic hand (pixels): wrist at the bottom, fingers up, ~100 px tall."""
    pts = np.zeros((21, 2))
    pts[0] = [0.0, 50.0]
    for finger, x in enumerate((-30.0, -15.0, 0.0, 15.0, 30.0)):
        base = 1 + 4 * finger
        for j in range(4):
            pts[base + j] = [x * (1.0 + 0.1 * j), 10.0 - 15.0 * j if finger else 30.0 - 10 * j]
    return pts + rng.normal(0.0, 0.5, pts.shape)


def _rotate(pts: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.asarray(pts @ np.array([[c, -s], [s, c]]).T, float)


def test_crop_maps_the_roi_centre_and_axes() -> None:
    roi = Roi(cx=300.0, cy=200.0, size=112.0, rotation=math.pi / 2)
    M = roi.crop_to_image(224)
    np.testing.assert_allclose(M @ [112.0, 112.0, 1.0], [300.0, 200.0])
    # the crop's "up" (fingers) is image +x for rotation +90 degrees
    np.testing.assert_allclose(M @ [112.0, 0.0, 1.0], [356.0, 200.0])
    corners = roi.corners()
    assert corners.shape == (4, 2)
    np.testing.assert_allclose(roi.bounds(), [244.0, 144.0, 356.0, 256.0])


def test_crop_samples_the_rotated_square() -> None:
    image = np.zeros((400, 600, 3), np.uint8)
    image[190:211, 340:361] = (0, 0, 255)  # red square 50 px right of the ROI centre
    roi = Roi(cx=300.0, cy=200.0, size=224.0, rotation=math.pi / 2)
    tensor = crop(image, roi)
    assert tensor.shape == (1, 3, 224, 224)
    red = tensor[0, 0]
    v, u = np.unravel_index(np.argmax(red), red.shape)
    assert abs(u - 112) <= 11 and abs(v - 62) <= 11  # image +x is the crop's up


def test_tracking_roi_follows_rotation_and_translation() -> None:
    rng = np.random.default_rng(1)
    hand = _hand(rng)
    upright = roi_from_landmarks(hand + CENTRE)
    assert upright.rotation == pytest.approx(0.0, abs=0.05)
    for angle in (-2.5, -1.0, 0.7, 2.0):
        roi = roi_from_landmarks(_rotate(hand, angle) + CENTRE)
        assert math.remainder(roi.rotation - angle, 2 * math.pi) == pytest.approx(0.0, abs=0.05)
        assert roi.size == pytest.approx(upright.size, rel=0.05)
        # the ROI centre moves with the hand: rotating the hand rotates the centre's offset
        offset = _rotate(np.array([[upright.cx - 400.0, upright.cy - 300.0]]), angle)[0]
        np.testing.assert_allclose([roi.cx - 400.0, roi.cy - 300.0], offset, atol=2.0)
    moved = roi_from_landmarks(hand + CENTRE + np.array([50.0, 20.0]))
    assert (moved.cx - upright.cx, moved.cy - upright.cy) == pytest.approx((50.0, 20.0))
    # the ROI contains every landmark
    lo, hi = upright.bounds()[:2], upright.bounds()[2:]
    assert ((hand + CENTRE > lo) & (hand + CENTRE < hi)).all()


def test_rotation_and_iou_helpers() -> None:
    assert rotation_towards(np.array([0.0, 10.0]), np.array([0.0, 0.0])) == pytest.approx(0.0)
    assert rotation_towards(np.array([0.0, 0.0]), np.array([0.0, 10.0])) == pytest.approx(-math.pi)
    assert box_iou(np.array([0, 0, 2, 2]), np.array([1, 0, 3, 2])) == pytest.approx(1 / 3)
    assert box_iou(np.array([0, 0, 1, 1]), np.array([2, 2, 3, 3])) == 0.0


def test_handedness_follows_mediapipe_mirror_convention() -> None:
    # MediaPipe's score is P("Right") for a mirrored (selfie) image
    assert handedness_from_score(0.9, mirrored=True) == ("right", 0.9)
    assert handedness_from_score(0.9, mirrored=False) == ("left", 0.9)
    hand, score = handedness_from_score(0.2, mirrored=False)
    assert hand == "right" and score == pytest.approx(0.8)
