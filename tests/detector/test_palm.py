"""Palm detection geometry: anchors, decoding, weighted NMS, letterbox, palm -> ROI; real model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.detector.config import DetectorConfig
from services.detector.landmarks import Roi
from services.detector.models import model_path
from services.detector.palm import (
    PALM_INPUT,
    PalmDetection,
    PalmDetector,
    decode,
    letterbox,
    roi_from_palm,
    ssd_anchors,
    weighted_nms,
)
from services.detector.runtime import create_session
from tests.detector.conftest import CATCHER_CROP, HAND_REGIONS, crop


def test_anchor_layout_matches_the_model_output() -> None:
    a = ssd_anchors()
    assert a.shape == (2016, 2)
    np.testing.assert_allclose(a[0], [0.5 / 24, 0.5 / 24])
    np.testing.assert_allclose(a[1], a[0])  # 2 anchors per cell on the stride-8 layer
    np.testing.assert_allclose(a[2], [1.5 / 24, 0.5 / 24])  # x runs fastest
    np.testing.assert_allclose(a[2 * 24], [0.5 / 24, 1.5 / 24])
    first16 = 24 * 24 * 2
    np.testing.assert_allclose(a[first16:first16 + 6], [[0.5 / 12, 0.5 / 12]] * 6)
    np.testing.assert_allclose(a[-1], [11.5 / 12, 11.5 / 12])


def test_decode_places_boxes_and_keypoints_relative_to_their_anchor() -> None:
    raw = np.zeros((2016, 18))
    logits = np.full(2016, -10.0)
    i = 1152 + 6 * (12 * 5 + 7)  # a stride-16 cell, column 7, row 5
    logits[i] = 3.0
    raw[i, :4] = [9.6, -19.2, 38.4, 19.2]  # dx, dy, w, h in input pixels
    raw[i, 4:6] = [0.0, 19.2]  # wrist keypoint
    boxes, keypoints, scores = decode(raw, logits, 0.5)
    assert scores == pytest.approx([1.0 / (1.0 + math.exp(-3.0))])
    cx, cy = (7.5 / 12) + 0.05, (5.5 / 12) - 0.1
    np.testing.assert_allclose(boxes[0], [cx - 0.1, cy - 0.05, cx + 0.1, cy + 0.05])
    np.testing.assert_allclose(keypoints[0, 0], [7.5 / 12, 5.5 / 12 + 0.1])
    np.testing.assert_allclose(keypoints[0, 1], [7.5 / 12, 5.5 / 12])  # raw 0: the anchor
    assert decode(raw, np.full(2016, 1e9), 0.5)[2].max() <= 1.0  # logits clipped


def test_weighted_nms_merges_overlaps_by_score_and_keeps_the_rest() -> None:
    boxes = np.array([[0.0, 0.0, 1.0, 1.0], [0.1, 0.0, 1.1, 1.0], [3.0, 3.0, 4.0, 4.0]])
    keypoints = np.zeros((3, 7, 2))
    keypoints[:, 0] = [[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]]
    scores = np.array([0.9, 0.6, 0.7])
    out = weighted_nms(boxes, keypoints, scores, 0.3)
    assert [s for s, _, _ in out] == [0.9, 0.7]
    np.testing.assert_allclose(out[0][1], [0.04, 0.0, 1.04, 1.0])  # (0.9*0 + 0.6*0.1) / 1.5
    np.testing.assert_allclose(out[0][2][0], [0.4, 0.0])
    np.testing.assert_allclose(out[1][1], boxes[2])


def test_letterbox_keeps_the_aspect_and_maps_back() -> None:
    image = np.zeros((720, 1280, 3), np.uint8)
    image[:, :, 2] = 255  # red in BGR
    tensor, box = letterbox(image)
    assert tensor.shape == (1, 3, PALM_INPUT, PALM_INPUT) and tensor.dtype == np.float32
    assert tensor[0, 0, 96, 96] == pytest.approx(1.0)  # RGB order: red is channel 0
    assert tensor[0, 2, 96, 96] == 0.0
    assert tensor[0, 0, 0, 96] == 0.0  # zero padding above the 192x108 content
    rows = np.flatnonzero(tensor[0, 0, :, 96] > 0.5)
    assert (rows[0], rows[-1]) == (42, 149)
    corners = box.to_frame(np.array([[0.0, 42 / 192], [1.0, 150 / 192]]))
    np.testing.assert_allclose(corners, [[0.0, 0.0], [1280.0, 720.0]], atol=1.0)


def test_palm_roi_points_from_the_wrist_to_the_fingers() -> None:
    box = np.array([100.0, 200.0, 140.0, 240.0])
    up = np.zeros((7, 2))
    up[0], up[2] = [120.0, 235.0], [120.0, 205.0]  # wrist below the middle MCP
    roi = roi_from_palm(PalmDetection(0.9, box, up), scale=2.6, shift_y=-0.5)
    assert roi.rotation == pytest.approx(0.0)
    assert (roi.cx, roi.cy, roi.size) == pytest.approx((120.0, 200.0, 104.0))
    right = np.zeros((7, 2))
    right[0], right[2] = [105.0, 220.0], [135.0, 220.0]  # fingers point to +x
    roi = roi_from_palm(PalmDetection(0.9, box, right), scale=2.6, shift_y=-0.5)
    assert roi.rotation == pytest.approx(math.pi / 2)
    assert (roi.cx, roi.cy) == pytest.approx((140.0, 220.0))  # shifted towards the fingers


def test_real_palm_model_finds_the_catching_hand(models_dir: object,
                                                 opencv_images: dict[str, np.ndarray]) -> None:
    config = DetectorConfig(device="cpu")
    detector = PalmDetector(create_session(model_path("palm_full", str(models_dir)), "cpu", 2),
                            config.palm_score_threshold, config.palm_nms_iou)
    image = crop(opencv_images["basketball1.png"], CATCHER_CROP)
    palms = detector(image)
    assert palms and palms[0].score > 0.5
    x0, y0 = CATCHER_CROP[:2]
    xmin, ymin, xmax, ymax = HAND_REGIONS[("basketball1.png", CATCHER_CROP)]
    cx, cy = 0.5 * (palms[0].box[:2] + palms[0].box[2:]) + (x0, y0)
    assert xmin <= cx <= xmax and ymin <= cy <= ymax
    roi: Roi = roi_from_palm(palms[0])
    assert roi.size > 2.0 * (palms[0].box[2] - palms[0].box[0])
