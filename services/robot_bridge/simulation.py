"""Articulate a synthetic demonstration's object in simulation with an estimated model.

The synthetic generator gives the true object in the camera frame; the estimate is in the
camera frame too. :func:`articulate_in_simulation` places that true object in the simulated
robot's workspace through a hand-eye calibration ``T_base_camera`` (default: the one that puts
the robot's grasp on the object exactly at the nominal grasp pose, so every object is reachable),
grasps it, and runs the bridge exactly as the service would: model checks, plan from the
estimated model moved into the base frame with the same ``T_base_camera``, execution under the
safety limits. Estimation errors therefore reach the robot exactly as they are in the camera.

Robot grasps (``T_cam_grasp``): the gripper approaches into the mounting surface (TCP z = minus
the object's outward normal, object frame y). Revolute objects are held on the lever: the key on
its axis (the key's bow), the window lock 6 cm from the axis, any other object where the human
held it; prismatic objects where the human held them, TCP y along the slide.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import ArticulateRequest, ArticulateResult, KinematicModel
from services.common.se3 import se3_inverse
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.executor import Bridge, Execution
from services.robot_bridge.mujoco_backend import (
    WINDOW_LOCK_LEVER_M,
    MujocoBackend,
    forward_kinematics,
    nominal_grasp_pose,
)
from services.robot_bridge.panda_scene import Q_GRASP_RAD, Q_MAX_RAD, Q_MIN_RAD, ObjectSpec
from services.robot_bridge.refinement import RefinementConfig
from services.robot_bridge.trajectory import ArticulationPlan, flipped_grasp_q7

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
SECONDS_PER_HALF_TURN = 6.0      # 180 deg in 6 s (docs/robot_bridge.md#grasp-configuration)
PRISMATIC_SPEED_M_PER_S = 0.02   # mean speed of a prismatic articulation
MIN_DURATION_S = 2.0


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


def default_duration(amount: float, joint_type: str) -> float:
    if joint_type == "revolute":
        return max(MIN_DURATION_S, SECONDS_PER_HALF_TURN * abs(amount) / math.pi)
    return max(MIN_DURATION_S, abs(amount) / PRISMATIC_SPEED_M_PER_S)


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
    ``duration_s`` to 6 s per 180 deg (prismatic: 2 cm/s; at least 2 s). The model's age is checked only with
    ``check_age`` (synthetic stamps are arbitrary); ``refinement`` runs it closed loop
    (docs/robot_bridge.md#closed-loop). Never raises for a bad model or an
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
    T_grasp = T_bc @ grasp_in_camera(obj)
    # Joint 7 branch: the grasp may be turned by pi about the approach so the turn fits.
    change = 0.0
    if model.type == "revolute" and model.revolute is not None:
        change = amt * float((T_bc[:3, :3] @ np.asarray(model.revolute.axis)) @ T_grasp[:3, 2])
    q7 = flipped_grasp_q7(float(Q_GRASP_RAD[6]), change, (float(Q_MIN_RAD[6]),
                                                          float(Q_MAX_RAD[6])),
                          cfg.joint7_margin_rad)
    seed = Q_GRASP_RAD.copy()
    seed[6] = Q_GRASP_RAD[6] if q7 is None else q7
    try:
        probe = MujocoBackend(None, cfg, q_init=seed)
        q_init = probe.solve_ik(_flip_if(T_grasp, seed[6] != Q_GRASP_RAD[6]), seed)
        T_handle = forward_kinematics(q_init)
        spec = sim_object(obj, T_bc, T_handle)
        backend = MujocoBackend(spec, cfg, q_init=q_init)
    except ValueError as exc:
        log.warning("cannot grasp %s in simulation: %s", obj.name, exc)
        result = ArticulateResult(stamp_ns=model.stamp_ns, frame_id=model.frame_id,
                                  success=False, reason="workspace", articulated=0.0,
                                  peak_force_n=0.0, mean_force_n=0.0, duration_s=0.0)
        return SimArticulation(result, None, T_bc, None, amt, None)
    bridge = Bridge(backend, cfg, refinement)  # refinement: closed loop when set
    now = time.time_ns() if check_age else None
    result = bridge.articulate(request, model, now_ns=now)
    return SimArticulation(result, bridge.last_execution, T_bc, spec, amt, bridge.last_plan)


def articulate_demonstration(model: KinematicModel, demo: object,
                             **kwargs: object) -> SimArticulation:
    """:func:`articulate_in_simulation` on a synthetic ``Demonstration``'s true object.

    The hook for ``handkse demo``: ``model`` is the final estimate (camera frame); keyword
    arguments are passed on (``T_base_camera``, ``amount``, ``duration_s``, ``config``).
    """
    return articulate_in_simulation(model, object_in_camera(demo), **kwargs)  # type: ignore[arg-type]


def _flip_if(T: Array, flip: bool) -> Array:
    """``T`` turned by pi about its own z axis when ``flip`` (the other parallel-gripper grasp)."""
    if not flip:
        return T
    out = T.copy()
    out[:3, 0] = -T[:3, 0]
    out[:3, 1] = -T[:3, 1]
    return out


def format_result(result: ArticulateResult, joint_type: str = "revolute") -> str:
    """One line for the demo: success, reason, amount reached, peak and mean force."""
    reached = (f"{math.degrees(result.articulated):.1f} deg" if joint_type == "revolute"
               else f"{result.articulated * 1000:.1f} mm")
    return (f"simulated articulation: {'SUCCESS' if result.success else 'FAILED'} "
            f"({result.reason}), articulated {reached}, peak force {result.peak_force_n:.1f} N, "
            f"mean force {result.mean_force_n:.1f} N, {result.duration_s:.1f} s")
