"""Per-landmark visibility: RTMPose SimCC scores, or a documented heuristic.

MediaPipe's hand-landmark model returns one presence score per hand and **no** per-landmark
visibility; the paper (section III.A.1) takes per-landmark scores from a second, heatmap-style
model (AlphaPose) run on MediaPipe's hand box, and ignores landmarks below a threshold.

1. With a user-supplied RTMPose-hand ONNX model (``--keypoint-model``, see
   :data:`services.detector.models.RTMPOSE_HINT`), :class:`SimccKeypointModel` runs it on the box
   of the MediaPipe landmarks (padding 1.25, as rtmlib) and the visibility of landmark i is its
   SimCC confidence: the mean of the maxima of its x and y distributions, clipped to [0, 1]
   (rtmlib 0.0.16; a demo threshold of 0.43). Its 2-D keypoints replace MediaPipe's, as
   AlphaPose's did in the paper (same 21-point order: COCO-WholeBody hand = MediaPipe).
2. Without it, :func:`heuristic_visibility` = hand presence x in-image x depth consistency.
   **This is a heuristic, not a learned score.** Depth consistency compares the depth measured
   at each landmark with the depth the hand model expects there: the model's relative depths
   (world landmarks, metres) plus one offset, the median over the landmarks of measured minus
   relative depth. A landmark measured much *nearer* than expected is behind something (an
   object, the other hand): visibility falls to 0 over ``occlusion_margin_m`` (logistic of width
   ``margin_softness_m``). One measured much *farther* than expected shows the background
   through a gap (the depth missed the finger): visibility falls too, at
   ``background_margin_m``. A landmark without depth is not judged (factor 1; its point is NaN).
   Self-occlusion within the hand is within the margins and is not detected.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

RTMPOSE_MEAN = (123.675, 116.28, 103.53)  # RGB, ImageNet (mmpose data_preprocessor)
RTMPOSE_STD = (58.395, 57.12, 57.375)


def _logistic(x: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.asarray(0.5 * (1.0 + np.tanh(0.5 * x)), np.float64)  # overflow-free sigmoid


def in_image_factor(pixels: NDArray[Any], width: int, height: int, margin_px: float
                    ) -> NDArray[np.float64]:
    """1 inside the image, fading linearly to 0 within ``margin_px`` of the border, 0 outside."""
    p = np.asarray(pixels, np.float64).reshape(-1, 2)
    d = np.asarray(np.min(np.column_stack([p[:, 0] + 0.5, p[:, 1] + 0.5, width - 0.5 - p[:, 0],
                                           height - 0.5 - p[:, 1]]), axis=1), np.float64)
    if margin_px <= 0.0:
        return (d >= 0.0).astype(np.float64)
    return np.asarray(np.clip(d / margin_px, 0.0, 1.0), np.float64)


def depth_consistency(z_measured: NDArray[Any], z_relative: NDArray[Any],
                      occlusion_margin_m: float = 0.03, background_margin_m: float = 0.08,
                      softness_m: float = 0.008) -> tuple[NDArray[np.float64], float]:
    """Per-landmark factor in [0, 1] and the fitted hand depth offset (NaN without depth).

    ``z_measured``: depth at each landmark (m, NaN = none); ``z_relative``: the hand model's
    relative depth of each landmark (m, any common offset).
    """
    zm = np.asarray(z_measured, np.float64)
    zr = np.asarray(z_relative, np.float64)
    ok = np.isfinite(zm)
    factor = np.ones_like(zm)
    if not ok.any():
        return factor, float("nan")
    offset = float(np.median(zm[ok] - zr[ok]))
    ahead = (offset + zr) - zm  # > 0: measured nearer than the model puts the landmark
    with np.errstate(invalid="ignore"):
        occluded = _logistic((ahead - occlusion_margin_m) / softness_m)
        background = _logistic((-ahead - background_margin_m) / softness_m)
    factor[ok] = ((1.0 - occluded) * (1.0 - background))[ok]
    return factor, offset


def heuristic_visibility(presence: float, pixels: NDArray[Any], z_measured: NDArray[Any],
                         z_relative: NDArray[Any], image_size: tuple[int, int], *,
                         image_margin_px: float = 2.0, occlusion_margin_m: float = 0.03,
                         background_margin_m: float = 0.08, softness_m: float = 0.008
                         ) -> NDArray[np.float32]:
    """presence x in-image x depth consistency, per landmark, in [0, 1] (float32)."""
    w, h = image_size
    depth_factor, _ = depth_consistency(z_measured, z_relative, occlusion_margin_m,
                                        background_margin_m, softness_m)
    v = float(np.clip(presence, 0.0, 1.0)) * in_image_factor(pixels, w, h, image_margin_px)
    return np.clip(v * depth_factor, 0.0, 1.0).astype(np.float32)


def box_affine(pixels: NDArray[Any], input_w: int, input_h: int, padding: float
               ) -> NDArray[np.float64]:
    """2x3 map image -> model input for the padded box of ``pixels``, aspect fixed to the
    input's (rtmlib ``bbox_xyxy2cs`` + ``top_down_affine``, no rotation)."""
    p = np.asarray(pixels, np.float64)
    lo, hi = p.min(axis=0), p.max(axis=0)
    centre = 0.5 * (lo + hi)
    bw, bh = np.maximum(hi - lo, 1.0) * padding
    aspect = input_w / input_h
    if bw > bh * aspect:
        bh = bw / aspect
    else:
        bw = bh * aspect
    k = input_w / bw
    return np.array([[k, 0.0, input_w / 2.0 - k * centre[0]],
                     [0.0, k, input_h / 2.0 - k * centre[1]]])


