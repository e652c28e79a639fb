"""Run an articulation on a backend with every safety check, and the request-level bridge.

:func:`execute` streams a planned trajectory to a :class:`~services.robot_bridge.backend.
RobotBackend` tick by tick and aborts on the first violated limit (force, wrist torque, torque
saturation, tracking error, backend error), then holds the measured pose for ``settle_s`` so the
arm comes to rest. :class:`Bridge` turns an ``ArticulateRequest`` plus a ``KinematicModel`` into
an ``ArticulateResult``: model checks, plan checks, dry runs and execution, with the reason of
every refusal or abort (see :mod:`services.robot_bridge.safety`).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import (
    ArticulatePlan,
    ArticulateRequest,
    ArticulateResult,
    KinematicModel,
)
from services.common.se3 import se3_inverse
from services.robot_bridge.backend import BackendError, BackendState, RobotBackend
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.panda_scene import Q_MAX_RAD, Q_MIN_RAD, TAU_MAX_NM
from services.robot_bridge.refinement import RefinementConfig, RefinementRecord, Refiner
from services.robot_bridge.safety import (
    Refusal,
    SaturationWatch,
    check_amount,
    check_model,
    check_uncertainty,
    tracking_violation,
    wrench_violation,
)
from services.robot_bridge.trajectory import (
    ArticulationPlan,
    amount_text,
    joint_in_base,
    plan_checks,
)

log = logging.getLogger(__name__)

Array = NDArray[np.float64]
# on_tick(state, articulating, commanded pose T_base_target or None while not moving)
Tick = Callable[[BackendState, bool, Array | None], None]
# Called with the checked plan just before it would start (or a dry run answer): a refusal
# stops it (the service's check of the caller's deadline).
StartGate = Callable[[ArticulationPlan], Refusal | None]
_INV_TAU_MAX = 1.0 / TAU_MAX_NM


@dataclass
class Trace:
    """Per-tick record of an execution (lists of floats; base frame, SI units)."""

    t_s: list[float] = field(default_factory=list)
    force_n: list[float] = field(default_factory=list)
    torque_nm: list[float] = field(default_factory=list)
    progress: list[float] = field(default_factory=list)        # commanded joint progress
    articulated: list[float] = field(default_factory=list)     # reached joint progress
    tau_ratio: list[float] = field(default_factory=list)       # max |tau_i| / tau_max_i sent
    tau_rate_nm_per_s: list[float] = field(default_factory=list)  # max |dtau_i/dt| sent
    joint_speed_rad_per_s: list[float] = field(default_factory=list)  # max |dq_i|
    tcp_speed_m_per_s: list[float] = field(default_factory=list)     # |dp/dt| of the TCP
    command_position: list[Array] = field(default_factory=list)     # commanded TCP position (3,)
    stopped_at_s: float | None = None                          # time of the abort, if any

    def arrays(self) -> dict[str, Array]:
        return {k: np.asarray(v, float) for k, v in self.__dict__.items() if isinstance(v, list)}


@dataclass(frozen=True)
class Execution:
    """Outcome of :func:`execute`: the result message fields and the trace."""

    success: bool
    reason: str
    detail: str
    articulated: float
    peak_force_n: float
    mean_force_n: float
    peak_torque_nm: float
    duration_s: float
    trace: Trace
    refinement: RefinementRecord | None = None   # closed loop only


class _Progress:
    """Joint progress made by this request, signed like the plan (rad or m).

    One formula on every backend: :meth:`ArticulationPlan.progress_from_motion` of the grasp's
    motion since this request's start (the plan's grasp pose), about / along the request's
    axis. A real robot measures its TCP. Where the backend sees the object's grasped part
    (simulation; ``start.object_pose``), the grasp is carried along by the part's own motion
    instead, so what counts is how far the object moved, not the arm, and a joint left turned
    by an earlier request counts nothing.
    """

    def __init__(self, plan: ArticulationPlan, start: BackendState) -> None:
        self.plan = plan
        part = start.object_pose
        self._part_R0_T = None if part is None else part[:3, :3].T.copy()
        self._part_p0 = None if part is None else part[:3, 3].copy()
        self._revolute = plan.joint.joint_type == "revolute"

    def __call__(self, state: BackendState, previous: float) -> float:
        plan, part = self.plan, state.object_pose
        if self._part_R0_T is None or self._part_p0 is None or part is None:
            return plan.progress_from_pose(state.T_base_ee, previous)
        R_moved = part[:3, :3] @ self._part_R0_T
        if self._revolute:  # only the rotation counts
            return plan.progress_from_motion(R_moved, _NO_DISPLACEMENT, previous)
        grasp = plan.T_base_grasp[:3, 3]
        return plan.progress_from_motion(R_moved, R_moved @ (grasp - self._part_p0)
                                         + part[:3, 3] - grasp, previous)


_NO_DISPLACEMENT = np.zeros(3)


def execute(backend: RobotBackend, plan: ArticulationPlan, config: RobotBridgeConfig, *,
            force_limit_n: float | None = None, on_tick: Tick | None = None,
            cancel: threading.Event | None = None, record: bool = True,
            refiner: Refiner | None = None) -> Execution:
    """Follow ``plan`` on ``backend`` (already holding the grasp pose) under the safety limits.

    ``on_tick(state, articulating)`` runs after every control tick (publishing, pacing).
    Success: no abort and at least ``(1 - success_tolerance) |amount|`` reached by this
    request, in the direction of ``amount`` (:class:`_Progress`).

    With a ``refiner`` (closed loop, docs/robot_bridge.md#closed-loop) the command comes from its
    re-planned, blended path and stiffness, progress is measured about its latest axis, and its
    refusals (``model_jump``, ``model_diverged``, a failed re-plan check) abort like any limit.
    """
    force_limit = config.force_limit_n if force_limit_n is None else min(force_limit_n,
                                                                          config.force_limit_n)
    dt = backend.control_period_s
    watch = SaturationWatch(config.saturation_abort_s, dt)
    trace = Trace()
    backend.start(config.gains())
    backend.zero_wrench()
    n_motion = math.ceil(plan.total_s / dt)
    n_settle = math.ceil(config.settle_s / dt)
    abort: Refusal | None = None
    articulated = 0.0
    peak_f = peak_t = 0.0
    sum_f = 0.0
    n_f = 0
    s = backend.read()
    t0 = s.t_s
    progress_made = _Progress(plan, s)
    progress = 0.0
    taus: list[Array] = [s.tau]
    dqs: list[Array] = []
    tcp: list[Array] = [s.T_base_ee[:3, 3]]
    abort_tick = 0
    i = 0
    while (i < n_motion and abort is None) or (abort is not None and i < abort_tick + n_settle):
        moving = abort is None
        if moving and refiner is not None:  # --- closed loop (services.robot_bridge.refinement)
            refused = refiner.tick(i * dt, round((s.t_s - t0) * 1e9) + _STAMP0_NS, s.T_base_ee,
                                   s.wrench)
            if refused is not None:
                abort, abort_tick, trace.stopped_at_s = refused, i, s.t_s - t0
                log.warning("articulation aborted: %s (%s)", refused.reason, refused.detail)
                backend.hold()
                moving = False
            else:
                T_d, twist_d, progress = refiner.sample(i * dt)
                progress_made.plan = refiner.plan
                gains = refiner.gains_at(i * dt)
                if gains is not None and backend.name == "mujoco":
                    backend.gains = gains  # type: ignore[attr-defined]
                backend.command(T_d, twist_d)
        elif moving:  # --- open loop
            T_d, twist_d, progress = plan.sample(i * dt)
            backend.command(T_d, twist_d)
        try:
            backend.step()
        except BackendError as exc:
            log.error("articulation stopped by the backend: %s", exc)
            if abort is None:
                abort = Refusal("robot_error", f"the robot stopped: {exc}")
                trace.stopped_at_s = s.t_s - t0
            break
        s = backend.read()
        f = math.sqrt(float(s.wrench[0] ** 2 + s.wrench[1] ** 2 + s.wrench[2] ** 2))
        tq = math.sqrt(float(s.wrench[3] ** 2 + s.wrench[4] ** 2 + s.wrench[5] ** 2))
        articulated = progress_made(s, articulated)
        if moving:
            peak_f, peak_t = max(peak_f, f), max(peak_t, tq)
            sum_f += f
            n_f += 1
            violation = (wrench_violation(s.wrench, force_limit, config.wrist_torque_limit_nm)
                         or watch.update(s.saturated)
                         or tracking_violation(T_d, s.T_base_ee, config.tracking_error_limit_m,
                                               config.tracking_error_limit_rad))
            if violation is None and cancel is not None and cancel.is_set():
                violation = Refusal("cancelled", "stopped on request (the bridge is stopping)")
            if violation is not None:
                abort = violation
                abort_tick = i
                trace.stopped_at_s = s.t_s - t0
                log.warning("articulation aborted: %s (%s)", violation.reason, violation.detail)
                backend.hold()
        if record:
            trace.t_s.append(s.t_s - t0)
            trace.force_n.append(f)
            trace.torque_nm.append(tq)
            trace.progress.append(progress)
            if moving:
                trace.command_position.append(T_d[:3, 3].copy())
            trace.articulated.append(articulated)
            taus.append(s.tau)
            dqs.append(s.dq)
            tcp.append(s.T_base_ee[:3, 3])
        if on_tick is not None:
            on_tick(s, moving, T_d if moving else None)
        i += 1
    duration = s.t_s - t0
    backend.stop()
    if record and dqs:
        tau = np.asarray(taus)
        trace.tau_ratio = list((np.abs(tau[1:]) * _INV_TAU_MAX).max(axis=1))
        trace.tau_rate_nm_per_s = list(np.abs(np.diff(tau, axis=0)).max(axis=1) / dt)
        trace.joint_speed_rad_per_s = list(np.abs(np.asarray(dqs)).max(axis=1))
        trace.tcp_speed_m_per_s = list(np.linalg.norm(np.diff(np.asarray(tcp), axis=0),
                                                      axis=1) / dt)
    mean_f = sum_f / n_f if n_f else 0.0
    refined = refiner.record() if refiner is not None else None
    if abort is not None:
        return Execution(False, abort.reason, abort.detail, articulated, peak_f, mean_f, peak_t,
                         duration, trace, refined)
    need = (1.0 - config.success_tolerance) * abs(plan.amount)
    reached = articulated * math.copysign(1.0, plan.amount)
    kind = plan.joint.joint_type
    done = f"{amount_text(articulated, kind)} of {amount_text(plan.amount, kind)}"
    if reached < need:
        return Execution(False, "incomplete",
                         f"reached {done} (success needs {1.0 - config.success_tolerance:.0%}): "
                         "the motion fell short; check the model's axis (handkse get model) "
                         "or whether the joint is blocked",
                         articulated, peak_f, mean_f, peak_t, duration, trace, refined)
    return Execution(True, "ok", f"articulated {done} in {duration:.1f} s, peak force "
                                 f"{peak_f:.1f} N", articulated, peak_f, mean_f, peak_t,
                     duration, trace, refined)


def plan_summary(plan: ArticulationPlan, config: RobotBridgeConfig,
                 force_limit_n: float) -> ArticulatePlan:
    """The wire summary of ``plan`` with the limits it runs under (``force_limit_n``: the
    request's, capped by ``config.force_limit_n``)."""
    linear, angular = plan.peak_speeds()
    return ArticulatePlan(
        joint_type=plan.joint.joint_type, axis=np.asarray(plan.joint.axis, "<f8"),
        point=np.asarray(plan.joint.point, "<f8"), amount=float(plan.amount),
        duration_s=float(plan.duration_s), hold_s=float(plan.hold_s),
        peak_linear_speed_m_per_s=float(linear), peak_angular_speed_rad_per_s=float(angular),
        force_limit_n=float(min(force_limit_n, config.force_limit_n)),
        wrist_torque_limit_nm=float(config.wrist_torque_limit_nm),
        max_linear_speed_m_per_s=float(config.max_linear_speed_m_per_s),
        max_angular_speed_rad_per_s=float(config.max_angular_speed_rad_per_s))


# Robot stamps fed to the estimator start here (it refuses non-positive stamps) [ns].
_STAMP0_NS = 1_000_000_000


def _joint_path_check(plan: ArticulationPlan, q: Array, margin_rad: float) -> Refusal | None:
    """IK along the plan on the generated Panda model; skipped (logged) without MuJoCo."""
    try:
        from services.robot_bridge.mujoco_backend import path_joint_check
    except ImportError:
        log.warning("mujoco is not installed: the joint-range check of the planned path is "
                    "skipped (pip install 'handkse[robot]')")
        return None
    return path_joint_check(plan, q, margin_rad)


class Bridge:
    """Request-level articulation on one backend: checks, plan, dry run, execution."""

    def __init__(self, backend: RobotBackend, config: RobotBridgeConfig,
                 refinement: RefinementConfig | None = None) -> None:
        self.backend = backend
        self.config = config
        self.refinement = refinement   # closed loop when set (revolute models)
        self.last_plan: ArticulationPlan | None = None      # of the last request, if checked
        self.last_execution: Execution | None = None        # of the last request, if executed
        # The plan of the last request as built, before its plan checks (it may be refused).
        self.proposed_plan: ArticulationPlan | None = None

    def plan(self, request: ArticulateRequest, model: KinematicModel | None,
             now_ns: int | None) -> ArticulationPlan | Refusal:
        """The checked plan for ``request`` on ``model`` (in its ``frame_id``), or why not.

        Model checks (type, probability, age), the model's frame mapped into the base frame by
        its calibration (``T_base_camera`` / ``T_base_world``), the model's own uncertainty at
        the current grasp, the amount, then the plan checks.
        """
        c = self.config
        self.proposed_plan = None
        refusal = check_model(model, min_type_probability=c.min_type_probability,
                              max_age_s=c.max_model_age_s, now_ns=now_ns)
        if refusal is not None:
            return refusal
        assert model is not None
        T_base_frame = c.base_T_frame(model.frame_id)
        if T_base_frame is None:
            return Refusal("uncalibrated_frame",
                           f"the model is in the {model.frame_id!r} frame and "
                           f"robot_bridge.T_base_{model.frame_id} is not set: add that "
                           "calibration to the [robot_bridge] config")
        state = self.backend.read()
        grasp = se3_inverse(T_base_frame) @ np.append(state.T_base_ee[:3, 3], 1.0)
        refusal = check_uncertainty(
            model, grasp[:3], max_direction_std_rad=math.radians(c.max_axis_direction_std_deg),
            max_position_std_m=c.max_axis_position_std_m)
        if refusal is not None:
            return refusal
        joint = joint_in_base(model, T_base_frame)
        refusal = check_amount(request.amount, request.duration_s, joint.joint_type)
        if refusal is not None:
            return refusal
        plan = ArticulationPlan(joint=joint, T_base_grasp=state.T_base_ee.copy(),
                                amount=float(request.amount), duration_s=float(request.duration_s),
                                hold_s=c.hold_s)
        self.proposed_plan = plan
        refusal = plan_checks(plan, float(state.q[6]),
                              max_linear_m_per_s=c.max_linear_speed_m_per_s,
                              max_angular_rad_per_s=c.max_angular_speed_rad_per_s,
                              joint7_limits_rad=(float(Q_MIN_RAD[6]), float(Q_MAX_RAD[6])),
                              joint7_margin_rad=c.joint7_margin_rad)
        if refusal is None and c.check_joint_path:
            refusal = _joint_path_check(plan, state.q, c.joint_limit_margin_rad)
        return refusal if refusal is not None else plan

    def _refiner(self, plan: ArticulationPlan, model: KinematicModel) -> Refiner | None:
        """The closed-loop refiner of ``plan`` (revolute, with ``refinement`` set), or None."""
        c = self.config
        T_base_frame = c.base_T_frame(model.frame_id)
        if self.refinement is None or model.type != "revolute" or T_base_frame is None:
            return None
        if self.backend.name != "mujoco":
            # Its feed and re-plan ticks take up to ~3 ms inline (bench/results/robot.json):
            # over a real arm's 1 kHz budget. Simulation only until they leave the control loop.
            log.warning("closed-loop refinement runs in simulation only in this version; "
                        "articulating open loop on the %s backend", self.backend.name)
            return None
        checks = {"q7_rad": float(self.backend.read().q[6]),
                  "max_linear_m_per_s": c.max_linear_speed_m_per_s,
                  "max_angular_rad_per_s": c.max_angular_speed_rad_per_s,
                  "joint7_limits_rad": (float(Q_MIN_RAD[6]), float(Q_MAX_RAD[6])),
                  "joint7_margin_rad": c.joint7_margin_rad}
        refinement = self.refinement
        if self.backend.name == "mujoco" and refinement.grasp_stiffness_n_per_m is None:
            # The simulated grasp spring is known exactly (docs/robot_bridge.md#closed-loop).
            refinement = replace(refinement, grasp_stiffness_n_per_m=c.grasp_stiffness_n_per_m,
                                 grasp_stiffness_nm_per_rad=c.grasp_stiffness_nm_per_rad)
        return Refiner(model, T_base_frame, plan, c.gains(), checks,
                       self.backend.control_period_s, refinement)

    def articulate(self, request: ArticulateRequest, model: KinematicModel | None, *,
                   now_ns: int | None, on_tick: Tick | None = None,
                   cancel: threading.Event | None = None,
                   gate: StartGate | None = None) -> ArticulateResult:
        """Check, plan and (unless ``request.dry_run``) execute; never raises for a bad model.

        ``gate`` sees the checked plan last, just before execution (and before a dry run's
        answer, so that a dry run answers what the request would get).
        """
        stamp = model.stamp_ns if model is not None else 0
        frame = model.frame_id if model is not None else "camera"
        self.last_execution = None
        planned = self.plan(request, model, now_ns)
        self.last_plan = planned if isinstance(planned, ArticulationPlan) else None
        if not isinstance(planned, Refusal) and gate is not None:
            planned = gate(planned) or planned
        summary = (None if self.proposed_plan is None
                   else plan_summary(self.proposed_plan, self.config, request.force_limit_n))
        if isinstance(planned, Refusal):
            log.warning("articulation refused: %s (%s)", planned.reason, planned.detail)
            return ArticulateResult(stamp_ns=stamp, frame_id=frame, success=False,
                                    reason=planned.reason, articulated=0.0, peak_force_n=0.0,
                                    mean_force_n=0.0, duration_s=0.0, detail=planned.detail,
                                    plan=summary)
        if request.dry_run:
            kind = planned.joint.joint_type
            return ArticulateResult(
                stamp_ns=stamp, frame_id=frame, success=True, reason="dry_run",
                articulated=0.0, peak_force_n=0.0, mean_force_n=0.0,
                duration_s=planned.total_s, plan=summary,
                detail=f"would articulate {amount_text(planned.amount, kind)} in "
                       f"{planned.duration_s:.1f} s (+{planned.hold_s:.1f} s hold); every "
                       "check passed; nothing moved")
        refiner = self._refiner(planned, model) if model is not None else None
        ex = execute(self.backend, planned, self.config, force_limit_n=request.force_limit_n,
                     on_tick=on_tick, cancel=cancel, refiner=refiner)
        self.last_execution = ex
        return ArticulateResult(stamp_ns=stamp, frame_id=frame, success=ex.success,
                                reason=ex.reason, articulated=float(ex.articulated),
                                peak_force_n=float(ex.peak_force_n),
                                mean_force_n=float(ex.mean_force_n),
                                duration_s=float(max(ex.duration_s, 0.0)), detail=ex.detail,
                                plan=summary)
