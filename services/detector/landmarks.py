"""Hand ROIs and the MediaPipe hand-landmark model (224x224, 21 landmarks).

A :class:`Roi` is a rotated square in image pixels: centre ``(cx, cy)``, side ``size`` and
``rotation`` (rad). The crop's "up" (``-v``) points from the wrist towards the fingers, so an
upright hand has rotation 0; a crop pixel ``(u, v)`` of an ``n x n`` crop maps to the image point
``c + R(rotation) (size / n) ((u, v) - n / 2)`` with ``R`` the 2-D rotation matrix (image axes,
``v`` down). This is MediaPipe's ``NormalizedRect`` in pixels.

Landmark-model outputs (tflite2onnx keeps MediaPipe's names): ``Identity`` (1, 63) x, y, z in
crop pixels, z relative to the wrist in the same scale as x; ``Identity_1`` presence and
``Identity_2`` handedness, both already sigmoided; ``Identity_3`` (1, 63) world landmarks in
metres around the hand's centre, axes of the crop (rotated here into image axes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from services.common.protocol import NUM_LANDMARKS

LANDMARK_INPUT = 224
WRIST, INDEX_MCP, MIDDLE_MCP, RING_MCP = 0, 5, 9, 13
# MediaPipe hand_landmark_landmarks_to_roi: the landmarks that bound the tracking ROI
# (wrist, thumb CMC/MCP/IP, and the MCP and PIP of each finger).
ROI_LANDMARKS = (0, 1, 2, 3, 5, 6, 9, 10, 13, 14, 17, 18)


def normalize_radians(angle: float) -> float:
    """Angle wrapped into [-pi, pi)."""
    return angle - 2.0 * math.pi * math.floor((angle + math.pi) / (2.0 * math.pi))


def rotation_towards(p0: NDArray[Any], p1: NDArray[Any]) -> float:
    """ROI rotation that makes the direction ``p0 -> p1`` (pixels) point up in the crop.

    MediaPipe's ``target_angle = 90 deg - atan2(-(y1 - y0), x1 - x0)``.
    """
    return normalize_radians(math.pi / 2.0 - math.atan2(-(p1[1] - p0[1]), p1[0] - p0[0]))


@dataclass(frozen=True)
class Roi:
    """Rotated square hand region in image pixels (see the module docstring)."""

    cx: float
    cy: float
    size: float
    rotation: float

    def crop_to_image(self, n: int) -> NDArray[np.float64]:
        """2x3 affine map from crop pixels of an ``n x n`` crop to image pixels."""
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        k = self.size / n
        A = np.array([[c * k, -s * k], [s * k, c * k]])
        t = np.array([self.cx, self.cy]) - A @ np.array([n / 2.0, n / 2.0])
        return np.hstack([A, t[:, None]])

    def corners(self) -> NDArray[np.float64]:
        """(4, 2) image corners: top-left, top-right, bottom-right, bottom-left of the crop."""
        M = self.crop_to_image(1)
        square = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 1.0, 1.0]])
        return square @ M.T

    def bounds(self) -> NDArray[np.float64]:
        """Axis-aligned bounds ``[xmin, ymin, xmax, ymax]`` of the rotated square."""
        pts = self.corners()
        return np.concatenate([pts.min(axis=0), pts.max(axis=0)])


def box_iou(a: NDArray[Any], b: NDArray[Any]) -> float:
    """IoU of two ``[xmin, ymin, xmax, ymax]`` boxes."""
    iw = min(a[2], b[2]) - max(a[0], b[0])
    ih = min(a[3], b[3]) - max(a[1], b[1])
    if iw <= 0.0 or ih <= 0.0:
        return 0.0
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0.0 else 0.0


def transform_rect(cx: float, cy: float, width: float, height: float, rotation: float,
                   scale: float, shift_y: float) -> Roi:
    """MediaPipe's ``RectTransformationCalculator`` in pixels, with ``square_long``.

    Shift the centre by ``shift_y * height`` along the rotated y axis (negative: towards the
    fingers), take the long side and scale it.
    """
    cx += -height * shift_y * math.sin(rotation)
    cy += height * shift_y * math.cos(rotation)
    return Roi(cx, cy, max(width, height) * scale, rotation)


def roi_from_landmarks(pixels: NDArray[Any], scale: float = 2.0, shift_y: float = -0.1) -> Roi:
    """Tracking ROI for the next frame from this frame's landmarks (pixels, (21, 2)).

    MediaPipe ``hand_landmark_landmarks_to_roi``: rotation from the wrist towards the mean of the
    middle MCP and the mid-point of the index and ring MCPs; the rotated bounding box of the
    palm and finger-base landmarks; shift -0.1, scale 2.0, squared on the long side.
    """
    p = np.asarray(pixels, float)
    mid = 0.5 * (0.5 * (p[INDEX_MCP] + p[RING_MCP]) + p[MIDDLE_MCP])
    rotation = rotation_towards(p[WRIST], mid)
    pts = p[list(ROI_LANDMARKS)]
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    c, s = math.cos(rotation), math.sin(rotation)
    R = np.array([[c, -s], [s, c]])
    local = (pts - centre) @ R  # rows: R^T (p - centre), coordinates in the crop's axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    box_centre = centre + R @ (0.5 * (lo + hi))
    width, height = hi - lo
    return transform_rect(float(box_centre[0]), float(box_centre[1]), float(width),
                          float(height), rotation, scale, shift_y)


def crop(image_bgr: NDArray[Any], roi: Roi, n: int = LANDMARK_INPUT) -> NDArray[np.float32]:
    """The ROI as a (1, 3, n, n) RGB tensor in [0, 1] (border pixels replicated)."""
    patch = cv2.warpAffine(image_bgr, roi.crop_to_image(n), (n, n),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                           borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(cv2.dnn.blobFromImage(patch, 1.0 / 255.0, swapRB=True), np.float32)


@dataclass(frozen=True)
class LandmarkEstimate:
    """One run of the landmark model on one ROI, mapped back to the image."""

    roi: Roi
    pixels: NDArray[np.float64]  # (21, 2) image pixels (u, v)
    z_px: NDArray[np.float64]  # (21,) depth relative to the wrist, image-pixel scale
    world: NDArray[np.float64]  # (21, 3) metres around the hand centre, image axes (z forward)
    presence: float  # hand presence in [0, 1]
    handedness: str  # "left" / "right" (of the person)
    handedness_score: float  # confidence of ``handedness`` in [0.5, 1]


def handedness_from_score(right_score: float, mirrored: bool) -> tuple[str, float]:
    """Person's hand from MediaPipe's ``Identity_2``.

    The model answers P("Right") for a *mirrored* (selfie) image; on an unmirrored camera image
    that label is the person's left hand.
    """
    label_right = right_score >= 0.5
    is_right = label_right if mirrored else not label_right
    return ("right" if is_right else "left"), max(right_score, 1.0 - right_score)


class LandmarkModel:
    """The hand-landmark ONNX model on one ROI at a time."""

    def __init__(self, session: Any, mirrored: bool = False) -> None:
        self.session = session
        self.input_name = session.get_inputs()[0].name
        self.output_names = [o.name for o in session.get_outputs()]
        for name in ("Identity", "Identity_1", "Identity_2", "Identity_3"):
            if name not in self.output_names:
                raise ValueError(f"landmark model lacks output {name} (has {self.output_names}); "
                                 "run `handkse models prepare --force`")
        self.mirrored = mirrored

    def infer(self, tensor: NDArray[np.float32]) -> dict[str, NDArray[np.float32]]:
        outputs = self.session.run(None, {self.input_name: tensor})
        return dict(zip(self.output_names, outputs, strict=True))

    def postprocess(self, roi: Roi, out: dict[str, NDArray[np.float32]]) -> LandmarkEstimate:
        raw = out["Identity"].reshape(NUM_LANDMARKS, 3).astype(np.float64)
        M = roi.crop_to_image(LANDMARK_INPUT)
        pixels = raw[:, :2] @ M[:, :2].T + M[:, 2]
        z_px = raw[:, 2] * (roi.size / LANDMARK_INPUT)
        world = out["Identity_3"].reshape(NUM_LANDMARKS, 3).astype(np.float64)
        c, s = math.cos(roi.rotation), math.sin(roi.rotation)
        world = np.column_stack([c * world[:, 0] - s * world[:, 1],
                                 s * world[:, 0] + c * world[:, 1], world[:, 2]])
        hand, hand_score = handedness_from_score(float(out["Identity_2"].ravel()[0]),
                                                 self.mirrored)
        return LandmarkEstimate(roi=roi, pixels=pixels, z_px=z_px, world=world,
                                presence=float(out["Identity_1"].ravel()[0]),
                                handedness=hand, handedness_score=hand_score)

    def __call__(self, image_bgr: NDArray[Any], roi: Roi) -> LandmarkEstimate:
        return self.postprocess(roi, self.infer(crop(image_bgr, roi)))


__all__ = ["LANDMARK_INPUT", "LandmarkEstimate", "LandmarkModel", "Roi", "box_iou", "crop",
           "handedness_from_score", "roi_from_landmarks", "rotation_towards", "transform_rect"]
