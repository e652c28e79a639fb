"""The hand pipeline: colour + registered depth -> up to two hands of 21 3-D landmarks.

Per frame (MediaPipe Hands' structure, on ONNX Runtime):

1. ROIs: in tracking mode each hand found in the previous frame gives its next ROI from its
   landmarks (:func:`~services.detector.landmarks.roi_from_landmarks`), and palm detection is
   skipped while the hands stay present. Palm detection (:mod:`services.detector.palm`) runs
   when no hand is tracked, every ``palm_interval_frames`` while fewer than ``max_hands`` are,
   on every frame with ``tracking = False``, and again on the same frame when every tracked
   hand was just lost. A palm whose ROI overlaps a tracked hand's is that hand.
2. Landmarks (:mod:`services.detector.landmarks`) on each ROI; a hand is kept while its presence
   stays above the threshold; of two hands that converged onto one, the more present is kept.
3. Optional RTMPose-hand keypoints and confidences on each hand box
   (:class:`~services.detector.visibility.SimccKeypointModel`).
4. Back-projection (:mod:`services.detector.backproject`) and visibility
   (:mod:`services.detector.visibility`).

:meth:`HandPipeline.process` returns the hands and the time of each stage (``preprocess``:
letterbox and crops; ``palm``: palm model, decoding, NMS; ``landmarks``: landmark and keypoint
models; ``backproject``: depth, 3-D points and visibility). The class keeps the tracking state;
it is not thread-safe (one per frame stream).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import CameraIntrinsics
from services.detector.backproject import backproject, landmark_depths
from services.detector.config import DetectorConfig
from services.detector.landmarks import (
    LandmarkEstimate,
    LandmarkModel,
    Roi,
    box_iou,
    crop,
    roi_from_landmarks,
)
from services.detector.palm import PalmDetection, PalmDetector, letterbox, roi_from_palm
from services.detector.visibility import SimccKeypointModel, heuristic_visibility

STAGES = ("preprocess", "palm", "landmarks", "backproject")


@dataclass(frozen=True)
class DetectedHand:
    """One hand of one frame. Points are in the camera frame (m), NaN where there is no depth."""

    handedness: str  # "left" / "right" of the person
    score: float  # hand presence in [0, 1]
    pixels: NDArray[np.float64]  # (21, 2) image pixels (u, v)
    points: NDArray[np.float64]  # (21, 3) camera frame, metres; NaN rows without depth
    visibility: NDArray[np.float32]  # (21,) in [0, 1]
    depth_m: NDArray[np.float64]  # (21,) robust depth at each landmark, NaN = none
    world: NDArray[np.float64]  # (21, 3) the model's metric hand shape (image axes)
    roi: Roi  # the ROI the landmarks came from
    tracked: bool  # True when the ROI came from the previous frame's landmarks
    handedness_score: float = 1.0


@dataclass(frozen=True)
class FrameResult:
    hands: tuple[DetectedHand, ...]
    timings_s: dict[str, float] = field(default_factory=dict)  # stage -> seconds (stages run)
    palm_ran: bool = False


def square_tiles(width: int, height: int, min_aspect: float = 1.2
                 ) -> list[tuple[int, int, int]]:
    """The two squares ``(x0, y0, side)`` at the ends of a long frame (none for a frame
    closer to square than ``min_aspect``): a hand ~8 % of a 16:9 frame's width is ~14 % of
    such a square, which the 192-px palm detector finds."""
    side = min(width, height)
    if max(width, height) < min_aspect * side:
        return []
    if width >= height:
        return [(0, 0, side), (width - side, 0, side)]
    return [(0, 0, side), (0, height - side, side)]


def _landmark_bounds(e: LandmarkEstimate) -> NDArray[np.float64]:
    return np.concatenate([e.pixels.min(axis=0), e.pixels.max(axis=0)])


class HandPipeline:
    """Hand detection and tracking on a stream of frames (see the module docstring)."""

    def __init__(self, config: DetectorConfig, palm: PalmDetector, landmarks: LandmarkModel,
                 keypoints: SimccKeypointModel | None = None,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self.config = config
        # stage timer: wall time by default; the benchmark passes time.thread_time with one
        # ORT thread to measure CPU cost independently of other load on the machine
        self.clock = clock
        self.palm = palm
        self.landmarks = landmarks
        self.keypoints = keypoints
        self._tracked: list[Roi] = []
        self._frames_since_palm = 0

    @classmethod
    def from_config(cls, config: DetectorConfig,
                    clock: Callable[[], float] = time.perf_counter) -> HandPipeline:
        """Load the prepared models (``ModelsMissing`` tells the user to run ``models prepare``)
        and start ONNX Runtime sessions on ``config.device``."""
        from services.detector.models import model_path, models_dir_or_default
        from services.detector.runtime import create_session

        root = models_dir_or_default(config.models_dir or None)

        def session(path: Any) -> Any:
            return create_session(path, config.device, config.threads, cache_dir=root)

        palm = PalmDetector(session(model_path(f"palm_{config.palm_model}", root)),
                            config.palm_score_threshold, config.palm_nms_iou)
        landmarks = LandmarkModel(session(model_path(f"landmark_{config.landmark_model}", root)),
                                  mirrored=config.mirrored_input)
        keypoints = None
        if config.keypoint_model:
            from pathlib import Path

            from services.detector.models import RTMPOSE_HINT

            path = Path(config.keypoint_model).expanduser()
            if not path.is_file():
                raise FileNotFoundError(f"keypoint model {path} does not exist; {RTMPOSE_HINT}")
            keypoints = SimccKeypointModel(session(path), config.keypoint_bbox_padding,
                                           config.keypoint_simcc_split_ratio)
        return cls(config, palm, landmarks, keypoints, clock)

    @property
    def providers(self) -> list[str]:
        """Execution providers of the landmark session, best first."""
        return list(self.landmarks.session.get_providers())

    def reset(self) -> None:
        """Forget the tracked hands (the next frame runs palm detection)."""
        self._tracked = []
        self._frames_since_palm = 0

    # --- stages ---

    def _detect_palms(self, image: NDArray[Any], timings: dict[str, float],
                      offset: tuple[int, int] = (0, 0)) -> list[PalmDetection]:
        t0 = self.clock()
        tensor, box = letterbox(image)
        t1 = self.clock()
        palms = self.palm.postprocess(*self.palm.infer(tensor), box)
        t2 = self.clock()
        timings["preprocess"] = timings.get("preprocess", 0.0) + (t1 - t0)
        timings["palm"] = timings.get("palm", 0.0) + (t2 - t1)
        if offset == (0, 0):
            return palms
        shift = np.array(offset, float)
        return [PalmDetection(p.score, p.box + np.tile(shift, 2), p.keypoints + shift)
                for p in palms]

    def _palm_rois(self, image: NDArray[Any], timings: dict[str, float]) -> list[Roi]:
        """Palm ROIs, best first: on the whole frame, else on its two end squares."""
        c = self.config
        palms = self._detect_palms(image, timings)
        if not palms and c.palm_tiles:
            for x0, y0, side in square_tiles(image.shape[1], image.shape[0]):
                palms += self._detect_palms(image[y0:y0 + side, x0:x0 + side], timings,
                                            (x0, y0))
            palms.sort(key=lambda p: -p.score)
        self._frames_since_palm = 0
        return [roi_from_palm(p, c.palm_roi_scale, c.palm_roi_shift) for p in palms]

    def _run_landmarks(self, image: NDArray[Any], rois: list[Roi],
                       timings: dict[str, float]) -> list[LandmarkEstimate]:
        out = []
        for roi in rois:
            t0 = self.clock()
            tensor = crop(image, roi)
            t1 = self.clock()
            out.append(self.landmarks.postprocess(roi, self.landmarks.infer(tensor)))
            t2 = self.clock()
            timings["preprocess"] = timings.get("preprocess", 0.0) + (t1 - t0)
            timings["landmarks"] = timings.get("landmarks", 0.0) + (t2 - t1)
        return out

    def _new_hands(self, image: NDArray[Any], tracked: list[LandmarkEstimate],
                   timings: dict[str, float]) -> list[LandmarkEstimate]:
        """Palm detection for hands not yet tracked; returns the accepted new hands."""
        c = self.config
        taken = [e.roi.bounds() for e in tracked]
        rois: list[Roi] = []
        for roi in self._palm_rois(image, timings):
            if len(tracked) + len(rois) >= c.max_hands:
                break
            bounds = roi.bounds()
            if any(box_iou(bounds, b) > c.duplicate_iou for b in taken):
                continue
            taken.append(bounds)
            rois.append(roi)
        return [e for e in self._run_landmarks(image, rois, timings)
                if e.presence >= c.presence_threshold]

    def _dedupe(self, estimates: list[LandmarkEstimate]) -> list[LandmarkEstimate]:
        kept: list[LandmarkEstimate] = []
        for e in sorted(estimates, key=lambda e: -e.presence):
            if all(box_iou(_landmark_bounds(e), _landmark_bounds(k)) <= self.config.duplicate_iou
                   for k in kept):
                kept.append(e)
        return kept[: self.config.max_hands]

    # --- frame ---

    def process(self, image_bgr: NDArray[Any], depth: NDArray[Any] | None,
                depth_scale_m: float, intrinsics: CameraIntrinsics) -> FrameResult:
        """Hands in one frame.

        ``image_bgr``: (H, W, 3) uint8; ``depth``: (H_d, W_d) raw depth registered to the colour
        image (``depth_scale_m`` metres per unit, 0 = none) or None; ``intrinsics`` of the colour
        image.
        """
        c = self.config
        timings: dict[str, float] = {}
        palm_ran = False
        tracked_rois = self._tracked if c.tracking else []
        hands = [e for e in self._run_landmarks(image_bgr, tracked_rois, timings)
                 if e.presence >= c.tracking_presence_threshold]
        from_tracking = {id(e) for e in hands}
        self._frames_since_palm += 1
        # no hand (none tracked, or every tracked hand lost): detect palms in this same frame
        if (not c.tracking or not hands
                or (len(hands) < c.max_hands and self._frames_since_palm >= c.palm_interval_frames)):
            hands += self._new_hands(image_bgr, hands, timings)
            palm_ran = True
        hands = self._dedupe(hands)
        self._tracked = ([roi_from_landmarks(e.pixels, c.tracking_roi_scale, c.tracking_roi_shift)
                          for e in hands] if c.tracking else [])
        result = tuple(self._finish(image_bgr, depth, depth_scale_m, intrinsics, e,
                                    id(e) in from_tracking, timings) for e in hands)
        return FrameResult(hands=result, timings_s=timings, palm_ran=palm_ran)

    def _finish(self, image: NDArray[Any], depth: NDArray[Any] | None, scale_m: float,
                intrinsics: CameraIntrinsics, e: LandmarkEstimate, tracked: bool,
                timings: dict[str, float]) -> DetectedHand:
        c = self.config
        h, w = image.shape[:2]
        pixels = e.pixels
        scores = None
        if self.keypoints is not None:
            t0 = self.clock()
            pixels, scores = self.keypoints(image, e.pixels)
            timings["landmarks"] = timings.get("landmarks", 0.0) + self.clock() - t0
        t0 = self.clock()
        if depth is not None:
            z = landmark_depths(depth, scale_m, pixels, (w, h), window=c.depth_window_px,
                                min_valid=c.depth_min_valid, edge_jump_m=c.depth_edge_jump_m,
                                cluster_m=c.depth_cluster_m, depth_min_m=c.depth_min_m,
                                depth_max_m=c.depth_max_m)
        else:
            z = np.full(len(pixels), np.nan)
        points = backproject(pixels, z, intrinsics)
        if scores is not None:
            visibility = scores.astype(np.float32)
        else:
            visibility = heuristic_visibility(
                e.presence, pixels, z, e.world[:, 2], (w, h), image_margin_px=c.image_margin_px,
                occlusion_margin_m=c.occlusion_margin_m, background_margin_m=c.background_margin_m,
                softness_m=c.margin_softness_m)
        timings["backproject"] = timings.get("backproject", 0.0) + self.clock() - t0
        return DetectedHand(handedness=e.handedness, score=float(np.clip(e.presence, 0.0, 1.0)),
                            pixels=pixels, points=points, visibility=visibility, depth_m=z,
                            world=e.world, roi=e.roi, tracked=tracked,
                            handedness_score=e.handedness_score)


__all__ = ["STAGES", "DetectedHand", "FrameResult", "HandPipeline"]
