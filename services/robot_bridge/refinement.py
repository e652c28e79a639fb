"""Closed-loop articulation: refine the joint from the robot's own grasp motion and re-plan.

While the gripper holds the part, the grasp pose moves the way the object's joint lets it, so
the robot's end-effector poses are evidence of the joint (docs/robot_bridge.md#closed-loop).
:class:`Refiner` feeds them, mapped into the model's frame through the calibration
``T_base_frame`` (``T_base_camera`` for a camera model), into a fresh
:class:`~services.kinematics.estimator.KinematicEstimator` (the camera's estimator, used as a
library) at ``feed_rate_hz``, fuses its revolute estimate with the executed model (the prior) in
information form when the two agree, and re-plans the rest of the path from the result at
``replan_rate_hz``. The executed joint moves toward the refined one at bounded rates, and each
re-plan is blended into the command over ``blend_replans`` re-plan periods (overlapping) with a
minimum-jerk weight, so the commanded pose, twist and stiffness stay continuous; every re-planned
path passes the plan checks again (speed, workspace, joint 7). Refinement only ever lowers
stiffness (``compliance``) and never touches a limit. :class:`RefinementRecord` keeps the refined
model and the robot's own estimate at 90 deg of progress (``CHECKPOINT_RAD``) too.

Aborts (:class:`~services.robot_bridge.safety.Refusal`): ``model_jump`` when the robot's own
estimate, once engaged, moves faster than ``jump_direction_deg_per_s`` / ``jump_position_m_per_s``;
``model_diverged`` when its 1-sigma axis direction or grasp position grows above
``divergence_factor`` times its smallest value so far; a re-planned path that fails a plan check
aborts with that check's reason.

Frames: ``T_base_*`` 4x4 base-frame poses (m); the estimator and the published robot body are
in the model's ``frame_id``. Only revolute models are refined in this version; prismatic ones
run open loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import KinematicModel
from services.common.se3 import se3_inverse, so3_exp
from services.kinematics.estimator import KinematicEstimator, chi2_quantile_of_sigmas
from services.kinematics.filters import tangent_basis
from services.robot_bridge.compliance import AxisBelief, ComplianceLaw, MatrixGains
from services.robot_bridge.controller import ImpedanceGains
from services.robot_bridge.safety import Refusal
from services.robot_bridge.trajectory import ArticulationPlan, JointInBase, min_jerk, plan_checks

Array = NDArray[np.float64]

# Robot grasp-pose noise fed to the estimator, 1-sigma per axis (docs/robot_bridge.md#closed-loop):
# Panda repeatability is 0.1 mm, but an uncalibrated arm's kinematic error is about 1 mm inside
# the workspace and the grasp itself yields (about 1 mm at 20 N on a 20 kN/m grasp).
ROBOT_POSITION_STD_M = 1.0e-3
ROBOT_ROTATION_STD_RAD = math.radians(0.5)
# The published robot body carries no measured twist (zeros): its variance says "unknown".
ROBOT_LINEAR_SPEED_STD = 1.0
ROBOT_ANGULAR_SPEED_STD = 1.0


def robot_pose_covariance() -> Array:
    """6x6 covariance of the grasp pose's left perturbation (linear first) [m^2, rad^2]."""
    return np.diag([ROBOT_POSITION_STD_M ** 2] * 3 + [ROBOT_ROTATION_STD_RAD ** 2] * 3)


def robot_body_covariance(R_frame_base: Array) -> Array:
    """12x12 covariance of the robot body (pose then twist), expressed in the model frame.

    Isotropic per block, so the rotation ``R_frame_base`` leaves it unchanged; it is accepted
    for the day a block becomes anisotropic.
    """
    del R_frame_base
    return np.diag([ROBOT_POSITION_STD_M ** 2] * 3 + [ROBOT_ROTATION_STD_RAD ** 2] * 3
                   + [ROBOT_LINEAR_SPEED_STD ** 2] * 3 + [ROBOT_ANGULAR_SPEED_STD ** 2] * 3)


