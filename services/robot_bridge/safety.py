"""Safety limits as pure functions: each returns what is actually allowed, or a refusal reason.

Reasons are short stable labels (they end up in ``ArticulateResult.reason``):

=====================  =========================================================================
``busy``               another request is being served (one articulation at a time; the second
                       is refused at once, never queued)
``caller_gone``        the caller's timeout had passed before the articulation could start (the
                       reply could not be delivered); nothing was started
``timeout_too_short``  the planned motion would not end within the caller's timeout
``low_confidence``     the model's type probability is below the configured threshold
``uncertain_model``    the model's own covariance puts its axis direction, or a revolute axis'
                       position at the grasp, beyond the configured 1-sigma bounds
``uncalibrated_frame`` the model's ``frame_id`` has no calibration to the robot base frame
``unsupported_type``   the model is rigid, disconnected or unknown (nothing to articulate)
``stale_model``        the model is older than the configured age (or stamped in the future), or
                       the kinematics service cannot be asked and the last model received from
                       it is older than ``max_cached_model_age_s`` (see :func:`check_cached_model`)
``no_model``           no model was given and none could be obtained from the kinematics service
``no_segment``         the request names a contact phase the demonstration does not have
``open_segment``       the request names a contact phase that is still open (the hand holds it)
``invalid_request``    amount zero/non-finite, or a duration that is too short
``too_fast``           the planned peak Cartesian speed exceeds the configured limit
``workspace``          the planned path leaves the reachable workspace
``joint7_range``       joint 7 would leave its range (regrasp rotated by 180 deg about the approach)
``joint_limits``       the planned path needs a joint beyond (or within a margin of) its range
``force_limit``        ``|F|`` at the wrist exceeded the force limit (default 70 N)
``torque_limit``       ``|T|`` at the wrist exceeded the wrist torque limit
``torque_saturation``  a joint torque demand exceeded Franka's limit for longer than allowed
``tracking_error``     the end-effector lagged the target by more than the bound
``robot_error``        the backend reported an error (reflex, communication, simulation)
``cancelled``          stopped on request (service shutdown)
``model_jump``         closed loop: the robot's refined axis moved faster than the bound per second
``model_diverged``     closed loop: the refined axis' 1-sigma grew above a factor of its minimum
``incomplete``         the trajectory ended without reaching the commanded amount
=====================  =========================================================================
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import KinematicModel
from services.kinematics.filters import tangent_basis

Array = NDArray[np.float64]

ARTICULABLE_TYPES = ("revolute", "prismatic")
# Allowed clock skew for a model stamped slightly in the future (camera and robot clocks) [s].
FUTURE_TOLERANCE_S = 1.0


@dataclass(frozen=True)
class Refusal:
    """Why a request is not executed: a stable ``reason`` label and a ``detail`` sentence that
    names the numbers and, where the operator can do something, what to do
    (``ArticulateResult.detail``)."""

    reason: str
    detail: str


@dataclass(frozen=True)
class TorqueCommand:
    """A joint torque command after clamping (N m).

    ``tau`` is what is sent; ``saturated`` is true when the demand exceeded a joint's torque
    limit (the clamp reduced its magnitude, not only its rate).
    """

    tau: Array
    saturated: bool


def clamp_torque(tau_desired: Array, tau_previous: Array, dt_s: float, tau_max_nm: Array,
                 rate_max_nm_per_s: float) -> TorqueCommand:
    """Clamp a torque demand to ``|tau| <= tau_max`` and ``|tau - tau_prev| <= rate_max dt``.

    ``tau_previous`` must itself be within the limits (it is the last command sent); the result
    then satisfies both bounds exactly.
    """
    step = rate_max_nm_per_s * dt_s
    lo = np.maximum(tau_previous - step, -tau_max_nm)
    hi = np.minimum(tau_previous + step, tau_max_nm)
    tau = np.minimum(np.maximum(tau_desired, lo), hi)
    saturated = bool((np.abs(tau_desired) > tau_max_nm).any())
    return TorqueCommand(tau=tau, saturated=saturated)


def clamp_twist(twist: Array, linear_max_m_per_s: float, angular_max_rad_per_s: float) -> Array:
    """Scale the linear and angular parts of a twist (6,) down to their speed limits."""
    out = np.array(twist, dtype=float)
    for lo, limit in ((0, linear_max_m_per_s), (3, angular_max_rad_per_s)):
        n = math.sqrt(float(out[lo] ** 2 + out[lo + 1] ** 2 + out[lo + 2] ** 2))
        if n > limit:
            out[lo:lo + 3] *= limit / n
    return out


def check_model(model: KinematicModel | None, *, min_type_probability: float,
                max_age_s: float, now_ns: int | None) -> Refusal | None:
    """Refuse a model that is missing, not articulable, uncertain or stale.

    ``now_ns`` is the current time on the clock of the model's ``stamp_ns`` (wall clock for the
    live pipeline); ``None`` skips the age check (offline evaluation of recorded estimates).
    """
    if model is None:
        return Refusal("no_model", "no kinematic model was given or available: run the "
                                   "kinematics service and demonstrate, or send a model")
    if model.type not in ARTICULABLE_TYPES:
        return Refusal("unsupported_type",
                       f"model type {model.type!r} cannot be articulated (need revolute or "
                       "prismatic): demonstrate the motion (again) until the model is one")
    params = model.revolute if model.type == "revolute" else model.prismatic
    if params is None:
        return Refusal("unsupported_type", f"model type {model.type} has no parameters: send "
                                           "a model with its joint parameters")
    p = float(model.probabilities.get(model.type, 0.0))
    if p < min_type_probability:
        return Refusal("low_confidence",
                       f"P({model.type}) = {p:.3f} is below the threshold {min_type_probability} "
                       "(robot_bridge.min_type_probability): demonstrate the motion longer or "
                       "again")
    if now_ns is not None:
        age_s = (now_ns - model.stamp_ns) * 1e-9
        if age_s > max_age_s:
            return Refusal("stale_model",
                           f"model is {age_s:.0f} s old (limit {max_age_s:g} s, "
                           "robot_bridge.max_model_age_s): replay with wall-clock stamps "
                           "(handkse replay without --keep-stamps) or record a new "
                           "demonstration")
        if age_s < -FUTURE_TOLERANCE_S:
            return Refusal("stale_model",
                           f"model is stamped {-age_s:.1f} s in the future: synchronise the "
                           "clocks of the camera and robot computers (e.g. chrony)")
    return None


def check_uncertainty(model: KinematicModel, grasp: Array, *, max_direction_std_rad: float,
                      max_position_std_m: float) -> Refusal | None:
    """Refuse a model whose own covariance says its joint is not known well enough to act on.

    ``model`` has passed :func:`check_model` (revolute or prismatic, with parameters); ``grasp``
    (3,) is the robot's grasp point in the model's frame (m). Both bounds are on 1-sigma values
    of the published covariance, whose axis coordinates ``(b1, b2)`` [rad] are in
    ``tangent_basis(axis)`` (a small axis change is ``B b``):

    - axis direction (both types): the square root of the largest eigenvalue of the
      ``(b1, b2)`` block;
    - axis position (revolute): the published ``point`` is the axis' point nearest the frame
      origin, often half a metre from the object, so its own spread is mostly the direction's
      spread times that lever. What the robot meets is the axis at the grasp: the point of the
      axis nearest ``grasp`` moves, perpendicular to the axis, by
      ``d = P_perp dp + s B db`` with ``s = (grasp - point) . axis``; its largest 1-sigma
      displacement is checked.

    A covariance that is not positive semi-definite in these coordinates is refused too.
    """
    params = model.revolute if model.type == "revolute" else model.prismatic
    assert params is not None
    C = np.asarray(params.covariance, float)
    n = 5 if model.type == "revolute" else 2
    block = C[:n, :n]
    eig = np.linalg.eigvalsh(block)
    if not np.isfinite(eig).all() or eig[0] < -1e-9 * max(float(np.abs(eig).max()), 1e-12):
        names = "(b1, b2, px, py, pz)" if n == 5 else "(b1, b2)"
        return Refusal("uncertain_model", f"the {model.type} covariance of {names} is not "
                                          f"positive semi-definite (eigenvalue {eig[0]:.3g}): "
                                          "the model is broken; reset the kinematics service "
                                          "and demonstrate again")
    direction = math.sqrt(max(float(np.linalg.eigvalsh(C[:2, :2]).max()), 0.0))
    if direction > max_direction_std_rad:
        return Refusal("uncertain_model",
                       f"axis direction 1-sigma {math.degrees(direction):.2f} deg exceeds "
                       f"{math.degrees(max_direction_std_rad):.2f} deg "
                       "(robot_bridge.max_axis_direction_std_deg): demonstrate a longer, "
                       "clearer stroke")
    rev = model.revolute
    if model.type != "revolute" or rev is None:
        return None
    axis = np.asarray(rev.axis, float)
    point = np.asarray(rev.point, float)
    s = float((np.asarray(grasp, float) - point) @ axis)
    J = np.hstack([s * tangent_basis(axis), np.eye(3) - np.outer(axis, axis)])
    position = math.sqrt(max(float(np.linalg.eigvalsh(J @ block @ J.T).max()), 0.0))
    if position > max_position_std_m:
        return Refusal("uncertain_model",
                       f"axis position 1-sigma at the grasp {position * 1e3:.1f} mm exceeds "
                       f"{max_position_std_m * 1e3:.1f} mm (robot_bridge.max_axis_position_std_m)"
                       ": demonstrate a longer, clearer stroke")
    return None


def check_cached_model(received_age_s: float | None, max_cached_age_s: float, why: str
                       ) -> Refusal | None:
    """May the bridge fall back to the last model it received, the kinematics service being
    unreachable (``why`` says how)?

    Only if that model arrived at most ``max_cached_age_s`` seconds ago (``received_age_s``, on
    the bridge's own monotonic clock; ``None``: never received). Otherwise ``stale_model``, or
    ``no_model`` when there is none: a robot must not act on an estimate that may have moved on
    while its source was cut off. The model itself still goes through :func:`check_model`.
    """
    if received_age_s is None:
        return Refusal("no_model", f"{why}; no model was received from it either: is handkse "
                                   "kinematics running on this rig and connected?")
    if received_age_s > max_cached_age_s:
        return Refusal("stale_model", f"{why}; the last model was received {received_age_s:.1f} s "
                                      f"ago (limit {max_cached_age_s:g} s): check that the "
                                      "kinematics service is running and reachable")
    return None


def check_amount(amount: float, duration_s: float, joint_type: str) -> Refusal | None:
    """Refuse a zero/non-finite amount or an implausible one (> 2 pi rad or > 1 m)."""
    if not math.isfinite(amount) or amount == 0.0:
        return Refusal("invalid_request", f"amount must be finite and non-zero, got {amount}")
    limit = 2.0 * math.pi if joint_type == "revolute" else 1.0
    if abs(amount) > limit:
        unit = "rad" if joint_type == "revolute" else "m"
        return Refusal("invalid_request", f"|amount| {abs(amount):.3f} {unit} exceeds "
                                          f"{limit:.3f} {unit} for a {joint_type} joint")
    if not duration_s > 0.0:
        return Refusal("invalid_request", f"duration_s must be > 0, got {duration_s}")
    return None


def wrench_violation(wrench: Array, force_limit_n: float, torque_limit_nm: float
                     ) -> Refusal | None:
    """``force_limit`` / ``torque_limit`` when the wrist wrench (6,) exceeds a limit."""
    f = math.sqrt(float(wrench[0] ** 2 + wrench[1] ** 2 + wrench[2] ** 2))
    if f > force_limit_n:
        return Refusal("force_limit", f"|F| = {f:.1f} N exceeded {force_limit_n:.1f} N: the "
                                      "object resists the planned path (a wrong axis, or the "
                                      "joint is blocked)")
    t = math.sqrt(float(wrench[3] ** 2 + wrench[4] ** 2 + wrench[5] ** 2))
    if t > torque_limit_nm:
        return Refusal("torque_limit", f"|T| = {t:.2f} N m exceeded {torque_limit_nm:.2f} N m: "
                                       "the planned rotation fights the object's (a tilted "
                                       "axis?)")
    return None


def tracking_violation(T_target: Array, T_actual: Array, max_position_m: float,
                       max_rotation_rad: float) -> Refusal | None:
    """``tracking_error`` when the end-effector is too far from its target pose."""
    dp = T_target[:3, 3] - T_actual[:3, 3]
    d = math.sqrt(float(dp @ dp))
    if d > max_position_m:
        return Refusal("tracking_error", f"position error {d * 100:.1f} cm exceeded "
                                         f"{max_position_m * 100:.1f} cm: the hand is held back")
    # trace(R_d R^T) = sum of the element-wise product; angle = acos((trace - 1) / 2)
    c = (float((T_target[:3, :3] * T_actual[:3, :3]).sum()) - 1.0) / 2.0
    a = math.acos(max(-1.0, min(1.0, c)))
    if a > max_rotation_rad:
        return Refusal("tracking_error", f"orientation error {math.degrees(a):.1f} deg exceeded "
                                         f"{math.degrees(max_rotation_rad):.1f} deg: the hand is "
                                         "held back")
    return None


class SaturationWatch:
    """Counts consecutive saturated control ticks; trips after ``max_s`` seconds of saturation."""

    def __init__(self, max_s: float, dt_s: float) -> None:
        self.max_ticks = max(1, round(max_s / dt_s))
        self.ticks = 0

    def update(self, saturated: bool) -> Refusal | None:
        self.ticks = self.ticks + 1 if saturated else 0
        if self.ticks >= self.max_ticks:
            return Refusal("torque_saturation",
                           f"joint torque demand above Franka's limits for {self.ticks} ticks: "
                           "the arm cannot follow the model (check its axis)")
        return None


def choose_segment(models: Sequence[KinematicModel], segment: int) -> KinematicModel | Refusal:
    """The model of contact phase ``segment`` from a ``KinematicModelList``'s ``models``, or why
    not: ``no_segment`` (no such phase), ``open_segment`` (still open: its estimate is not
    final). Whether its verdict can be articulated is :func:`check_model`'s."""
    for model in models:
        if model.segment == segment:
            if model.segment_end_ns is None:
                return Refusal("open_segment", f"contact phase {segment} is still open (the hand "
                                               "holds it): wait for the release")
            return model
    known = ", ".join(str(m.segment) for m in models) or "none"
    return Refusal("no_segment", f"the demonstration has no contact phase {segment} (phases: "
                                 f"{known})")
