"""Log handkse messages to a Rerun recording: the entity layout of ``handkse view``.

Imports ``rerun`` (the optional ``view`` extra); only the view command imports this module.
Every message is logged at its ``stamp_ns`` on the timestamp timeline ``stamp_ns``, so live
data, recordings and ``.rrd`` files line up on the capture clock.

Entities (3-D content in the messages' ``frame_id``, whose axes are the camera's: x right,
y down, z forward):

- ``world/camera`` pinhole of the colour camera (posed by ``T_world_camera`` when it moves),
  ``world/camera/image`` the colour image, ``world/camera/image/landmarks`` the 2-D landmarks;
- ``world/hand/detected`` the detector's 3-D landmarks, coloured by visibility, with bones;
- ``world/hand/tracked`` the tracker's landmark estimates, coloured by status (green used,
  red outlier, blue excluded, grey untracked);
- ``world/hand/body`` the hand body pose (transform with axes), ``world/hand/body_covariance``
  its position ellipsoid, ``world/hand/trail`` the recent origins;
- ``world/model/axis`` (line, revolute) or ``world/model/arrow`` (prismatic),
  ``world/model/cone`` the axis uncertainty, ``world/model/sweep`` the demonstrated arc or
  stroke, ``world/model/point_covariance`` where the revolute axis passes near the hand;
- ``robot/ee`` the end-effector pose, ``robot/target`` the commanded pose and ``robot/trail``,
  in the robot's base frame (a space of
  its own: the camera-to-base calibration is not on the bus);
- ``plots/type_probability/{rigid,prismatic,revolute,disconnected}``, ``plots/joint/q``,
  ``plots/robot/force_n`` and ``plots/robot/force_limit_n`` time series; ``log/model`` and
  ``log/errors`` text.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from services.common.protocol import (
    JOINT_TYPES,
    CameraIntrinsics,
    HandBody,
    HandLandmarks,
    KinematicModel,
    ProtocolError,
    RgbdFrame,
    RobotState,
)
from services.view import geometry as geo

TIMELINE = "stamp_ns"
CAMERA = "world/camera"
IMAGE = "world/camera/image"
IMAGE_LANDMARKS = "world/camera/image/landmarks"
DETECTED = "world/hand/detected"
TRACKED = "world/hand/tracked"
BODY = "world/hand/body"
BODY_COVARIANCE = "world/hand/body_covariance"
TRAIL = "world/hand/trail"
AXIS = "world/model/axis"
ARROW = "world/model/arrow"
CONE = "world/model/cone"
SWEEP = "world/model/sweep"
POINT_COVARIANCE = "world/model/point_covariance"
ROBOT_EE = "robot/ee"
ROBOT_TRAIL = "robot/trail"
ROBOT_TARGET = "robot/target"
PROBABILITY = "plots/type_probability"
JOINT_Q = "plots/joint/q"
FORCE = "plots/robot/force_n"
FORCE_LIMIT = "plots/robot/force_limit_n"
MODEL_LOG = "log/model"
ERROR_LOG = "log/errors"

DETECTED_CLASS, TRACKED_CLASS = 0, 1
_MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}


@dataclass(frozen=True)
class SceneOptions:
    """What to draw: ``trail_length`` body poses kept, ``n_sigma`` of every uncertainty,
    ``force_limit_n`` drawn beside the measured force, ``images`` whether camera images are
    logged (they dominate an ``.rrd``'s size), ``axis_length_m`` of the drawn joint axis."""

    trail_length: int = 300
    n_sigma: float = geo.DEFAULT_N_SIGMA
    force_limit_n: float = 70.0
    images: bool = True
    axis_length_m: float = 0.3


def blueprint() -> rrb.Blueprint:
    """The default layout: the 3-D scene, the camera image, the time series and the logs."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="world", name="scene"),
                rrb.Spatial3DView(origin="robot", name="robot (base frame)"),
                row_shares=[4, 1],
            ),
            rrb.Vertical(
                rrb.Spatial2DView(origin=IMAGE, name="camera"),
                rrb.TimeSeriesView(origin=PROBABILITY, name="type probability"),
                rrb.TimeSeriesView(origin="plots/robot", name="robot force [N]"),
                rrb.TextLogView(origin="log", name="log"),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline=TIMELINE),
        collapse_panels=True,
    )


@dataclass
class SceneCounters:
    """Messages logged per kind, and rejected payloads by reason."""

    logged: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)

    @property
    def total(self) -> int:
        return sum(self.logged.values())


class RerunScene:
    """Turns bus payloads into Rerun entities on one recording (call from one thread)."""

    def __init__(self, rec: rr.RecordingStream, options: SceneOptions | None = None) -> None:
        self.rec = rec
        self.options = options or SceneOptions()
        self.counters = SceneCounters()
        self._intrinsics: CameraIntrinsics | None = None
        self._T_world_camera: np.ndarray | None = None
        self._trail: deque[np.ndarray] = deque(maxlen=self.options.trail_length)
        self._robot_trail: deque[np.ndarray] = deque(maxlen=self.options.trail_length)
        self._range = geo.JointRange()
        self._model_type: str | None = None
        self._drawn: str | None = None  # the joint type whose entities are on screen
        self._robot_mode: str | None = None
        self._log_static()

    # --- dispatch ---

    def handle(self, key: str, payload: bytes) -> bool:
        """Decode and log one payload by its key; False for keys the view does not draw.

        A payload that does not decode is counted by reason and noted in ``log/errors``, and so is
        one that decodes but cannot be drawn (``undrawable``).
        """
        suffix = key.split("/", 2)[-1] if key.count("/") >= 2 else key
        decode = _HANDLERS.get(suffix)
        if decode is None:
            return False
        cls, method = decode
        try:
            message = cls.from_msgpack(payload)
        except ProtocolError as exc:
            self.counters.rejected[exc.reason] = self.counters.rejected.get(exc.reason, 0) + 1
            self.rec.log(ERROR_LOG, rr.TextLog(f"{key}: {exc}", level=rr.TextLogLevel.WARN))
            return True
        try:
            method(self, message)
        except ValueError as exc:  # valid on the wire, but nothing drawable (e.g. a huge value)
            self.counters.rejected["undrawable"] = self.counters.rejected.get("undrawable", 0) + 1
            self.rec.log(ERROR_LOG, rr.TextLog(f"{key}: cannot draw: {exc}",
                                               level=rr.TextLogLevel.WARN))
            return True
        self.counters.logged[suffix] = self.counters.logged.get(suffix, 0) + 1
        return True

    def _at(self, stamp_ns: int) -> None:
        self.rec.set_time(TIMELINE, timestamp=np.datetime64(int(stamp_ns), "ns"))

    def _log_static(self) -> None:
        log = self.rec.log
        log("world", rr.ViewCoordinates.RDF, static=True)
        log("robot", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        bones = list(geo.HAND_BONES)
        log("world", rr.AnnotationContext([
            rr.ClassDescription(info=rr.AnnotationInfo(id=DETECTED_CLASS),
                                keypoint_connections=bones),
            rr.ClassDescription(info=rr.AnnotationInfo(id=TRACKED_CLASS),
                                keypoint_connections=bones),
        ]), static=True)
        log(IMAGE_LANDMARKS, rr.AnnotationContext([
            rr.ClassDescription(info=rr.AnnotationInfo(id=DETECTED_CLASS),
                                keypoint_connections=bones)]), static=True)
        for name in JOINT_TYPES:
            log(f"{PROBABILITY}/{name}", rr.SeriesLines(colors=[geo.TYPE_COLORS[name]], names=name),
                static=True)
        log(JOINT_Q, rr.SeriesLines(names="q (rad or m)"), static=True)
        log(FORCE, rr.SeriesLines(colors=[[40, 120, 255]], names="measured |f|"), static=True)
        log(FORCE_LIMIT, rr.SeriesLines(colors=[[235, 50, 40]], names="limit", widths=2.0),
            static=True)

    # --- messages ---

    def frame(self, msg: RgbdFrame) -> None:
        self._at(msg.stamp_ns)
        k = msg.intrinsics
        self._intrinsics = k
        self._T_world_camera = msg.T_world_camera
        if msg.T_world_camera is not None:
            t, q = geo.pose_translation_quat(msg.T_world_camera)
            self.rec.log(CAMERA, rr.Transform3D(translation=t, quaternion=q))
        self.rec.log(IMAGE, rr.Pinhole(focal_length=[k.fx, k.fy], principal_point=[k.cx, k.cy],
                                       width=k.width, height=k.height,
                                       image_plane_distance=0.1))
        if not self.options.images:
            return
        color = msg.color
        if color.encoding in _MEDIA_TYPES:
            self.rec.log(IMAGE, rr.EncodedImage(contents=color.data,
                                                media_type=_MEDIA_TYPES[color.encoding]))
        else:  # bgr8
            pixels = np.frombuffer(color.data, np.uint8).reshape(color.height, color.width, 3)
            self.rec.log(IMAGE, rr.Image(pixels, color_model="BGR"))

    def landmarks(self, msg: HandLandmarks) -> None:
        self._at(msg.stamp_ns)
        if not msg.hands:
            self.rec.log(DETECTED, rr.Clear(recursive=False))
            self.rec.log(IMAGE_LANDMARKS, rr.Clear(recursive=False))
            return
        # Bones join keypoint ids, which two hands would share: bones for a single hand only.
        single = len(msg.hands) == 1
        hands = [geo.detected_landmarks(h) for h in msg.hands]
        self.rec.log(DETECTED, rr.Points3D(
            np.vstack([h.points for h in hands]), colors=np.vstack([h.colors for h in hands]),
            radii=0.005, class_ids=DETECTED_CLASS, keypoint_ids=hands[0].ids if single else None))
        pixels, colors, ids = [], [], []
        for hand in msg.hands:
            uv = geo.hand_pixels(hand, self._intrinsics, msg.T_world_camera)
            if uv is None:
                continue
            keep = np.isfinite(uv).all(axis=1)
            pixels.append(uv[keep])
            colors.append(geo.visibility_colors(hand.visibility)[keep])
            ids.append(np.flatnonzero(keep))
        if pixels:
            self.rec.log(IMAGE_LANDMARKS, rr.Points2D(
                np.vstack(pixels), colors=np.vstack(colors), radii=3.0, class_ids=DETECTED_CLASS,
                keypoint_ids=ids[0] if single else None))

    def body(self, msg: HandBody) -> None:
        self._at(msg.stamp_ns)
        lm = geo.tracked_landmarks(msg.landmarks)
        self.rec.log(TRACKED, rr.Points3D(lm.points, colors=lm.colors, radii=0.004,
                                          class_ids=TRACKED_CLASS, keypoint_ids=lm.ids))
        if not msg.initialized:
            return
        t, q = geo.pose_translation_quat(msg.pose)
        self.rec.log(BODY, rr.Transform3D(translation=t, quaternion=q),
                     rr.TransformAxes3D(axis_length=0.05))
        e = geo.body_ellipsoid(msg.pose, msg.covariance, self.options.n_sigma)
        self.rec.log(BODY_COVARIANCE, rr.Ellipsoids3D(
            centers=[e.center], half_sizes=[e.half_sizes], quaternions=[e.quat_xyzw],
            colors=[[255, 255, 255, 110]], fill_mode="solid"))
        self._trail.append(t)
        if len(self._trail) >= 2:
            self.rec.log(TRAIL, rr.LineStrips3D([np.array(self._trail)],
                                                colors=[[230, 230, 230]], radii=0.001))

    def model(self, msg: KinematicModel) -> None:
        self._at(msg.stamp_ns)
        for name in JOINT_TYPES:
            self.rec.log(f"{PROBABILITY}/{name}", rr.Scalars(float(msg.probabilities[name])))
        q_range = self._range.update(msg)
        q = geo.joint_value(msg)
        if q is not None:
            self.rec.log(JOINT_Q, rr.Scalars(q))
        if msg.type != self._model_type:
            self._model_type = msg.type
            probability = msg.probabilities.get(msg.type, float("nan"))
            self.rec.log(MODEL_LOG, rr.TextLog(
                f"model {msg.type} (p {probability:.2f}) after {msg.updates} updates"))
        g = geo.joint_geometry(msg, q_range, self.options.n_sigma, self.options.axis_length_m)
        drawn = None if g is None else g.type
        if drawn != self._drawn:  # clear what the previous type drew, once
            for path in (AXIS, ARROW, CONE, SWEEP, POINT_COVARIANCE):
                self.rec.log(path, rr.Clear(recursive=False))
            self._drawn = drawn
        if g is None:
            return
        color = [*geo.TYPE_COLORS[g.type], 255]
        if g.type == "revolute":
            self.rec.log(AXIS, rr.LineStrips3D([g.segment], colors=[color], radii=0.003,
                                               labels=["revolute axis"]))
            assert g.point_ellipsoid is not None
            e = g.point_ellipsoid
            self.rec.log(POINT_COVARIANCE, rr.Ellipsoids3D(
                centers=[e.center], half_sizes=[e.half_sizes], quaternions=[e.quat_xyzw],
                colors=[[*geo.TYPE_COLORS[g.type], 90]], fill_mode="solid"))
        else:
            self.rec.log(ARROW, rr.Arrows3D(origins=[g.segment[0]],
                                            vectors=[g.segment[1] - g.segment[0]],
                                            colors=[color], radii=0.003,
                                            labels=["prismatic axis"]))
        self.rec.log(CONE, rr.LineStrips3D(g.cone, colors=[[*geo.TYPE_COLORS[g.type], 120]],
                                           radii=0.0008))
        self.rec.log(SWEEP, rr.LineStrips3D([g.sweep], colors=[[255, 255, 255]], radii=0.002))

    def robot(self, msg: RobotState) -> None:
        self._at(msg.stamp_ns)
        t, q = geo.pose_translation_quat(msg.T_base_ee)
        self.rec.log(ROBOT_EE, rr.Transform3D(translation=t, quaternion=q),
                     rr.TransformAxes3D(axis_length=0.08))
        self._robot_trail.append(t)
        if len(self._robot_trail) >= 2:
            self.rec.log(ROBOT_TRAIL, rr.LineStrips3D([np.array(self._robot_trail)],
                                                      colors=[[120, 200, 255]], radii=0.001))
        if msg.T_base_target is not None:
            tt, qt = geo.pose_translation_quat(msg.T_base_target)
            self.rec.log(ROBOT_TARGET, rr.Transform3D(translation=tt, quaternion=qt),
                         rr.TransformAxes3D(axis_length=0.05))
        self.rec.log(FORCE, rr.Scalars(float(np.linalg.norm(msg.wrench[:3]))))
        self.rec.log(FORCE_LIMIT, rr.Scalars(self.options.force_limit_n))
        if msg.mode != self._robot_mode:
            self._robot_mode = msg.mode
            level = rr.TextLogLevel.ERROR if msg.mode == "fault" else rr.TextLogLevel.INFO
            self.rec.log(MODEL_LOG, rr.TextLog(f"robot {msg.mode} ({msg.backend})", level=level))


_HANDLERS = {
    "camera/rgbd": (RgbdFrame, RerunScene.frame),
    "hand/landmarks": (HandLandmarks, RerunScene.landmarks),
    "hand/body": (HandBody, RerunScene.body),
    "kinematics/model": (KinematicModel, RerunScene.model),
    "robot/state": (RobotState, RerunScene.robot),
}
