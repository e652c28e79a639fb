"""A true object, seen by the camera, placed and grasped in simulation; articulated along a model.

The synthetic generator gives the true object in the camera frame (an object calibration file
does too, :func:`object_from_file`); the estimate is in the camera frame as well.
:func:`grasp_scene` places that true object in the simulated robot's workspace through a
hand-eye calibration ``T_base_camera`` and grasps it. Two users, one placement:

- the robot bridge service (``--sim-object synthetic:OBJECT``, :func:`place_configured_object`):
  through its own ``T_base_camera``, the one it maps models with;
- :func:`articulate_in_simulation` (robot trials): through ``T_base_camera`` (default: the one
  that puts the robot's grasp on the object exactly at the nominal grasp pose, so every object
  is reachable), then the bridge exactly as the service runs it: model checks, plan from the
  estimated model moved into the base frame with the same ``T_base_camera``, execution under the
  safety limits.

Estimation errors therefore reach the robot exactly as they are in the camera.

Robot grasps (``T_cam_grasp``): the gripper approaches into the mounting surface (TCP z = minus
the object's outward normal, object frame y). Revolute objects are held on the lever: the key on
its axis (the key's bow), the window lock 6 cm from the axis, any other object where the human
held it; prismatic objects where the human held them, TCP y along the slide.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from services.common.protocol import ArticulateRequest, ArticulateResult, KinematicModel
from services.common.se3 import se3_inverse
from services.robot_bridge.config import RobotBridgeConfig, SimObjectSource, sim_object_source
from services.robot_bridge.executor import Bridge, Execution
from services.robot_bridge.mujoco_backend import (
    WINDOW_LOCK_LEVER_M,
    MujocoBackend,
    forward_kinematics,
    nominal_grasp_pose,
)
from services.robot_bridge.panda_scene import Q_GRASP_RAD, Q_MAX_RAD, Q_MIN_RAD, ObjectSpec
from services.robot_bridge.refinement import RefinementConfig
from services.robot_bridge.trajectory import (
    ArticulationPlan,
    default_duration,
    flipped_grasp_q7,
)

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

# Robot grasp distance from the revolute axis per object (None: where the human held it) [m].
ROBOT_LEVER_M: dict[str, float | None] = {"key": 0.0, "window_lock": WINDOW_LOCK_LEVER_M}
# Joint dynamics per simulated object (armature kg m^2 or kg, damping, friction); see
# mujoco_backend.preset_object.
_DYNAMICS: dict[str, dict[str, float]] = {
    "key": {"armature": 1e-3},
    "window_lock": {"armature": 2e-3},
    "bolt": {"armature": 0.2, "damping": 2.0, "frictionloss": 1.0},
}


@dataclass(frozen=True)
class ObjectInCamera:
    """The true articulated object in the camera frame (metres, radians).

    ``axis`` unit, oriented so that positive motion is the direction of the human's opening
    stroke; ``point`` on the axis (revolute) or the grasp at the first frame (prismatic);
    ``grasp`` where the human held the part at the first frame; ``normal`` the mounting
    surface's outward normal; ``demonstrated`` the range of the opening stroke (rad or m).
    """

    name: str
    joint_type: str
    axis: Array
    point: Array
    grasp: Array
    normal: Array
    demonstrated: float

    def chord_m(self) -> float:
        """Straight-line distance the human's grasp point travelled over the opening stroke."""
        if self.joint_type == "prismatic":
            return self.demonstrated
        d = self.grasp - self.point
        r = float(np.linalg.norm(d - (d @ self.axis) * self.axis))
        return 2.0 * r * math.sin(min(self.demonstrated, math.pi) / 2.0)


@dataclass(frozen=True)
class SimArticulation:
    """Result of :func:`articulate_in_simulation` plus what produced it."""

    result: ArticulateResult
    execution: Execution | None
    T_base_camera: Array
    object_base: ObjectSpec | None   # the true object in the base frame
    amount: float
    plan: ArticulationPlan | None     # the executed plan (estimated joint in the base frame)


def object_in_camera(demo: object) -> ObjectInCamera:
    """The true object of a synthetic ``Demonstration`` (``services.synthetic.generator``)."""
    truth = demo.truth  # type: ignore[attr-defined]
    joint = truth.joint
    q = np.asarray(joint.q, float)
    extreme = float(q[int(np.argmax(np.abs(q)))])  # the opening stroke (a return may follow)
    sign = 1.0 if extreme >= 0.0 else -1.0
    axis = sign * np.asarray(joint.axis, float)
    return ObjectInCamera(name=str(demo.object_name),  # type: ignore[attr-defined]
                          joint_type=str(joint.type), axis=axis,
                          point=np.asarray(joint.point, float),
                          grasp=np.asarray(truth.grasp_points[0], float),
                          normal=np.asarray(truth.T_camera_object[:3, 1], float),
                          demonstrated=abs(extreme))


