"""Configuration of the robot bridge (``[robot_bridge]`` TOML section).

Defaults follow the ICRA-25 paper (sec. IV.C: 70 N force limit, 180 deg articulation with a
Jacobian-transpose Cartesian impedance controller) and docs/robot_bridge.md#gains-and-errors
(gains 1000 N/m and 50 N m/rad, a 20 kN/m / 30 N m/rad compliant grasp in simulation). Every
safety limit is on by default; a request may lower the force limit but never raise it above
``force_limit_n``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import check_pose
from services.robot_bridge.controller import ImpedanceGains

BACKENDS = ("mujoco", "panda")
SIM_OBJECTS = ("key", "window_lock", "bolt")
_IDENTITY = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class RobotBridgeConfig:
    """Parameters of :mod:`services.robot_bridge` (SI units, as the field names say)."""

    # --- Backend ---
    backend: str = "mujoco"               # "mujoco" (simulation) or "panda" (panda-python)
    robot_host: str = ""                  # Panda's address (backend "panda")
    # Calibrations, 16 numbers, row-major: the pose of each frame a kinematic model may be given
    # in (its frame_id) in the robot base frame. "camera": the hand-eye calibration of a static
    # camera; "world": the frame of a moving camera's poses T_world_camera. Empty: not
    # calibrated, and a model in that frame is refused (uncalibrated_frame).
    T_base_camera: tuple[float, ...] = _IDENTITY
    T_base_world: tuple[float, ...] = ()

    # --- Model checks (refused with a reason) ---
    min_type_probability: float = 0.8     # P(type) of the model's type must reach this
    # Bounds on the model's own 1-sigma uncertainty (uncertain_model beyond them; see
    # docs/robot_bridge.md#model-uncertainty): the axis direction (both types), and for a
    # revolute joint the position of its axis at the grasp, perpendicular to the axis.
    max_axis_direction_std_deg: float = 5.0
    max_axis_position_std_m: float = 0.01
    max_model_age_s: float = 120.0        # model stamp_ns must be at most this old (wall clock)
    model_query_timeout_s: float = 2.0    # get on the kinematics service when no model is given
    # When that get fails (service down, link cut), the last model received from the service is
    # used only if it arrived at most this long ago (about one Zenoh lease); else stale_model.
    # 0: never fall back.
    max_cached_model_age_s: float = 2.0

    # --- Abort limits (checked every control tick) ---
    force_limit_n: float = 70.0           # |F| at the wrist (paper: 70 N)
    wrist_torque_limit_nm: float = 12.0   # |T| at the wrist: the wrist joints' 12 N m limit
    tracking_error_limit_m: float = 0.10  # TCP position error to the target
    tracking_error_limit_rad: float = 0.6  # TCP orientation error to the target
    saturation_abort_s: float = 0.005     # joint torque demand above Franka's limit this long

    # --- Plan checks ---
    max_linear_speed_m_per_s: float = 0.25
    max_angular_speed_rad_per_s: float = 2.0
    joint7_margin_rad: float = 0.1        # keep joint 7 this far inside its range
    check_joint_path: bool = True         # IK along the planned path (needs mujoco, else skipped)
    joint_limit_margin_rad: float = 0.0   # ... every joint at least this far inside its range

    # --- Closed loop (docs/robot_bridge.md#closed-loop) ---
    # Refine a revolute model from the robot's own grasp motion while articulating, re-plan and
    # comply where the model is unsure. Simulation (mujoco) only in this version: on a real
    # robot the bridge warns and runs open loop (the refinement runs in the control tick).
    closed_loop: bool = False

    # --- Controller (Jacobian-transpose Cartesian impedance) ---
    translational_stiffness_n_per_m: float = 1000.0
    rotational_stiffness_nm_per_rad: float = 50.0
    damping_ratio: float = 1.0
    nullspace_stiffness_nm_per_rad: float = 0.5

    # --- Execution ---
    hold_s: float = 0.5                   # keep the final target this long after the motion
    settle_s: float = 1.0                 # after an abort, hold the measured pose this long
    success_tolerance: float = 0.03       # success: reached at least (1 - this) of the amount

    # --- Service ---
    state_rate_hz: float = 100.0          # RobotState publication rate (wall clock)
    # How long a caller that sends no ArticulateRequest.timeout_s is taken to wait for the
    # result (Zenoh's default query timeout); nothing starts that could not end within it.
    request_timeout_s: float = 10.0

    # --- Simulation (backend "mujoco") ---
    # The simulated object (docs/robot_bridge.md#simulated-object): a preset ("key",
    # "window_lock", "bolt") at the nominal grasp pose; "synthetic:OBJECT[:PARTICIPANT[:SEED[:VARIANT]]]",
    # the true object of that synthetic demonstration; or an object calibration file (*.toml),
    # the object in the camera frame. The last two are placed through T_base_camera.
    sim_object: str = "key"
    sim_realtime_factor: float = 1.0      # service pacing: 1 = real time, 0 = as fast as possible
    grasp_stiffness_n_per_m: float = 20000.0
    grasp_stiffness_nm_per_rad: float = 30.0
    grasp_damping_n_s_per_m: float = 20.0
    grasp_damping_nm_s_per_rad: float = 0.05

    # --- Real robot (backend "panda") ---
    # Franka reflex thresholds, raised above the software limits so the bridge aborts first.
    reflex_force_threshold_n: float = 100.0
    reflex_torque_threshold_nm: float = 30.0   # Cartesian torque reflex
    reflex_joint_torque_threshold_nm: float = 60.0  # joints 1-4; joints 5-7 use 2/3 of it

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        sim_object_source(self.sim_object)  # raises ValueError naming the rule
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{f.name} must be finite, got {v!r}")
        positive = ("min_type_probability", "max_axis_direction_std_deg",
                    "max_axis_position_std_m", "request_timeout_s", "max_model_age_s",
                    "model_query_timeout_s",
                    "force_limit_n", "wrist_torque_limit_nm", "tracking_error_limit_m",
                    "tracking_error_limit_rad", "saturation_abort_s", "max_linear_speed_m_per_s",
                    "max_angular_speed_rad_per_s", "translational_stiffness_n_per_m",
                    "rotational_stiffness_nm_per_rad", "damping_ratio", "state_rate_hz",
                    "grasp_stiffness_n_per_m", "grasp_stiffness_nm_per_rad",
                    "reflex_force_threshold_n", "reflex_torque_threshold_nm",
                    "reflex_joint_torque_threshold_nm")
        for name in positive:
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        non_negative = ("max_cached_model_age_s", "joint7_margin_rad", "joint_limit_margin_rad",
                        "nullspace_stiffness_nm_per_rad", "hold_s", "settle_s",
                        "success_tolerance", "sim_realtime_factor", "grasp_damping_n_s_per_m",
                        "grasp_damping_nm_s_per_rad")
        for name in non_negative:
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if self.min_type_probability > 1.0:
            raise ValueError(f"min_type_probability must be <= 1, got {self.min_type_probability}")
        if self.success_tolerance >= 1.0:
            raise ValueError(f"success_tolerance must be < 1, got {self.success_tolerance}")
        if self.max_angular_speed_rad_per_s > 2.5 or self.max_linear_speed_m_per_s > 1.7:
            raise ValueError("speed limits must stay within Franka's Cartesian limits "
                             "(1.7 m/s, 2.5 rad/s)")
        if self.reflex_force_threshold_n <= self.force_limit_n:
            raise ValueError(f"reflex_force_threshold_n ({self.reflex_force_threshold_n}) must "
                             f"exceed force_limit_n ({self.force_limit_n}) so the software "
                             "abort acts first")
        _check_calibration("T_base_camera", self.T_base_camera, required=True)
        _check_calibration("T_base_world", self.T_base_world, required=False)

    def base_T_camera(self) -> NDArray[np.float64]:
        """``T_base_camera`` as a 4x4 array."""
        return np.asarray(self.T_base_camera, float).reshape(4, 4)

    def base_T_frame(self, frame_id: str) -> NDArray[np.float64] | None:
        """``T_base_{frame_id}`` (4x4) for a model's ``frame_id``; None when not calibrated."""
        values = {"camera": self.T_base_camera, "world": self.T_base_world}.get(frame_id, ())
        return np.asarray(values, float).reshape(4, 4) if values else None

    def gains(self) -> ImpedanceGains:
        return ImpedanceGains(translational_n_per_m=self.translational_stiffness_n_per_m,
                              rotational_nm_per_rad=self.rotational_stiffness_nm_per_rad,
                              damping_ratio=self.damping_ratio,
                              nullspace_nm_per_rad=self.nullspace_stiffness_nm_per_rad)


