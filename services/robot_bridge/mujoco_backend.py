"""Simulated backend: the generated Panda + one articulated object in MuJoCo, torque-controlled.

Every 1 ms control tick (``step``) runs ``mj_step1`` (kinematics and velocities of the tick),
then, in numpy, the Jacobian-transpose impedance law of :mod:`services.robot_bridge.controller`
exactly as the real robot runs it, plus gravity and Coriolis compensation from ``qfrc_bias``
(simulation only: the real Panda compensates gravity itself), then the pure torque clamp of
:mod:`services.robot_bridge.safety` (Franka's torque and torque-rate limits), and the grasp:
a 6-D spring-damper between the TCP and the object's handle applied through ``xfrc_applied``
(equal and opposite), then ``mj_step2``. The grasp spring's wrench on the TCP is the simulated
wrist force/torque reading (an ideal F/T sensor at the TCP).

The grasp is made at ``reset``: the robot is placed (by inverse kinematics unless a
configuration is given) with its TCP on the handle frame, and the spring's rest offset is the
relative pose at that moment. Frames: base = MuJoCo world; SI units throughout.
"""

from __future__ import annotations

import math
from functools import lru_cache

import mujoco
import numpy as np
from numpy.typing import NDArray

from services.robot_bridge.backend import BackendError, BackendState
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.controller import ImpedanceGains, impedance_torque, orientation_error
from services.robot_bridge.panda_scene import (
    Q_GRASP_RAD,
    Q_MAX_RAD,
    Q_MIN_RAD,
    TAU_MAX_NM,
    TAU_RATE_MAX_NM_PER_S,
    ObjectSpec,
    scene_xml,
)
from services.robot_bridge.safety import Refusal, clamp_torque, clamp_twist
from services.robot_bridge.trajectory import ArticulationPlan, cross3

Array = NDArray[np.float64]

WINDOW_LOCK_LEVER_M = 0.06   # handle 6 cm from the axis
BOLT_STROKE_M = 0.035        # full stroke of the sliding bolt
TIMESTEP_S = 0.001
_EYE4 = np.eye(4)
_BADQACC = int(mujoco.mjtWarning.mjWARN_BADQACC)


@lru_cache(maxsize=1)
def _arm_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(scene_xml(None, TIMESTEP_S))


def forward_kinematics(q: Array) -> Array:
    """TCP pose ``T_base_tcp`` (4x4) of the generated Panda at joint angles ``q`` (7,)."""
    m = _arm_model()
    d = mujoco.MjData(m)
    d.qpos[:7] = q
    mujoco.mj_kinematics(m, d)
    sid = m.site("tcp").id
    T = np.eye(4)
    T[:3, :3] = d.site_xmat[sid].reshape(3, 3)
    T[:3, 3] = d.site_xpos[sid]
    return T


def solve_ik(m: mujoco.MjModel, d: mujoco.MjData, T_target: Array, q_seed: Array,
             iterations: int = 300, tolerance: float = 1e-7) -> Array:
    """Joint angles (7,) putting the TCP at ``T_target``: damped least squares from a seed,
    clipped to the joint ranges. Overwrites ``d.qpos[:7]``.

    Raises ``ValueError`` when no solution within 1 mm / 0.01 rad is found.
    """
    site = m.site("tcp").id
    jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    q = np.array(q_seed, float)
    err = np.zeros(6)
    for i in range(iterations + 1):
        d.qpos[:7] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)  # mj_jacSite needs it (docs/robot_bridge.md#simulation)
        err[:3] = T_target[:3, 3] - d.site_xpos[site]
        err[3:] = orientation_error(T_target[:3, :3], d.site_xmat[site].reshape(3, 3))
        if float(err @ err) < tolerance**2 or i == iterations:
            break
        mujoco.mj_jacSite(m, d, jacp, jacr, site)
        J = np.vstack([jacp[:, :7], jacr[:, :7]])
        dq = J.T @ np.linalg.solve(J @ J.T + 1e-4 * np.eye(6), err)
        q = np.clip(q + dq, Q_MIN_RAD, Q_MAX_RAD)
    if np.linalg.norm(err[:3]) > 1e-3 or np.linalg.norm(err[3:]) > 1e-2:
        raise ValueError(f"no joint configuration reaches the pose (residual "
                         f"{np.linalg.norm(err[:3]) * 1e3:.1f} mm, "
                         f"{math.degrees(np.linalg.norm(err[3:])):.1f} deg)")
    return q