@dataclass(frozen=True)
class RefinementConfig:
    """Closed-loop parameters (Hz, s, deg, m as named). Defaults: docs/robot_bridge.md#closed-loop."""

    feed_rate_hz: float = 20.0               # robot grasp poses into the estimator
    replan_rate_hz: float = 10.0             # re-plans; each blends in over ...
    blend_replans: float = 3.0               # ... this many re-plan periods (overlapping)
    engage_direction_std_deg: float = 2.0    # robot estimate used once its 1-sigma is below ...
    engage_position_std_m: float = 0.005     # ... these (direction; axis position at the grasp)
    min_type_probability: float = 0.8        # ... and P(revolute) reaches this
    max_direction_rate_deg_per_s: float = 8.0  # executed axis turns toward it at most this fast
    max_position_rate_m_per_s: float = 0.008    # executed axis point moves at most this fast
    jump_direction_deg_per_s: float = 45.0   # robot estimate faster than this: model_jump
    jump_position_m_per_s: float = 0.05
    divergence_factor: float = 3.0           # 1-sigma above this x its minimum: model_diverged
    divergence_floor_deg: float = 0.2        # ... not counted below these 1-sigma values
    divergence_floor_m: float = 0.0005
    prior_gate_sigmas: float = 3.0           # prior fused only if within this many sigmas
    compliance: bool = True                  # lower stiffness where the model is unsure
    # The grasp's own stiffness: the measured wrench deflects the part from the TCP by
    # wrench / stiffness, which is undone before the pose is fed (None: fed uncorrected). The
    # correction's error, DEFLECTION_ERROR of the deflection, is added to the pose noise.
    grasp_stiffness_n_per_m: float | None = None
    grasp_stiffness_nm_per_rad: float | None = None

    def __post_init__(self) -> None:
        for name in ("feed_rate_hz", "replan_rate_hz", "blend_replans",
                     "engage_direction_std_deg",
                     "engage_position_std_m", "max_direction_rate_deg_per_s",
                     "max_position_rate_m_per_s", "jump_direction_deg_per_s",
                     "jump_position_m_per_s", "prior_gate_sigmas"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"refinement {name} must be > 0, got {getattr(self, name)!r}")
        if not self.divergence_factor > 1.0:
            raise ValueError(f"refinement divergence_factor must be > 1, got "
                             f"{self.divergence_factor!r}")


DEFLECTION_ERROR = 0.1


def axis_belief(model: KinematicModel, T_base_frame: Array, grasp_base: Array) -> AxisBelief:
    """The model's revolute axis moved into the base frame, at the grasp ``grasp_base`` (3,)."""
    rev = model.revolute
    assert rev is not None
    R, t = T_base_frame[:3, :3], T_base_frame[:3, 3]
    a_f = np.asarray(rev.axis, float)
    a = R @ a_f
    c = R @ np.asarray(rev.point, float) + t
    s = float((grasp_base - c) @ a)
    foot = c + s * a
    # d foot = P_perp dc + s B db (the axis through c turned by B db), both in the base frame.
    C5 = np.asarray(rev.covariance, float)[:5, :5]
    B = R @ tangent_basis(a_f)
    M = np.zeros((5, 5))
    M[:2, :2] = np.eye(2)
    M[2:, :2] = s * B
    M[2:, 2:] = (np.eye(3) - np.outer(a, a)) @ R
    return AxisBelief(a, foot, M @ C5 @ M.T)