class SimccKeypointModel:
    """A top-down SimCC keypoint model (RTMPose-hand ``end2end.onnx``) on one hand box.

    Input (1, 3, H, W) RGB normalised with ImageNet mean/std; outputs ``simcc_x`` (1, K, W*r)
    and ``simcc_y`` (1, K, H*r), r = ``split_ratio`` (2.0 for RTMPose).
    """

    def __init__(self, session: Any, padding: float = 1.25, split_ratio: float = 2.0) -> None:
        self.session = session
        inp = session.get_inputs()[0]
        self.input_name = inp.name
        _, channels, h, w = inp.shape
        if channels != 3 or not isinstance(h, int) or not isinstance(w, int):
            raise ValueError(f"keypoint model input must be [1, 3, H, W] with fixed H, W; got "
                             f"{inp.shape}")
        self.input_h, self.input_w = h, w
        outs = session.get_outputs()
        if len(outs) < 2:
            raise ValueError("keypoint model must output simcc_x and simcc_y")
        self.padding = padding
        self.split_ratio = split_ratio
        self._mean = np.array(RTMPOSE_MEAN, np.float32)
        self._inv_std = 1.0 / np.array(RTMPOSE_STD, np.float32)

    def __call__(self, image_bgr: NDArray[Any], pixels: NDArray[Any]
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Keypoints (K, 2) in image pixels and their confidences (K,) in [0, 1]."""
        M = box_affine(pixels, self.input_w, self.input_h, self.padding)
        patch = cv2.warpAffine(image_bgr, M, (self.input_w, self.input_h),
                               flags=cv2.INTER_LINEAR)
        rgb = patch[:, :, ::-1].astype(np.float32)
        tensor = ((rgb - self._mean) * self._inv_std).transpose(2, 0, 1)[None].copy()
        simcc_x, simcc_y = self.session.run(None, {self.input_name: tensor})[:2]
        sx, sy = simcc_x[0], simcc_y[0]
        loc = np.column_stack([sx.argmax(axis=1), sy.argmax(axis=1)]) / self.split_ratio
        score = 0.5 * (sx.max(axis=1) + sy.max(axis=1))
        Minv = cv2.invertAffineTransform(M)
        keypoints = loc @ Minv[:, :2].T + Minv[:, 2]
        return keypoints, np.clip(score.astype(np.float64), 0.0, 1.0)


__all__ = ["SimccKeypointModel", "box_affine", "depth_consistency", "heuristic_visibility",
           "in_image_factor"]