OBJECT_FILE_KEYS = ("name", "type", "axis", "point", "grasp", "normal", "travel")
DEFAULT_TRAVEL = {"revolute": math.pi, "prismatic": 0.035}  # rad, m


def object_from_file(path: str | Path) -> ObjectInCamera:
    """An object calibration file (TOML; docs/robot_bridge.md#simulated-object): the
    articulated object in the camera frame, metres.

    Keys: ``type`` ("revolute" or "prismatic"), ``axis`` (positive: the way to articulate),
    ``point`` (on a revolute axis; for a prismatic joint any point of the sliding line),
    ``grasp`` (where the part is held), ``normal`` (the mounting surface's outward normal: the
    gripper approaches against it), optional ``name`` (a preset's name gives its dynamics and
    robot grasp; default "object") and ``travel`` (the joint's range from the start, rad or m;
    default 180 deg / 35 mm). Raises ``ValueError`` naming the file and the key.
    """
    where = f"object calibration file {path}"
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise ValueError(f"{where} does not exist") from None
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{where} cannot be read: {exc}") from None
    unknown = sorted(set(doc) - set(OBJECT_FILE_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {', '.join(unknown)}; known: "
                         f"{', '.join(OBJECT_FILE_KEYS)}")
    joint_type = doc.get("type")
    if joint_type not in DEFAULT_TRAVEL:
        raise ValueError(f"{where}: type must be \"revolute\" or \"prismatic\", got "
                         f"{joint_type!r}")

    def vector(key: str, unit: bool = False) -> Array:
        try:
            v = np.asarray(doc[key], float)
        except KeyError:
            raise ValueError(f"{where}: {key} is missing (3 numbers, metres)") from None
        except (TypeError, ValueError):
            raise ValueError(f"{where}: {key} must be 3 numbers, got {doc[key]!r}") from None
        if v.shape != (3,) or not np.isfinite(v).all():
            raise ValueError(f"{where}: {key} must be 3 finite numbers, got {doc[key]!r}")
        if unit:
            n = float(np.linalg.norm(v))
            if n < 1e-9:
                raise ValueError(f"{where}: {key} must not be zero")
            v = v / n
        return v

    travel = doc.get("travel", DEFAULT_TRAVEL[joint_type])
    if isinstance(travel, bool) or not isinstance(travel, (int, float)) or not travel > 0:
        raise ValueError(f"{where}: travel must be a positive number, got {travel!r}")
    name = doc.get("name", "object")
    if not isinstance(name, str) or not name:
        raise ValueError(f"{where}: name must be a non-empty string, got {name!r}")
    return ObjectInCamera(name=name, joint_type=joint_type, axis=vector("axis", unit=True),
                          point=vector("point"), grasp=vector("grasp"),
                          normal=vector("normal", unit=True), demonstrated=float(travel))


def object_from_source(source: SimObjectSource) -> ObjectInCamera:
    """The camera-frame object of a ``synthetic`` or ``file`` :class:`SimObjectSource`."""
    if source.kind == "synthetic":
        from services.synthetic.generator import generate

        return object_in_camera(generate(source.name, source.participant, source.seed,
                                         variant=source.variant))
    if source.kind == "file":
        return object_from_file(source.path)
    raise ValueError(f"a {source.kind} object has no camera-frame description")


def place_configured_object(config: RobotBridgeConfig
                            ) -> tuple[RobotBridgeConfig, GraspScene, str]:
    """The object of ``config.sim_object`` (synthetic or file) grasped in simulation, the config
    the bridge must run under, and a sentence saying where the object is.

    The object is in the camera frame and goes through ``T_base_camera``, the calibration the
    bridge maps camera-frame models with, so the simulated object is where the camera saw it.
    An identity ``T_base_camera`` (the default: not calibrated) is replaced by
    :func:`default_hand_eye`, the calibration that puts the robot's grasp on the object at the
    nominal grasp pose, and the returned config carries it. Raises ``ValueError`` when the object
    cannot be read or grasped.
    """
    source = sim_object_source(config.sim_object)
    obj = object_from_source(source)
    T_bc = config.base_T_camera()
    chosen = bool(np.allclose(T_bc, np.eye(4)))
    if chosen:
        T_bc = default_hand_eye(obj)
        config = replace(config, T_base_camera=tuple(float(v) for v in T_bc.ravel()))
    try:
        scene = grasp_scene(obj, T_bc, config)
    except ValueError as exc:
        raise ValueError(f"the simulated arm cannot grasp {source} through "
                         f"robot_bridge.T_base_camera: {exc}") from None
    p = scene.obj.T_base_handle[:3, 3]
    how = ("T_base_camera chosen to put the grasp at the nominal grasp pose" if chosen
           else "through the configured T_base_camera")
    where = (f"{obj.name} ({obj.joint_type}) from {source}, grasped at "
             f"[{p[0]:+.3f}, {p[1]:+.3f}, {p[2]:+.3f}] m in the base frame, {how}")
    return config, scene, where


def _unit(v: Array) -> Array:
    return v / float(np.linalg.norm(v))


def grasp_in_camera(obj: ObjectInCamera) -> Array:
    """``T_camera_grasp``: the robot's TCP pose on the object at q = 0 (module docstring)."""
    z = _unit(-obj.normal)
    if obj.joint_type == "prismatic":
        y = obj.axis - (obj.axis @ z) * z
        if np.linalg.norm(y) < 1e-6:
            y = np.cross(z, [1.0, 0.0, 0.0])
        y = _unit(y)
        x = np.cross(y, z)
        origin = obj.grasp
    else:
        a = obj.axis
        d = obj.grasp - obj.point
        axial = float(d @ a)
        radial = d - axial * a
        r_human = float(np.linalg.norm(radial))
        u = radial / r_human if r_human > 1e-6 else _unit(np.cross(a, [1.0, 0.0, 0.0]))
        lever = ROBOT_LEVER_M.get(obj.name)
        r = r_human if lever is None else lever
        origin = obj.point + axial * a + r * u
        if abs(float(a @ z)) > 0.7:      # axis along the approach: TCP x along the lever
            x = _unit(u - (u @ z) * z)
            y = np.cross(z, x)
        else:                            # axis across the approach: TCP y along the axis
            y = _unit(a - (a @ z) * z)
            x = np.cross(y, z)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, origin
    return T


def default_hand_eye(obj: ObjectInCamera) -> Array:
    """``T_base_camera`` that puts the robot's grasp on ``obj`` at the nominal grasp pose."""
    return nominal_grasp_pose() @ se3_inverse(grasp_in_camera(obj))


def sim_object(obj: ObjectInCamera, T_base_camera: Array, T_base_handle: Array) -> ObjectSpec:
    """The true object in the base frame, grasped at ``T_base_handle``."""
    R, t = T_base_camera[:3, :3], T_base_camera[:3, 3]
    axis = _unit(R @ obj.axis)
    point = R @ obj.point + t
    rng = None
    if obj.joint_type == "prismatic":
        stroke = max(obj.demonstrated, 0.01)
        rng = (-0.002, stroke + 0.002)
    return ObjectSpec(obj.name, "revolute" if obj.joint_type == "revolute" else "prismatic",
                      axis, point, T_base_handle, range=rng, **_DYNAMICS.get(obj.name, {}))


# The paper's robot task (sec. IV.C): turn the key and the window lock by 180 deg.
PAPER_AMOUNT_RAD: dict[str, float] = {"key": math.pi, "window_lock": math.pi}


def task_amount(model: KinematicModel, obj: ObjectInCamera) -> float:
    """The articulation task in the model's convention (rad or m, signed about/along its axis).

    How far: the paper's 180 deg for the key and the window lock, else the human's opening
    stroke (for a model of the wrong type: the distance the grasp travelled, or 180 deg). Which
    way: the direction the human moved, taken from the demonstration's ground truth, expressed
    about the model's own axis. The task is given; the model only supplies the joint.
    """
    if model.type == "revolute" and model.revolute is not None:
        axis = np.asarray(model.revolute.axis, float)
        size = (PAPER_AMOUNT_RAD.get(obj.name, obj.demonstrated)
                if obj.joint_type == "revolute" else math.pi)
    elif model.type == "prismatic" and model.prismatic is not None:
        axis = np.asarray(model.prismatic.axis, float)
        size = obj.chord_m()
    else:
        return 0.0
    return size if float(axis @ obj.axis) >= 0.0 else -size


@dataclass(frozen=True)
class GraspScene:
    """A true object placed in the simulated robot's workspace and the arm grasping it.

    ``T_base_camera`` the calibration it was placed through; ``obj`` the object in the base
    frame, grasped at ``obj.T_base_handle``; ``q_init`` (7,) the arm's grasp configuration.
    """

    T_base_camera: Array
    obj: ObjectSpec
    q_init: Array

    def backend(self, config: RobotBridgeConfig) -> MujocoBackend:
        """The simulation of this scene, the arm holding the grasp."""
        return MujocoBackend(self.obj, config, q_init=self.q_init)


def true_task(obj: ObjectInCamera) -> float:
    """The articulation task on the true joint (rad or m, positive along ``obj.axis``, the
    human's direction): the paper's 180 deg for the key and the window lock, else the
    demonstrated range."""
    if obj.joint_type == "revolute":
        return PAPER_AMOUNT_RAD.get(obj.name, obj.demonstrated)
    return obj.chord_m()


def grasp_scene(obj: ObjectInCamera, T_base_camera: Array, config: RobotBridgeConfig,
                joint7_change_rad: float | None = None) -> GraspScene:
    """Place ``obj`` (camera frame) through ``T_base_camera`` and grasp it (module docstring).

    The grasp may be turned by pi about the approach (the other parallel-gripper grasp) so that
    joint 7 can make the turn ``joint7_change_rad`` the articulation will need (default: that of
    :func:`true_task`). Raises ``ValueError`` when the arm cannot reach the grasp.
    """
    T_bc = np.asarray(T_base_camera, float)
    T_grasp = T_bc @ grasp_in_camera(obj)
    change = joint7_change_rad
    if change is None:
        change = 0.0 if obj.joint_type != "revolute" else (
            true_task(obj) * float((T_bc[:3, :3] @ obj.axis) @ T_grasp[:3, 2]))
    q7 = flipped_grasp_q7(float(Q_GRASP_RAD[6]), change, (float(Q_MIN_RAD[6]),
                                                          float(Q_MAX_RAD[6])),
                          config.joint7_margin_rad)
    seed = Q_GRASP_RAD.copy()
    seed[6] = Q_GRASP_RAD[6] if q7 is None else q7
    probe = MujocoBackend(None, config, q_init=seed)
    q_init = probe.solve_ik(_flip_if(T_grasp, seed[6] != Q_GRASP_RAD[6]), seed)
    return GraspScene(T_bc, sim_object(obj, T_bc, forward_kinematics(q_init)), q_init)


def articulate_in_simulation(model: KinematicModel, obj: ObjectInCamera, *,
                             T_base_camera: Array | None = None, amount: float | None = None,
                             duration_s: float | None = None,
                             config: RobotBridgeConfig | None = None,
                             check_age: bool = False,
                             refinement: RefinementConfig | None = None) -> SimArticulation:
    """Grasp the true ``obj`` in simulation and articulate it along the estimated ``model``.

    ``model`` and ``obj`` are in the camera frame; ``T_base_camera`` defaults to
    :func:`default_hand_eye`. ``amount`` defaults to :func:`task_amount` (180 deg for the key
    and the window lock, else the demonstrated range, in the demonstrated direction);
    ``duration_s`` to 6 s per 180 deg (prismatic: 2 cm/s; at least 2 s). The model's age is
    checked only with ``check_age`` (synthetic stamps are arbitrary); ``refinement`` runs it
    closed loop (docs/robot_bridge.md#closed-loop). Never raises for a bad model or an
    unreachable object: the result says why (``reason``).
    """
    cfg = config or RobotBridgeConfig()
    T_bc = default_hand_eye(obj) if T_base_camera is None else np.asarray(T_base_camera, float)
    cfg = replace(cfg, backend="mujoco", T_base_camera=tuple(float(v) for v in T_bc.ravel()))
    amt = task_amount(model, obj) if amount is None else float(amount)
    dur = default_duration(amt, model.type) if duration_s is None else float(duration_s)
    request = ArticulateRequest(stamp_ns=model.stamp_ns, frame_id=model.frame_id,
                                amount=amt, duration_s=dur,
                                force_limit_n=cfg.force_limit_n)
    # Joint 7 branch for the turn the estimated model will ask for.
    change = 0.0
    if model.type == "revolute" and model.revolute is not None:
        T_grasp = T_bc @ grasp_in_camera(obj)
        change = amt * float((T_bc[:3, :3] @ np.asarray(model.revolute.axis)) @ T_grasp[:3, 2])
    try:
        scene = grasp_scene(obj, T_bc, cfg, change)
        backend = scene.backend(cfg)
    except ValueError as exc:
        log.warning("cannot grasp %s in simulation: %s", obj.name, exc)
        result = ArticulateResult(stamp_ns=model.stamp_ns, frame_id=model.frame_id,
                                  success=False, reason="workspace", articulated=0.0,
                                  peak_force_n=0.0, mean_force_n=0.0, duration_s=0.0,
                                  detail=f"the arm cannot grasp the {obj.name}: {exc}")
        return SimArticulation(result, None, T_bc, None, amt, None)
    bridge = Bridge(backend, cfg, refinement)  # refinement: closed loop when set
    now = time.time_ns() if check_age else None
    result = bridge.articulate(request, model, now_ns=now)
    return SimArticulation(result, bridge.last_execution, T_bc, scene.obj, amt,
                           bridge.last_plan)


def _flip_if(T: Array, flip: bool) -> Array:
    """``T`` turned by pi about its own z axis when ``flip`` (the other parallel-gripper grasp)."""
    if not flip:
        return T
    out = T.copy()
    out[:3, 0] = -T[:3, 0]
    out[:3, 1] = -T[:3, 1]
    return out