def path_joint_check(plan: ArticulationPlan, q_start: Array, margin_rad: float,
                     waypoints: int = 30) -> Refusal | None:
    """``joint_limits`` when the planned TCP path needs a joint within ``margin_rad`` of its
    range (or beyond it), by inverse kinematics along the path from ``q_start`` on the generated
    Panda model (the kinematics the real arm has too). About 10 ms for 30 waypoints."""
    m = _arm_model()
    d = mujoco.MjData(m)
    q = np.asarray(q_start, float)
    for t in np.linspace(0.0, plan.duration_s, waypoints):
        T, _, progress = plan.sample(float(t))
        try:
            q = solve_ik(m, d, T, q, iterations=60)
        except ValueError:
            return Refusal("joint_limits", f"the planned path leaves the arm's joint ranges at "
                                           f"{progress:.3f} of {plan.amount:.3f}: articulate "
                                           "less, or grasp from another side")
        margin = np.minimum(q - Q_MIN_RAD, Q_MAX_RAD - q)
        if float(margin.min()) < margin_rad:
            j = int(np.argmin(margin))
            return Refusal("joint_limits", f"joint {j + 1} comes within "
                                           f"{math.degrees(max(float(margin[j]), 0.0)):.1f} deg of "
                                           f"its limit at {progress:.3f} of {plan.amount:.3f}"
                                           ": articulate less, or grasp from another side")
    return None


def nominal_grasp_pose() -> Array:
    """TCP pose at :data:`Q_GRASP_RAD`, where the preset objects are placed (approach = TCP z)."""
    return forward_kinematics(Q_GRASP_RAD)


def preset_object(name: str, T_base_handle: Array | None = None) -> ObjectSpec:
    """One of the simulated objects, grasped at ``T_base_handle`` (default: nominal grasp).

    - ``key``: revolute about the approach axis (TCP z) through the grasp point;
    - ``window_lock``: revolute about the approach axis, handle 6 cm from it along TCP x;
    - ``bolt``: prismatic along TCP y, stroke 3.5 cm.
    """
    T = nominal_grasp_pose() if T_base_handle is None else np.asarray(T_base_handle, float)
    p, x, y, z = T[:3, 3], T[:3, 0], T[:3, 1], T[:3, 2]
    if name == "key":
        return ObjectSpec("key", "revolute", z.copy(), p.copy(), T, armature=1e-3)
    if name == "window_lock":
        return ObjectSpec("window_lock", "revolute", z.copy(), p - WINDOW_LOCK_LEVER_M * x, T,
                          armature=2e-3)
    if name == "bolt":
        return ObjectSpec("bolt", "prismatic", y.copy(), p.copy(), T,
                          range=(-0.002, BOLT_STROKE_M + 0.002), armature=0.2, damping=2.0,
                          frictionloss=1.0)
    raise ValueError(f"unknown simulated object {name!r}; known: key, window_lock, bolt")


