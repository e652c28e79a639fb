"""handkse messages as Foxglove messages (foxglove-sdk's schemas, protobuf-encoded), so that
Foxglove shows a recording without knowing the handkse protocol.

Imports ``foxglove`` (the optional ``view`` extra); only ``handkse export`` and
``handkse record --foxglove`` import this module. The raw msgpack channels stay as they are;
these channels are added beside them, all under ``/handkse/{rig}/foxglove/``:

- ``tf`` (``foxglove.FrameTransform``): the hand body (``{frame_id}`` -> ``hand``), a moving
  camera (``world`` -> ``camera``), the robot's end-effector (``{frame_id}`` -> ``ee``);
- ``hand/trail`` (``foxglove.PosesInFrame``): the last hand body poses;
- ``hand/landmarks`` (``foxglove.SceneUpdate``, entity ``detected``): detected landmarks as
  spheres coloured by visibility, and the bones;
- ``hand/body`` (``foxglove.SceneUpdate``, entity ``tracked``): tracked landmarks coloured by
  status, then the hand origin's position ellipsoid (the last sphere);
- ``model`` (``foxglove.SceneUpdate``, entity ``joint``): the axis as a line (revolute) or an
  arrow (prismatic), then the uncertainty cone's lines, then the swept range, and a label;
- ``camera/image`` (``foxglove.CompressedImage`` for jpeg/png, ``foxglove.RawImage`` for bgr8),
  ``camera/calibration`` (``foxglove.CameraCalibration``), ``camera/landmarks``
  (``foxglove.ImageAnnotations``): the colour image, its intrinsics and the 2-D landmarks.

Every message is stamped with its ``stamp_ns``; geometry is that of :mod:`services.view.geometry`.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

import foxglove.messages as fm
import numpy as np

from services.common.protocol import (
    HandBody,
    HandLandmarks,
    KinematicModel,
    ProtocolError,
    RgbdFrame,
    RobotState,
)
from services.common.recording import EncodedSchema, McapRecorder
from services.view import geometry as geo

TOPICS = ("tf", "hand/trail", "hand/landmarks", "hand/body", "model", "camera/image",
          "camera/calibration", "camera/landmarks")


def topic_root(key: str) -> str:
    """``/handkse/{rig}/foxglove`` for a ``handkse/{rig}/...`` key."""
    prefix, rig = key.split("/")[:2]
    return f"/{prefix}/{rig}/foxglove"


def _stamp(stamp_ns: int) -> fm.Timestamp:
    return fm.Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)


def _color(rgba: Sequence[float]) -> fm.Color:
    r, g, b, a = (float(c) for c in rgba)
    return fm.Color(r=r, g=g, b=b, a=a)


def _rgba8(c: np.ndarray) -> fm.Color:
    return _color(np.asarray(c, float) / 255.0)


def _vec(v: np.ndarray) -> fm.Vector3:
    return fm.Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _point(v: np.ndarray) -> fm.Point3:
    return fm.Point3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(q: np.ndarray) -> fm.Quaternion:
    return fm.Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _pose(position: np.ndarray, quat_xyzw: np.ndarray | None = None) -> fm.Pose:
    q = np.array([0.0, 0.0, 0.0, 1.0]) if quat_xyzw is None else quat_xyzw
    return fm.Pose(position=_vec(position), orientation=_quat(q))


_IDENTITY = np.zeros(3)


def _line(points: np.ndarray, color: fm.Color, thickness: float,
          kind: Any = fm.LinePrimitiveLineType.LineStrip) -> fm.LinePrimitive:
    return fm.LinePrimitive(type=kind, pose=_pose(_IDENTITY), thickness=thickness,
                            scale_invariant=True, points=[_point(p) for p in points], color=color)


def _spheres(points: np.ndarray, colors: np.ndarray, diameter: float) -> list[fm.SpherePrimitive]:
    size = fm.Vector3(x=diameter, y=diameter, z=diameter)
    return [fm.SpherePrimitive(pose=_pose(p), size=size, color=_rgba8(c))
            for p, c in zip(points, colors, strict=True)]


def _bones(points: np.ndarray, ids: np.ndarray, color: fm.Color) -> fm.LinePrimitive:
    """The hand skeleton between landmarks that have a position, as a line list."""
    where = {int(i): k for k, i in enumerate(ids)}
    pairs = [(points[where[a]], points[where[b]]) for a, b in geo.HAND_BONES
             if a in where and b in where]
    flat = np.array([p for pair in pairs for p in pair]) if pairs else np.zeros((0, 3))
    return _line(flat, color, 1.5, fm.LinePrimitiveLineType.LineList)


def _entity(msg: Any, entity_id: str, **primitives: Any) -> fm.SceneEntity:
    return fm.SceneEntity(timestamp=_stamp(msg.stamp_ns), frame_id=msg.frame_id, id=entity_id,
                          frame_locked=False, **primitives)


def _rotation_x_to(u: np.ndarray) -> np.ndarray:
    """Quaternion xyzw of a rotation taking +x to the unit ``u`` (Foxglove arrows point along x)."""
    e1, e2 = geo.perpendicular_basis(u)
    return geo.quat_xyzw_from_matrix(np.column_stack([u, e1, e2]))  # (u, e1, e2) right-handed


class FoxgloveChannels:
    """Translates bus payloads into Foxglove messages; keeps the trail and the demonstrated
    joint range between calls (thread-safe: recorder callbacks arrive on several threads)."""

    def __init__(self, trail_length: int = 300, n_sigma: float = geo.DEFAULT_N_SIGMA,
                 axis_length_m: float = 0.3) -> None:
        self.n_sigma = n_sigma
        self.axis_length_m = axis_length_m
        self._trails: dict[str, deque[fm.Pose]] = {}
        self._trail_length = trail_length
        self._ranges: dict[str, geo.JointRange] = {}
        self._intrinsics: dict[str, Any] = {}
        self._lock = threading.Lock()
        self.written = 0
        self.rejected: dict[str, int] = {}

    def translate(self, key: str, payload: bytes) -> list[tuple[str, Any, int]]:
        """``[(topic, foxglove message, stamp_ns), ...]`` for one payload; [] for keys not drawn
        and for payloads that do not decode (counted in ``rejected`` by reason)."""
        suffix = key.split("/", 2)[-1] if key.count("/") >= 2 else ""
        handler = _HANDLERS.get(suffix)
        if handler is None:
            return []
        cls, method = handler
        try:
            msg = cls.from_msgpack(payload)
        except ProtocolError as exc:
            self.rejected[exc.reason] = self.rejected.get(exc.reason, 0) + 1
            return []
        root = topic_root(key)
        with self._lock:
            return [(f"{root}/{name}", m, msg.stamp_ns) for name, m in method(self, msg, root)]

    def write(self, recorder: McapRecorder, key: str, payload: bytes, log_time_ns: int) -> int:
        """Translate and append to ``recorder``; returns how many Foxglove messages were written."""
        out = self.translate(key, payload)
        for topic, message, stamp_ns in out:
            schema = message.get_schema()
            recorder.write_encoded(
                topic, EncodedSchema(name=schema.name, encoding=schema.encoding,
                                     data=bytes(schema.data), message_encoding="protobuf"),
                message.encode(), log_time_ns=log_time_ns, publish_time_ns=stamp_ns)
        self.written += len(out)
        return len(out)

    # --- messages ---

    def _frame(self, msg: RgbdFrame, root: str) -> list[tuple[str, Any]]:
        k = msg.intrinsics
        self._intrinsics[root] = k
        stamp = _stamp(msg.stamp_ns)
        out: list[tuple[str, Any]] = [("camera/calibration", fm.CameraCalibration(
            timestamp=stamp, frame_id="camera", width=k.width, height=k.height,
            distortion_model="", D=[], K=[k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
            R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            P=[k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0]))]
        c = msg.color
        if c.encoding in ("jpeg", "png"):
            out.append(("camera/image", fm.CompressedImage(timestamp=stamp, frame_id="camera",
                                                           data=c.data, format=c.encoding)))
        else:
            out.append(("camera/image", fm.RawImage(timestamp=stamp, frame_id="camera",
                                                    width=c.width, height=c.height,
                                                    encoding="bgr8", step=3 * c.width,
                                                    data=c.data)))
        if msg.T_world_camera is not None:
            t, q = geo.pose_translation_quat(msg.T_world_camera)
            out.append(("tf", fm.FrameTransform(timestamp=stamp, parent_frame_id="world",
                                                child_frame_id="camera", translation=_vec(t),
                                                rotation=_quat(q))))
        return out

    def _landmarks(self, msg: HandLandmarks, root: str) -> list[tuple[str, Any]]:
        spheres: list[fm.SpherePrimitive] = []
        lines: list[fm.LinePrimitive] = []
        annotations: list[fm.PointsAnnotation] = []
        for hand in msg.hands:
            lm = geo.detected_landmarks(hand)
            spheres += _spheres(lm.points, lm.colors, 0.01)
            lines.append(_bones(lm.points, lm.ids, _color((0.85, 0.25, 0.25, 1.0))))
            uv = geo.hand_pixels(hand, self._intrinsics.get(root), msg.T_world_camera)
            if uv is not None:
                keep = np.isfinite(uv).all(axis=1)
                annotations.append(fm.PointsAnnotation(
                    timestamp=_stamp(msg.stamp_ns), type=fm.PointsAnnotationType.Points,
                    points=[fm.Point2(x=float(u), y=float(v)) for u, v in uv[keep]],
                    outline_color=_color((1.0, 0.85, 0.15, 1.0)),
                    outline_colors=[_rgba8(c) for c in geo.visibility_colors(hand.visibility)[keep]],
                    fill_color=_color((1.0, 0.85, 0.15, 1.0)), thickness=4.0))
        out: list[tuple[str, Any]] = [("hand/landmarks", fm.SceneUpdate(
            entities=[_entity(msg, "detected", spheres=spheres, lines=lines)]))]
        if annotations:
            out.append(("camera/landmarks", fm.ImageAnnotations(points=annotations)))
        return out

    def _body(self, msg: HandBody, root: str) -> list[tuple[str, Any]]:
        lm = geo.tracked_landmarks(msg.landmarks)
        spheres = _spheres(lm.points, lm.colors, 0.008)
        out: list[tuple[str, Any]] = []
        if msg.initialized:
            t, q = geo.pose_translation_quat(msg.pose)
            e = geo.body_ellipsoid(msg.pose, msg.covariance, self.n_sigma)
            spheres.append(fm.SpherePrimitive(pose=_pose(e.center, e.quat_xyzw),
                                              size=_vec(2.0 * e.half_sizes),
                                              color=_color((1.0, 1.0, 1.0, 0.35))))
            out.append(("tf", fm.FrameTransform(timestamp=_stamp(msg.stamp_ns),
                                                parent_frame_id=msg.frame_id,
                                                child_frame_id="hand", translation=_vec(t),
                                                rotation=_quat(q))))
            trail = self._trails.setdefault(root, deque(maxlen=self._trail_length))
            trail.append(_pose(t, q))
            out.append(("hand/trail", fm.PosesInFrame(timestamp=_stamp(msg.stamp_ns),
                                                      frame_id=msg.frame_id, poses=list(trail))))
        out.insert(0, ("hand/body", fm.SceneUpdate(
            entities=[_entity(msg, "tracked", spheres=spheres)])))
        return out

    def _model(self, msg: KinematicModel, root: str) -> list[tuple[str, Any]]:
        q_range = self._ranges.setdefault(root, geo.JointRange()).update(msg)
        g = geo.joint_geometry(msg, q_range, self.n_sigma, self.axis_length_m)
        rgb = tuple(c / 255.0 for c in geo.TYPE_COLORS[msg.type])
        probability = msg.probabilities.get(msg.type)
        text = msg.type if probability is None else f"{msg.type} p={probability:.2f}"
        label_at = np.asarray(msg.reference_pose, float)[:3, 3]
        lines: list[fm.LinePrimitive] = []
        arrows: list[fm.ArrowPrimitive] = []
        if g is not None:
            color = _color((*rgb, 1.0))
            if g.type == "revolute":
                lines.append(_line(g.segment, color, 3.0))
            else:
                length = float(np.linalg.norm(g.segment[1] - g.segment[0]))
                arrows.append(fm.ArrowPrimitive(
                    pose=_pose(g.segment[0], _rotation_x_to(g.axis)), shaft_length=0.8 * length,
                    shaft_diameter=0.005, head_length=0.2 * length, head_diameter=0.015,
                    color=color))
            lines += [_line(strip, _color((*rgb, 0.5)), 1.0) for strip in g.cone]
            lines.append(_line(g.sweep, _color((1.0, 1.0, 1.0, 1.0)), 2.0))
            label_at = g.origin
        texts = [fm.TextPrimitive(pose=_pose(label_at + np.array([0.0, -0.03, 0.0])),
                                  billboard=True, font_size=14.0, scale_invariant=True,
                                  color=_color((*rgb, 1.0)), text=text)]
        return [("model", fm.SceneUpdate(entities=[_entity(msg, "joint", lines=lines,
                                                           arrows=arrows, texts=texts)]))]

    def _robot(self, msg: RobotState, root: str) -> list[tuple[str, Any]]:
        t, q = geo.pose_translation_quat(msg.T_base_ee)
        return [("tf", fm.FrameTransform(timestamp=_stamp(msg.stamp_ns),
                                         parent_frame_id=msg.frame_id, child_frame_id="ee",
                                         translation=_vec(t), rotation=_quat(q)))]


_HANDLERS = {
    "camera/rgbd": (RgbdFrame, FoxgloveChannels._frame),
    "hand/landmarks": (HandLandmarks, FoxgloveChannels._landmarks),
    "hand/body": (HandBody, FoxgloveChannels._body),
    "kinematics/model": (KinematicModel, FoxgloveChannels._model),
    "robot/state": (RobotState, FoxgloveChannels._robot),
}