def fuse(prior: AxisBelief, robot: AxisBelief, gate_sigmas: float) -> AxisBelief:
    """Information-form fusion of two independent beliefs, or ``robot`` when they disagree.

    Four coordinates carry information: the direction's two in ``robot``'s tangent basis, and
    where each axis crosses the plane through ``robot.foot`` normal to ``robot.axis`` (two in
    that plane). Each foot's along-axis coordinate is fixed by construction (the point nearest
    the grasp), but along *its own* axis: fusing the two 3-d feet of axes a few degrees apart
    (as this function first did, with a small regulariser along each axis) pinned the result to
    the intersection of two thin slabs and extrapolated it, millimetres beyond both beliefs.
    Disagreement: the squared Mahalanobis distance beyond the ``gate_sigmas`` quantile of a
    4-dof Gaussian.
    """
    B_r = tangent_basis(robot.axis)
    sign = 1.0 if float(prior.axis @ robot.axis) >= 0.0 else -1.0
    a_p = sign * prior.axis
    # The prior's axis where it crosses the robot's plane (the prior foot moved along a_p).
    cos = float(a_p @ robot.axis)
    if cos < 0.5:  # more than 60 deg apart: nothing to fuse
        return robot
    f_p = prior.foot + (float((robot.foot - prior.foot) @ robot.axis) / cos) * a_p
    J_p = np.zeros((4, 5))
    J_p[:2, :2] = B_r.T @ tangent_basis(prior.axis) * sign
    J_p[2:, 2:] = B_r.T
    J_r = np.zeros((4, 5))
    J_r[:2, :2] = np.eye(2)
    J_r[2:, 2:] = B_r.T
    C_p = J_p @ prior.cov @ J_p.T
    C_r = J_r @ robot.cov @ J_r.T
    x_p = np.concatenate([B_r.T @ a_p, B_r.T @ (f_p - robot.foot)])  # robot's belief: 0
    try:
        d2 = float(x_p @ np.linalg.solve(C_p + C_r, x_p))
        I_p, I_r = np.linalg.inv(C_p), np.linalg.inv(C_r)
    except np.linalg.LinAlgError:
        return robot
    if not d2 <= chi2_quantile_of_sigmas(gate_sigmas, 4):
        return robot
    C_f = np.linalg.inv(I_p + I_r)
    x_f = C_f @ (I_p @ x_p)
    a = robot.axis + B_r @ x_f[:2]
    a /= np.linalg.norm(a)
    cov = J_r.T @ C_f @ J_r   # back to (b1, b2, foot): no along-axis position information
    return AxisBelief(a, robot.foot + B_r @ x_f[2:], cov)


def _turn_toward(a: Array, b: Array, max_angle: float) -> Array:
    """Unit ``a`` turned toward unit ``b`` by at most ``max_angle`` (rad)."""
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    angle = math.atan2(s, float(a @ b))
    if angle <= max_angle or s < 1e-12:
        return b.copy() if angle <= max_angle else a.copy()
    return so3_exp(axis / s * max_angle) @ a


class _Blend:
    """Minimum-jerk cross-fade from ``old`` to ``new`` over ``[t0, t0 + T]`` (poses, twists).

    ``old`` may itself be a blend still under way: re-plans overlap when ``T`` spans several
    re-plan periods, which turns the re-plans' steps into a nearly constant correction speed
    (one period per blend would move the command in a 10 Hz staircase of velocity bumps,
    which rang the grasp in simulation). :func:`_settled` drops the blends that have ended.
    """

    def __init__(self, old: ArticulationPlan | _Blend, new: ArticulationPlan, t0: float,
                 T: float) -> None:
        self.old, self.new, self.t0, self.T = old, new, t0, T

    def weight(self, t: float) -> tuple[float, float]:
        return min_jerk(t - self.t0, self.T)

    def sample(self, t: float) -> tuple[Array, Array, float]:
        T_o, tw_o, th = self.old.sample(t)
        T_n, tw_n, _ = self.new.sample(t)
        w, dw = self.weight(t)
        if w >= 1.0:
            return T_n, tw_n, th
        T = T_n.copy()
        dp = T_n[:3, 3] - T_o[:3, 3]
        T[:3, 3] = T_o[:3, 3] + w * dp
        R_rel = T_n[:3, :3] @ T_o[:3, :3].T
        phi = _so3_log(R_rel)
        T[:3, :3] = so3_exp(w * phi) @ T_o[:3, :3]
        twist = (1.0 - w) * tw_o + w * tw_n
        twist[:3] += dw * dp
        twist[3:] += dw * phi
        return T, twist, th


def _settled(path: ArticulationPlan | _Blend, t: float) -> ArticulationPlan | _Blend:
    """``path`` with every blend that has ended by ``t`` replaced by its target."""
    if not isinstance(path, _Blend):
        return path
    if t >= path.t0 + path.T:
        return path.new
    old = _settled(path.old, t)
    if old is not path.old:
        return _Blend(old, path.new, path.t0, path.T)
    return path


