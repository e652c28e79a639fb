"""Real-robot backend: a Franka Emika Panda through panda-python (``panda_py``).

The trajectory is streamed at 1 kHz to panda-py's C++ ``CartesianImpedance`` torque controller,
which runs the same Jacobian-transpose law as the simulation
(:mod:`services.robot_bridge.controller`) inside libfranka's real-time loop, so Python jitter
only delays a target update, never a torque. panda-py's controller has no velocity
feed-forward; :func:`~services.robot_bridge.controller.lead_target` shifts each target by
``K^-1 D v_d`` instead, which gives the same torques. libfranka limits the torque rate
(``limit_rate``) and panda-py clips torques to Franka's limits.

Safety: Franka's collision reflexes are raised above the bridge's limits at construction
(``reflex_*`` in the config, above the 70 N force limit), so the software checks in
:func:`services.robot_bridge.executor.execute` abort first and hold the pose gently instead of
triggering a reflex stop. The external wrench is libfranka's model-based estimate
``O_F_ext_hat_K`` (base frame); libfranka reports it as the wrench the robot exerts on the
environment (libfranka issue #26), so it is negated here into the wrench acting on the
end-effector. It has offsets of a few newtons: :meth:`zero_wrench` is called right after the
grasp. ``panda_py`` is never imported here: the factory passes in the ``Panda`` object and the
``panda_py.controllers`` module (tests pass fakes).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.robot_bridge.backend import BackendError, BackendState
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.controller import ImpedanceGains, lead_target, quat_xyzw_from_matrix
from services.robot_bridge.panda_scene import TAU_MAX_NM
from services.robot_bridge.safety import clamp_twist

log = logging.getLogger(__name__)

Array = NDArray[np.float64]

CONTROL_RATE_HZ = 1000.0
# A joint counts as saturated when its commanded torque is within this fraction of its limit.
_SATURATION_FRACTION = 0.999


def pose_from_franka(O_T_EE: Any) -> Array:
    """4x4 pose from libfranka's column-major 16-element array."""
    return np.asarray(O_T_EE, float).reshape(4, 4).T.copy()


class PandaPyBackend:
    """The :class:`~services.robot_bridge.backend.RobotBackend` on a real Panda."""

    name = "panda"
    object_axis_base: Array | None = None

    def __init__(self, panda: Any, controllers: Any, config: RobotBridgeConfig) -> None:
        """``panda``: a connected ``panda_py.Panda``; ``controllers``: ``panda_py.controllers``."""
        self.panda = panda
        self.controllers = controllers
        self.config = config
        self.control_period_s = 1.0 / CONTROL_RATE_HZ
        self.gains = config.gains()
        self._ctrl: Any = None
        self._ctx: Any = None
        self._wrench_offset = np.zeros(6)
        self._q_null = np.zeros(7)
        self._set_reflexes()
        self._state = self._read_robot()

    def _set_reflexes(self) -> None:
        """Raise Franka's collision thresholds above the software limits (see module doc)."""
        c = self.config
        tj = c.reflex_joint_torque_threshold_nm
        torques = [tj] * 4 + [tj * 2.0 / 3.0] * 3
        forces = [c.reflex_force_threshold_n] * 3 + [c.reflex_torque_threshold_nm] * 3
        self.panda.get_robot().set_collision_behavior(torques, torques, forces, forces)
        log.info("Franka reflexes: joint torques %s N m, Cartesian %s N / N m", torques, forces)

    def _read_robot(self) -> BackendState:
        s = self.panda.get_state()
        tau = np.asarray(s.tau_J_d, float)
        raw = -np.asarray(s.O_F_ext_hat_K, float)
        return BackendState(
            t_s=float(s.time.to_sec()), q=np.asarray(s.q, float), dq=np.asarray(s.dq, float),
            T_base_ee=pose_from_franka(s.O_T_EE), wrench=raw - self._wrench_offset, tau=tau,
            saturated=bool((np.abs(tau) >= _SATURATION_FRACTION * TAU_MAX_NM).any()))

    # --- RobotBackend ---

    def read(self) -> BackendState:
        """While articulating: the state of the last tick; when idle: a fresh read."""
        if self._ctx is None:
            self._state = self._read_robot()
        return self._state

    def start(self, gains: ImpedanceGains) -> None:
        """Start ``CartesianImpedance`` (no target filtering: the bridge streams at 1 kHz)."""
        if self._ctrl is not None:
            self.stop()
        self.gains = gains
        self._state = self._read_robot()
        self._q_null = self._state.q.copy()
        self._ctrl = self.controllers.CartesianImpedance(
            impedance=gains.panda_py_impedance(), damping_ratio=gains.damping_ratio,
            nullspace_stiffness=gains.nullspace_nm_per_rad, filter_coeff=1.0)
        self.panda.start_controller(self._ctrl)
        self._ctx = self.panda.create_context(frequency=CONTROL_RATE_HZ)
        self._ctx.__enter__()
        self.hold()

    def command(self, T_base_target: Array, twist_target: Array | None = None) -> Array:
        if self._ctrl is None:
            raise BackendError("command before start(): no controller is running")
        c = self.config
        sent = (np.zeros(6) if twist_target is None
                else clamp_twist(twist_target, c.max_linear_speed_m_per_s,
                                 c.max_angular_speed_rad_per_s))
        T = lead_target(T_base_target, sent, self.gains) if twist_target is not None \
            else T_base_target
        self._ctrl.set_control(np.ascontiguousarray(T[:3, 3]), quat_xyzw_from_matrix(T[:3, :3]),
                               self._q_null)
        return sent

    def step(self) -> None:
        """Wait for the next 1 kHz tick and read the state the control loop stored."""
        if self._ctx is None:
            raise BackendError("step before start(): no controller is running")
        try:
            ok = self._ctx.ok()
        except Exception as exc:  # panda-py re-raises the control loop's libfranka error here
            self._ctx = None
            self._ctrl = None
            raise BackendError(f"robot stopped: {exc}") from exc
        if not ok:
            raise BackendError("control context ended")
        self._state = self._read_robot()

    def zero_wrench(self) -> None:
        raw = self._state.wrench + self._wrench_offset
        self._wrench_offset = raw.copy()
        self._state = self._read_robot()

    def hold(self) -> None:
        if self._ctrl is not None:
            T = self._state.T_base_ee
            self._ctrl.set_control(np.ascontiguousarray(T[:3, 3]),
                                   quat_xyzw_from_matrix(T[:3, :3]), self._q_null)

    def stop(self) -> None:
        """Hold the measured pose, then end the torque controller (the robot holds itself)."""
        if self._ctrl is not None:
            self.hold()
            try:
                self.panda.stop_controller()
            finally:
                self._ctrl = None
                self._ctx = None

    def close(self) -> None:
        self.stop()
