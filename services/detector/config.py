"""Configuration of the hand detector: models, runtime, tracking, depth and visibility.

Defaults follow MediaPipe Hands' own graphs (``palm_detection_cpu``, ``hand_landmark_cpu``,
``hand_landmark_landmarks_to_roi``: palm score 0.5, weighted NMS at IoU 0.3, palm ROI scale 2.6
with a shift of -0.5 box heights towards the fingers, tracking ROI scale 2.0 with shift -0.1,
presence 0.5), the paper's Azure Kinect working distance (0.4-1.0 m) for the depth limits, and
docs/detector.md for the rest. Every field is a plain scalar or string so
the ``[detector]`` TOML section and ``--set detector.key=value`` can set it.
"""

from __future__ import annotations

from dataclasses import dataclass

DEVICES = ("auto", "cpu", "cuda", "tensorrt")
VARIANTS = ("full", "lite")


@dataclass(frozen=True)
class DetectorConfig:
    """Parameters of :class:`services.detector.pipeline.HandPipeline` and the detector service."""

    # --- models and runtime ---
    # Folder of the prepared ONNX models; "" = the user cache ($HANDKSE_MODELS_DIR, else
    # $XDG_CACHE_HOME/handkse/models, else ~/.cache/handkse/models).
    models_dir: str = ""
    palm_model: str = "full"  # "full" or "lite" MediaPipe palm detector
    landmark_model: str = "full"  # "full" or "lite" MediaPipe hand-landmark model
    # Optional RTMPose-hand (SimCC) ONNX file for per-landmark confidences; "" = depth heuristic.
    keypoint_model: str = ""
    device: str = "auto"  # ONNX Runtime providers: auto (TensorRT > CUDA > CPU), cpu, cuda, tensorrt
    threads: int = 2  # intra-op threads of each ONNX Runtime session (CPU provider)

    # --- palm detection (192x192 SSD) ---
    palm_score_threshold: float = 0.5  # sigmoid score of a palm anchor
    palm_nms_iou: float = 0.3  # weighted NMS merges boxes above this IoU
    palm_roi_scale: float = 2.6  # hand ROI side = palm box long side x this
    palm_roi_shift: float = -0.5  # ROI centre shift along the hand axis, in palm-box heights

    # --- hand landmarks (224x224) and tracking ---
    max_hands: int = 2
    presence_threshold: float = 0.5  # accept a hand found from a palm detection
    tracking_presence_threshold: float = 0.5  # keep tracking a hand while presence >= this
    tracking: bool = True  # False = palm detection on every frame (no ROI from landmarks)
    # When the whole frame shows no palm, search again in the two end squares of a wide frame
    # (hands ~8-10 % of the width, e.g. at 1 m from a 1280x720 Kinect); costs 2 more palm runs
    # per frame only while no hand is found.
    palm_tiles: bool = True
    # While fewer than max_hands are tracked, look for new palms every this many frames
    # (1 = every frame, as MediaPipe does); with no hand tracked it runs on every frame.
    palm_interval_frames: int = 10
    tracking_roi_scale: float = 2.0  # ROI from the previous landmarks: bounding side x this
    tracking_roi_shift: float = -0.1  # in ROI heights, towards the fingers
    duplicate_iou: float = 0.5  # a palm overlapping a tracked hand's ROI this much is that hand
    mirrored_input: bool = False  # True for selfie-mirrored images (MediaPipe's handedness convention)

    # --- depth back-projection ---
    depth_window_px: int = 5  # odd side of the depth window around each landmark (depth pixels)
    depth_min_valid: int = 3  # fewer usable depth pixels than this in the window -> NaN
    depth_edge_jump_m: float = 0.02  # a pixel differing this much from a 4-neighbour is an edge
    depth_cluster_m: float = 0.015  # keep window pixels within this of the reference depth
    depth_min_m: float = 0.15  # readings outside [min, max] are holes
    depth_max_m: float = 5.0

    # --- visibility (heuristic without a keypoint model; see services/detector/visibility.py) ---
    occlusion_margin_m: float = 0.03  # measured depth this far in front of the model -> occluded
    background_margin_m: float = 0.08  # measured depth this far behind the model -> background
    margin_softness_m: float = 0.008  # width of the logistic transition at each margin
    image_margin_px: float = 2.0  # landmarks closer than this to the border fade out
    # RTMPose SimCC input (when keypoint_model is set)
    keypoint_bbox_padding: float = 1.25
    keypoint_simcc_split_ratio: float = 2.0

    def __post_init__(self) -> None:
        if self.device not in DEVICES:
            raise ValueError(f"device must be one of {list(DEVICES)}, got {self.device!r}")
        for name in ("palm_model", "landmark_model"):
            if getattr(self, name) not in VARIANTS:
                raise ValueError(f"{name} must be one of {list(VARIANTS)}, got "
                                 f"{getattr(self, name)!r}")
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0 (0 = ONNX Runtime default), got {self.threads}")
        if not 1 <= self.max_hands <= 2:
            raise ValueError(f"max_hands must be 1 or 2 (HandLandmarks carries at most 2), "
                             f"got {self.max_hands}")
        if self.palm_interval_frames < 1:
            raise ValueError(f"palm_interval_frames must be >= 1, got {self.palm_interval_frames}")
        unit = {"palm_score_threshold": self.palm_score_threshold,
                "palm_nms_iou": self.palm_nms_iou,
                "presence_threshold": self.presence_threshold,
                "tracking_presence_threshold": self.tracking_presence_threshold,
                "duplicate_iou": self.duplicate_iou}
        for name, value in unit.items():
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        positive = {"palm_roi_scale": self.palm_roi_scale,
                    "tracking_roi_scale": self.tracking_roi_scale,
                    "depth_edge_jump_m": self.depth_edge_jump_m,
                    "depth_cluster_m": self.depth_cluster_m,
                    "depth_max_m": self.depth_max_m,
                    "occlusion_margin_m": self.occlusion_margin_m,
                    "background_margin_m": self.background_margin_m,
                    "margin_softness_m": self.margin_softness_m,
                    "keypoint_bbox_padding": self.keypoint_bbox_padding,
                    "keypoint_simcc_split_ratio": self.keypoint_simcc_split_ratio}
        for name, value in positive.items():
            if not value > 0.0:
                raise ValueError(f"{name} must be > 0, got {value}")
        if self.depth_window_px < 1 or self.depth_window_px % 2 == 0:
            raise ValueError(f"depth_window_px must be a positive odd number, got "
                             f"{self.depth_window_px}")
        if not 1 <= self.depth_min_valid <= self.depth_window_px**2:
            raise ValueError(f"depth_min_valid must be in [1, depth_window_px^2], got "
                             f"{self.depth_min_valid}")
        if not 0.0 <= self.depth_min_m < self.depth_max_m:
            raise ValueError(f"need 0 <= depth_min_m < depth_max_m, got {self.depth_min_m}, "
                             f"{self.depth_max_m}")
        if self.image_margin_px < 0.0:
            raise ValueError(f"image_margin_px must be >= 0, got {self.image_margin_px}")


__all__ = ["DEVICES", "VARIANTS", "DetectorConfig"]