def _so3_log(R: Array) -> Array:
    c = max(-1.0, min(1.0, (float(np.trace(R)) - 1.0) / 2.0))
    angle = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-9:
        return 0.5 * v
    return angle / (2.0 * math.sin(angle)) * v


@dataclass(frozen=True)
class RefinementRecord:
    """What the refinement did, for results and trials (base frame, SI units)."""

    replans: int
    engaged_at_s: float | None
    prior_fused: int
    axis: Array
    foot: Array
    direction_std_rad: float
    position_std_m: float
    # At the first feed past CHECKPOINT_RAD of commanded progress: the refined model (what the
    # executed joint moves toward) and the robot's own estimate (None before it is revolute).
    checkpoint: AxisBelief | None = None
    robot_at_checkpoint: AxisBelief | None = None


CHECKPOINT_RAD = math.pi / 2   # the "after 90 deg of articulation"


class Refiner:
    """Online refinement of the executed revolute joint from the robot's grasp poses.

    ``model`` is the model being executed (``frame_id`` mapped by ``T_base_frame``), ``plan`` its
    checked plan; ``gains`` today's impedance, never exceeded (``compliance``). Call
    :meth:`tick` once per control tick, then sample the command with :meth:`sample`.
    """

    def __init__(self, model: KinematicModel, T_base_frame: Array, plan: ArticulationPlan,
                 gains: ImpedanceGains, checks: dict[str, object], dt_s: float,
                 config: RefinementConfig | None = None) -> None:
        self.config = c = config or RefinementConfig()
        self.model = model
        self.T_base_frame = np.asarray(T_base_frame, float)
        self.T_frame_base = se3_inverse(self.T_base_frame)
        self.plan = plan                     # the target path of the latest re-plan
        self._path: ArticulationPlan | _Blend = plan
        self._checks = checks
        self._grasp = plan.T_base_grasp[:3, 3].copy()
        self.prior = axis_belief(model, self.T_base_frame, self._grasp)
        self.target = self.prior             # what the executed joint moves toward
        self._axis = plan.joint.axis.copy()  # executed joint (base frame)
        self._foot = self._foot_of(plan.joint)
        self.estimator = KinematicEstimator(frame_id=model.frame_id)
        self._cov = robot_pose_covariance()
        self._feed_every = max(1, round(1.0 / (c.feed_rate_hz * dt_s)))
        self._replan_every = max(1, round(1.0 / (c.replan_rate_hz * dt_s)))
        self._replan_s = self._replan_every * dt_s
        self._blend_s = c.blend_replans * self._replan_s
        self._tick = 0
        self._last_robot: tuple[float, AxisBelief] | None = None
        self._min_dir = math.inf
        self._min_pos = math.inf
        self.engaged_at_s: float | None = None
        self.replans = 0
        self.prior_fused = 0
        self.robot_belief: AxisBelief | None = None     # engaged robot estimates only
        self._robot_any: AxisBelief | None = None       # the latest revolute robot estimate
        self._checkpoint: tuple[AxisBelief, AxisBelief | None] | None = None
        self._law = ComplianceLaw(gains) if c.compliance else None
        self._gains_old: MatrixGains | None = None
        self._gains_new: MatrixGains | None = None
        if self._law is not None:
            self._gains_new = self._gains_old = self._law.gains(self._axis, self._foot,
                                                                self._grasp, self.target, 0.0)

    def _foot_of(self, joint: JointInBase) -> Array:
        return joint.point + float((self._grasp - joint.point) @ joint.axis) * joint.axis

    # ------------------------------------------------------------------ per tick

    def tick(self, t_s: float, stamp_ns: int, T_base_ee: Array,
             wrench: Array | None = None) -> Refusal | None:
        """Feed (every ``feed_rate_hz``) and re-plan (every ``replan_rate_hz``) at ``t_s``,
        the time since the start of the plan; ``stamp_ns`` the robot's stamp of ``T_base_ee``,
        ``wrench`` (6,) the measured wrench on the end-effector (N, N m, base frame)."""
        k = self._tick
        self._tick += 1
        if k % self._feed_every == 0:
            T, cov = self.grasped_part_pose(T_base_ee, wrench)
            refusal = self._feed(t_s, stamp_ns, T, cov)
            if refusal is not None:
                return refusal
            if self._checkpoint is None and abs(self.plan.sample(t_s)[2]) >= CHECKPOINT_RAD:
                self._checkpoint = (self.target, self._robot_any)
        if k % self._replan_every == 0 and k > 0:
            return self._replan(t_s)
        return None

    def sample(self, t_s: float) -> tuple[Array, Array, float]:
        """Commanded pose (4, 4), twist (6,) and progress at ``t_s`` (the blended path)."""
        return self._path.sample(t_s)

    def gains_at(self, t_s: float) -> MatrixGains | None:
        """The stiffness to command at ``t_s`` (blended like the path), or None (no compliance)."""
        if self._gains_new is None or self._gains_old is None:
            return None
        if not isinstance(self._path, _Blend):
            return self._gains_new
        w, _ = self._path.weight(t_s)
        return self._gains_old.lerp(self._gains_new, w)

    # ------------------------------------------------------------------ evidence

    def robot_estimate(self, stamp_ns: int, T_frame_ee: Array,
                       cov: Array) -> KinematicModel | None:
        """The estimator's model after this grasp pose (None if it rejected it)."""
        return self.estimator.update(stamp_ns, T_frame_ee, cov).model

    def grasped_part_pose(self, T_base_ee: Array, wrench: Array | None) -> tuple[Array, Array]:
        """The grasped part's pose (base frame) and its covariance in the model frame: the TCP
        moved by the grasp's deflection ``wrench / stiffness`` where the stiffness is known."""
        c = self.config
        cov = self._cov
        if wrench is None or c.grasp_stiffness_n_per_m is None or \
                c.grasp_stiffness_nm_per_rad is None:
            return T_base_ee, cov
        dp = np.asarray(wrench[:3], float) / c.grasp_stiffness_n_per_m
        dr = np.asarray(wrench[3:], float) / c.grasp_stiffness_nm_per_rad
        T = T_base_ee.copy()
        T[:3, 3] = T_base_ee[:3, 3] + dp
        T[:3, :3] = so3_exp(dr) @ T_base_ee[:3, :3]
        extra = np.diag([(DEFLECTION_ERROR * float(np.linalg.norm(dp))) ** 2] * 3
                        + [(DEFLECTION_ERROR * float(np.linalg.norm(dr))) ** 2] * 3)
        return T, cov + extra

    def _feed(self, t_s: float, stamp_ns: int, T_base_ee: Array,
              cov: Array | None = None) -> Refusal | None:
        c = self.config
        model = self.robot_estimate(stamp_ns, self.T_frame_base @ T_base_ee,
                                    self._cov if cov is None else cov)
        if model is None or model.type != "revolute" or model.revolute is None:
            return None
        if float(model.probabilities.get("revolute", 0.0)) < c.min_type_probability:
            return None
        robot = axis_belief(model, self.T_base_frame, self._grasp)
        if float(robot.axis @ self.prior.axis) < 0.0:
            robot = AxisBelief(-robot.axis, robot.foot, robot.cov)
        self._robot_any = robot
        d_std, p_std = robot.direction_std(), robot.position_std()
        if self.engaged_at_s is None:
            if d_std > math.radians(c.engage_direction_std_deg) or p_std > c.engage_position_std_m:
                return None
            self.engaged_at_s = t_s
        if self._last_robot is not None:
            t_prev, prev = self._last_robot
            dt = max(t_s - t_prev, 1e-6)
            turn = math.acos(max(-1.0, min(1.0, float(prev.axis @ robot.axis)))) / dt
            move = float(np.linalg.norm(robot.foot - prev.foot)) / dt
            if turn > math.radians(c.jump_direction_deg_per_s) or move > c.jump_position_m_per_s:
                return Refusal("model_jump",
                               f"refined axis moved {math.degrees(turn):.1f} deg/s, "
                               f"{move * 1e3:.1f} mm/s (bounds {c.jump_direction_deg_per_s:g} "
                               f"deg/s, {c.jump_position_m_per_s * 1e3:g} mm/s)")
        self._min_dir = min(self._min_dir, max(d_std, math.radians(c.divergence_floor_deg)))
        self._min_pos = min(self._min_pos, max(p_std, c.divergence_floor_m))
        if d_std > c.divergence_factor * self._min_dir or p_std > c.divergence_factor * self._min_pos:
            return Refusal("model_diverged",
                           f"refined axis 1-sigma grew to {math.degrees(d_std):.2f} deg, "
                           f"{p_std * 1e3:.2f} mm (minimum {math.degrees(self._min_dir):.2f} deg, "
                           f"{self._min_pos * 1e3:.2f} mm; factor {c.divergence_factor:g})")
        self._last_robot = (t_s, robot)
        self.robot_belief = robot
        fused = fuse(self.prior, robot, c.prior_gate_sigmas)
        if fused is not robot:
            self.prior_fused += 1
        self.target = fused
        return None

    # ------------------------------------------------------------------ re-plan

    def _replan(self, t_s: float) -> Refusal | None:
        c = self.config
        self._path = _settled(self._path, t_s)
        self._axis = _turn_toward(self._axis, self.target.axis,
                                  math.radians(c.max_direction_rate_deg_per_s) * self._replan_s)
        step = self.target.foot - self._foot
        n = float(np.linalg.norm(step))
        limit = c.max_position_rate_m_per_s * self._replan_s
        self._foot = self._foot + (step if n <= limit else step * (limit / n))
        joint = JointInBase("revolute", self._axis.copy(), self._foot.copy())
        new = replace(self.plan, joint=joint)
        refusal = plan_checks(new, **self._checks)  # type: ignore[arg-type]
        if refusal is not None:
            return Refusal(refusal.reason, f"re-planned path: {refusal.detail}")
        if self._law is not None:
            # from the stiffness commanded now (a blend may be under way): continuous
            self._gains_old = self.gains_at(t_s)
        self._path = _Blend(self._path, new, t_s, self._blend_s)
        self.plan = new
        self.replans += 1
        if self._law is not None:
            theta = new.sample(t_s + self._blend_s)[2]
            self._gains_new = self._law.gains(self._axis, self._foot, self._grasp, self.target,
                                              theta)
        return None

    def record(self) -> RefinementRecord:
        at = self._checkpoint
        return RefinementRecord(self.replans, self.engaged_at_s, self.prior_fused,
                                self._axis.copy(), self._foot.copy(),
                                self.target.direction_std(), self.target.position_std(),
                                None if at is None else at[0], None if at is None else at[1])