class MujocoBackend:
    """The :class:`~services.robot_bridge.backend.RobotBackend` in simulation."""

    name = "mujoco"

    def __init__(self, obj: ObjectSpec | None, config: RobotBridgeConfig | None = None,
                 q_init: Array | None = None) -> None:
        self.config = config or RobotBridgeConfig()
        self.obj = obj
        self.model = mujoco.MjModel.from_xml_string(scene_xml(obj, TIMESTEP_S))
        self.data = mujoco.MjData(self.model)
        self.control_period_s = float(self.model.opt.timestep)
        m = self.model
        self._site = m.site("tcp").id
        d = self.data
        # Views into MjData, made once (attribute access builds a new array every time).
        self._site_xpos = d.site_xpos[self._site]
        self._site_xmat = d.site_xmat[self._site]
        self._qpos7 = d.qpos[:7]
        self._qvel7 = d.qvel[:7]
        self._bias7 = d.qfrc_bias[:7]
        self._ctrl7 = d.ctrl[:7]
        self._xfrc = d.xfrc_applied
        self._tcp_body = m.body("tcp").id
        self.object_axis_base: Array | None = None
        if obj is not None:
            self._handle_body = m.body("handle").id
            self._obj_qadr = int(m.jnt_qposadr[m.joint("object_joint").id])
            self._obj_dadr = int(m.jnt_dofadr[m.joint("object_joint").id])
            self.object_axis_base = np.asarray(obj.axis_base, float).copy()
            self._axis = self.object_axis_base
            self._revolute = obj.joint_type == "revolute"
            self._obj_point = np.asarray(obj.point_base, float).copy()
        c = self.config
        self._k_grasp = np.array([c.grasp_stiffness_n_per_m] * 3 + [c.grasp_stiffness_nm_per_rad] * 3)
        self._d_grasp = np.array([c.grasp_damping_n_s_per_m] * 3
                                 + [c.grasp_damping_nm_s_per_rad] * 3)
        self._jacp = np.zeros((3, m.nv))
        self._jacr = np.zeros((3, m.nv))
        self._J = np.zeros((6, 7))
        self.gains = c.gains()
        if q_init is None:
            seed = Q_GRASP_RAD
            q_init = seed if obj is None else self.solve_ik(obj.T_base_handle, seed)
        self.reset(np.asarray(q_init, float))

    # --- setup ---

    def solve_ik(self, T_target: Array, q_seed: Array, iterations: int = 300) -> Array:
        """Joint angles (7,) putting the TCP at ``T_target`` (see :func:`solve_ik`; works on a
        scratch copy, the simulation state is untouched)."""
        return solve_ik(self.model, mujoco.MjData(self.model), T_target, q_seed, iterations)

    def reset(self, q: Array) -> None:
        """Place the arm at ``q`` at rest, the object at 0, and close the grasp (spring rest)."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:7] = q
        mujoco.mj_forward(m, d)
        self._tau = np.array(d.qfrc_bias[:7])  # holding torque: gravity compensation
        self._T_ee = self._tcp_pose()
        self._T_target = self._T_ee.copy()
        self._twist_target: Array | None = None
        self._q_null = np.array(q)
        self._wrench = np.zeros(6)
        self._wrench_offset = np.zeros(6)
        self._saturated = False
        self._t = 0.0
        if self.obj is not None:
            T_h = self._handle_pose()
            R_t = self._T_ee[:3, :3]
            self._grasp_R = R_t.T @ T_h[:3, :3]                       # handle in TCP frame
            self._grasp_p = R_t.T @ (T_h[:3, 3] - self._T_ee[:3, 3])  # handle origin, TCP frame
            if np.linalg.norm(self._grasp_p) > 0.005:
                raise ValueError(f"the TCP is {np.linalg.norm(self._grasp_p) * 1e3:.1f} mm from "
                                 "the handle: not a grasp")
        self._state = self._make_state(np.array(d.qpos[:7]), np.array(d.qvel[:7]))

    def _tcp_pose(self) -> Array:
        T = _EYE4.copy()
        T[:3, :3] = self._site_xmat.reshape(3, 3)
        T[:3, 3] = self._site_xpos
        return T

    def _handle_pose(self) -> Array:
        T = _EYE4.copy()
        T[:3, :3] = self.data.xmat[self._handle_body].reshape(3, 3)
        T[:3, 3] = self.data.xpos[self._handle_body]
        return T

    def _make_state(self, q: Array, dq: Array) -> BackendState:
        joint = pose = None
        if self.obj is not None:
            joint = float(self.data.qpos[self._obj_qadr])
            pose = self._handle_pose()
        return BackendState(t_s=self._t, q=q, dq=dq, T_base_ee=self._T_ee.copy(),
                            wrench=self._wrench - self._wrench_offset, tau=self._tau.copy(),
                            saturated=self._saturated, object_joint=joint, object_pose=pose)

    # --- RobotBackend ---

    def read(self) -> BackendState:
        return self._state

    def start(self, gains: ImpedanceGains) -> None:
        self.gains = gains
        self.hold()
        self._q_null = np.array(self.data.qpos[:7])

    def command(self, T_base_target: Array, twist_target: Array | None = None) -> Array:
        c = self.config
        sent = (np.zeros(6) if twist_target is None
                else clamp_twist(twist_target, c.max_linear_speed_m_per_s,
                                 c.max_angular_speed_rad_per_s))
        self._T_target = T_base_target
        self._twist_target = sent
        return sent

    def step(self) -> None:
        m, d = self.model, self.data
        mujoco.mj_step1(m, d)
        q = self._qpos7.copy()
        dq = self._qvel7.copy()
        self._T_ee = T = self._tcp_pose()
        mujoco.mj_jacSite(m, d, self._jacp, self._jacr, self._site)
        J = self._J
        J[:3] = self._jacp[:, :7]
        J[3:] = self._jacr[:, :7]
        tau, _ = impedance_torque(J, q, dq, T, self._T_target, self._twist_target, self._q_null,
                                  self.gains)
        cmd = clamp_torque(tau + self._bias7, self._tau, self.control_period_s, TAU_MAX_NM,
                           TAU_RATE_MAX_NM_PER_S)
        self._tau = cmd.tau
        self._saturated = cmd.saturated
        self._ctrl7[:] = cmd.tau
        if self.obj is not None:
            self._apply_grasp(T, J @ dq)
        self._state = self._make_state(q, dq)
        mujoco.mj_step2(m, d)
        self._t += self.control_period_s
        if d.warning[_BADQACC].number or not math.isfinite(float(d.qacc.sum())):
            raise BackendError(f"simulation diverged at t = {self._t:.3f} s (bad accelerations)")

    def _apply_grasp(self, T_ee: Array, ee_twist: Array) -> None:
        """Grasp spring-damper: wrench on the TCP (and its opposite on the handle)."""
        d = self.data
        hb = self._handle_body
        p_h = d.xpos[hb]
        R_h = d.xmat[hb].reshape(3, 3)
        R_t = T_ee[:3, :3]
        qd = float(d.qvel[self._obj_dadr])
        a = self._axis
        dv = np.empty(6)
        if self._revolute:
            w_h = qd * a
            dv[:3] = cross3(w_h, p_h - self._obj_point)
            dv[3:] = w_h
        else:
            dv[:3] = qd * a
            dv[3:] = 0.0
        dv -= ee_twist
        e = np.empty(6)
        e[:3] = p_h - T_ee[:3, 3] - R_t @ self._grasp_p
        e[3:] = orientation_error(R_h, R_t @ self._grasp_R)
        w = self._k_grasp * e + self._d_grasp * dv
        self._wrench = w
        self._xfrc[self._tcp_body] = w
        self._xfrc[hb] = -w

    def zero_wrench(self) -> None:
        self._wrench_offset = self._wrench.copy()
        self._state = self._make_state(self._state.q, self._state.dq)

    def hold(self) -> None:
        self._T_target = self._T_ee.copy()
        self._twist_target = None

    def stop(self) -> None:
        self.hold()

    def close(self) -> None:
        """Nothing to release in simulation."""