def _check_calibration(name: str, values: tuple[float, ...], required: bool) -> None:
    """A calibration is 16 numbers (row-major 4x4) of a rigid transform, or empty if optional."""
    if not values and not required:
        return
    T = np.asarray(values, float)
    if T.shape != (16,):
        raise ValueError(f"{name} needs 16 numbers (row-major 4x4), got {T.size}")
    if (problem := check_pose(T.reshape(4, 4))) is not None:
        raise ValueError(f"{name} is not a rigid transform: {problem}")


SYNTHETIC_PREFIX = "synthetic:"


@dataclass(frozen=True)
class SimObjectSource:
    """Where the simulated object comes from (``sim_object``): ``kind`` "preset" (``name`` one
    of :data:`SIM_OBJECTS`), "synthetic" (the demonstration ``generate(name, participant,
    seed, variant=variant)``) or "file" (an object calibration file at ``path``)."""

    kind: str
    name: str = ""
    participant: int = 3
    seed: int = 0
    path: str = ""
    variant: str = "cut"

    def __str__(self) -> str:
        if self.kind == "synthetic":
            text = f"{SYNTHETIC_PREFIX}{self.name}:{self.participant}:{self.seed}"
            return text if self.variant == "cut" else f"{text}:{self.variant}"
        return self.path if self.kind == "file" else self.name