def robot_body(stamp_ns: int, frame_id: str, T_frame_base: Array, T_base_ee: Array,
               twist_base: Array) -> object:
    """The grasp pose as a ``HandBody`` (``handkse/{rig}/robot/body``, docs/protocol.md).

    ``T_frame_base`` maps the base frame into ``frame_id`` (the inverse of ``T_base_camera``);
    ``twist_base`` (6,) the TCP twist ``[v, w]`` in the base frame. Motion model ``kinematic``,
    no landmarks (all NaN, status 0), covariance :func:`robot_body_covariance`.
    """
    from services.common.protocol import NUM_LANDMARKS, HandBody, LandmarkStates

    R = T_frame_base[:3, :3]
    twist = np.concatenate([R @ np.asarray(twist_base[:3], float),
                            R @ np.asarray(twist_base[3:], float)])
    landmarks = LandmarkStates(points=np.full((NUM_LANDMARKS, 3), np.nan, np.float32),
                               variance=np.full(NUM_LANDMARKS, np.nan, np.float32),
                               status=np.zeros(NUM_LANDMARKS, np.uint8))
    return HandBody(stamp_ns=int(stamp_ns), frame_id=frame_id, initialized=True,
                    pose=T_frame_base @ T_base_ee, twist=twist,
                    covariance=robot_body_covariance(R), motion_model="kinematic",
                    landmarks=landmarks)