def sim_object_source(text: str) -> SimObjectSource:
    """Parse ``sim_object``: a preset name, ``synthetic:OBJECT[:PARTICIPANT[:SEED[:VARIANT]]]``
    (participant 3, seed 0 and variant "cut" by default, as ``handkse replay --synthetic``) or a
    path ending in ``.toml``.

    Raises ``ValueError`` naming what is wrong (an unknown object lists the known ones).
    """
    if text in SIM_OBJECTS:
        return SimObjectSource("preset", name=text)
    if text.startswith(SYNTHETIC_PREFIX):
        parts = text[len(SYNTHETIC_PREFIX):].split(":")
        if not 1 <= len(parts) <= 4 or not parts[0]:
            raise ValueError(f"sim_object {text!r} must look like synthetic:OBJECT, "
                             "synthetic:OBJECT:PARTICIPANT, synthetic:OBJECT:PARTICIPANT:SEED or "
                             "synthetic:OBJECT:PARTICIPANT:SEED:VARIANT")
        from services.synthetic.splits import FREE_OBJECT, PARTICIPANTS, VARIANTS, preset

        variant = parts.pop() if len(parts) == 4 else "cut"
        if variant not in VARIANTS:
            raise ValueError(f"sim_object {text!r}: variant must be one of "
                             f"{', '.join(VARIANTS)}, got {variant!r}")

        name = parts[0]
        if name == FREE_OBJECT:
            raise ValueError(f"sim_object {text!r}: the {FREE_OBJECT!r} stream has no object")
        try:
            preset(name)
        except ValueError as exc:  # its message lists the known objects
            raise ValueError(f"sim_object {text!r}: {exc}") from None
        try:
            numbers = [int(v) for v in parts[1:]]
        except ValueError:
            raise ValueError(f"sim_object {text!r}: participant and seed must be whole "
                             "numbers") from None
        participant, seed = (numbers + [3, 0][len(numbers):])[:2]
        if participant not in PARTICIPANTS:
            raise ValueError(f"sim_object {text!r}: participant must be "
                             f"{min(PARTICIPANTS)}..{max(PARTICIPANTS)}, got {participant}")
        if seed < 0:
            raise ValueError(f"sim_object {text!r}: seed must be >= 0, got {seed}")
        return SimObjectSource("synthetic", name=name, participant=participant, seed=seed,
                               variant=variant)
    if text.endswith(".toml"):
        return SimObjectSource("file", path=text)
    raise ValueError(f"sim_object must be a preset ({', '.join(SIM_OBJECTS)}), "
                     f"synthetic:OBJECT[:PARTICIPANT[:SEED[:VARIANT]]] or an object calibration file "
                     f"(*.toml), got {text!r}")


SECTION = "robot_bridge"


def config_from_args(args: Any) -> RobotBridgeConfig:
    """The ``[robot_bridge]`` section from the CLI's ``--config FILE`` and ``--set`` overrides."""
    from services.common.config import section_from_args

    config = section_from_args(args, SECTION)
    assert isinstance(config, RobotBridgeConfig)
    return config
