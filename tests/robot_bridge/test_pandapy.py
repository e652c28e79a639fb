"""``PandaPyBackend`` against a fake of panda-python: command sequence and safety handling."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.controller import lead_target, quat_xyzw_from_matrix
from services.robot_bridge.executor import execute
from services.robot_bridge.factory import make_backend
from services.robot_bridge.pandapy_backend import PandaPyBackend, pose_from_franka
from services.robot_bridge.trajectory import ArticulationPlan, JointInBase
from tests.robot_bridge import fake_panda_py
from tests.robot_bridge.fake_panda_py import CartesianImpedance, FakePanda

CONFIG = RobotBridgeConfig(settle_s=0.05)


def _backend(panda: FakePanda, config: RobotBridgeConfig = CONFIG) -> PandaPyBackend:
    return PandaPyBackend(panda, fake_panda_py.controllers, config)


def _names(panda: FakePanda) -> list[str]:
    return [name for name, _ in panda.calls]


def _slide_plan(backend: PandaPyBackend, amount: float = 0.05, duration_s: float = 0.5
                ) -> ArticulationPlan:
    T0 = backend.read().T_base_ee.copy()
    return ArticulationPlan(JointInBase("prismatic", T0[:3, 1].copy(), T0[:3, 3].copy()), T0,
                            amount, duration_s, hold_s=0.05)


def test_reflexes_are_raised_above_the_software_limits() -> None:
    panda = FakePanda()
    _backend(panda)
    (name, args), = panda.calls
    assert name == "set_collision_behavior"
    lower_tau, upper_tau, lower_f, upper_f = args
    assert len(lower_tau) == len(upper_tau) == 7 and len(lower_f) == len(upper_f) == 6
    assert min(upper_f[:3]) > CONFIG.force_limit_n
    assert min(upper_f[3:]) > CONFIG.wrist_torque_limit_nm


def test_state_conversion_and_wrench_zeroing() -> None:
    panda = FakePanda(bias=np.array([3.0, -2.0, 1.0, 0.2, 0.0, -0.1]))
    be = _backend(panda)
    s = be.read()
    assert np.allclose(s.T_base_ee, panda.pose)
    assert np.allclose(pose_from_franka(list(panda.pose.T.reshape(-1))), panda.pose)
    # libfranka's O_F_ext_hat_K is negated into the wrench acting on the end-effector
    assert np.allclose(s.wrench, panda.bias)
    be.zero_wrench()
    assert np.allclose(be.read().wrench, 0.0)


def test_command_sequence_of_a_successful_articulation() -> None:
    CartesianImpedance.instances.clear()
    panda = FakePanda()
    be = _backend(panda)
    plan = _slide_plan(be)
    ex = execute(be, plan, CONFIG)
    assert ex.success, (ex.reason, ex.detail)
    assert ex.articulated == pytest.approx(0.05, abs=2e-3)  # estimated from the TCP pose
    names = _names(panda)
    assert names[:3] == ["set_collision_behavior", "start_controller", "create_context"]
    assert names[-1] == "stop_controller" and names.count("stop_controller") == 1
    ctrl, = CartesianImpedance.instances
    gains = CONFIG.gains()
    assert np.allclose(np.diag(ctrl.impedance), [1000.0] * 3 + [100.0] * 3)
    assert ctrl.damping_ratio == CONFIG.damping_ratio
    assert ctrl.nullspace_stiffness == CONFIG.nullspace_stiffness_nm_per_rad
    assert ctrl.filter_coeff == 1.0
    assert panda.calls[2][1] == (1000.0,)
    # one target per control tick, each the lead target of the plan sample
    n_ticks = round(plan.total_s / be.control_period_s)
    assert len(ctrl.targets) >= n_ticks
    i = n_ticks // 2
    T_d, twist, _ = plan.sample(i * be.control_period_s)
    lead = lead_target(T_d, twist, gains)
    streamed = ctrl.targets[1 + i]  # the first set_control is the hold at start
    assert np.allclose(streamed[0], lead[:3, 3])
    assert np.allclose(np.abs(streamed[1] @ quat_xyzw_from_matrix(lead[:3, :3])), 1.0)
    assert np.allclose(streamed[2], be.read().q)  # null-space posture = start posture


def test_force_limit_aborts_holds_and_stops_the_controller() -> None:
    CartesianImpedance.instances.clear()
    T0 = FakePanda().pose

    def wall(p: np.ndarray) -> np.ndarray:
        """A stiff wall 2 cm along the slide: 5000 N/m beyond it."""
        depth = float((p - T0[:3, 3]) @ T0[:3, 1]) - 0.02
        f = np.zeros(6)
        f[:3] = -5000.0 * max(depth, 0.0) * T0[:3, 1]
        return f

    panda = FakePanda(force_fn=wall, bias=np.array([4.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    be = _backend(panda)
    ex = execute(be, _slide_plan(be), CONFIG)
    assert not ex.success and ex.reason == "force_limit"
    assert CONFIG.force_limit_n < ex.peak_force_n < CONFIG.force_limit_n + 10.0
    ctrl, = CartesianImpedance.instances
    # targets: the hold at start, one per tick up to the abort, then only holds of the pose
    # measured at the abort (no more streaming during the settle time)
    stop_tick = round(ex.trace.stopped_at_s / be.control_period_s)
    assert len(ctrl.targets) == stop_tick + 3
    assert np.allclose(ctrl.targets[-1][0], ctrl.targets[-2][0])
    assert np.allclose(ctrl.targets[-1][0], panda.pose[:3, 3])  # the measured pose
    assert _names(panda)[-1] == "stop_controller"


def _spring(k: float, torque: bool = False):  # type: ignore[no-untyped-def]
    """External wrench growing with the TCP's displacement from its start (k per metre)."""
    p0 = FakePanda().pose[:3, 3].copy()

    def fn(p: np.ndarray) -> np.ndarray:
        f = np.zeros(6)
        f[4 if torque else 0] = k * float(np.linalg.norm(p - p0))
        return f

    return fn


def test_a_lower_request_limit_is_honoured_but_never_a_higher_one() -> None:
    be = _backend(FakePanda(force_fn=_spring(1000.0)))  # 50 N at the end of the 5 cm slide
    assert execute(be, _slide_plan(be), CONFIG).success
    be = _backend(FakePanda(force_fn=_spring(1000.0)))
    ex = execute(be, _slide_plan(be), CONFIG, force_limit_n=40.0)
    assert ex.reason == "force_limit" and ex.peak_force_n < 42.0
    be = _backend(FakePanda(force_fn=_spring(2000.0)))  # 100 N at the end
    ex = execute(be, _slide_plan(be), CONFIG, force_limit_n=500.0)
    assert ex.reason == "force_limit" and ex.peak_force_n < 72.0


def test_robot_error_is_reported_not_raised() -> None:
    panda = FakePanda(error_at_tick=100)
    be = _backend(panda)
    ex = execute(be, _slide_plan(be), CONFIG)
    assert not ex.success and ex.reason == "robot_error"
    assert "reflex" in ex.detail
    assert ex.trace.stopped_at_s == pytest.approx(0.099, abs=0.002)


def test_wrist_torque_and_saturation_abort() -> None:
    be = _backend(FakePanda(force_fn=_spring(300.0, torque=True)))  # 15 N m at 5 cm
    assert execute(be, _slide_plan(be), CONFIG).reason == "torque_limit"

    class Saturating(FakePanda):
        def get_state(self):  # type: ignore[no-untyped-def]
            s = super().get_state()
            s.tau_J_d = [0.0, 0.0, 0.0, 0.0, 12.0, 0.0, 0.0]
            return s

    panda = Saturating()
    be = _backend(panda)
    assert execute(be, _slide_plan(be), CONFIG).reason == "torque_saturation"


def test_factory_is_safe_by_default() -> None:
    with pytest.raises(ValueError, match="robot_host"):
        make_backend(RobotBridgeConfig(backend="panda"))
    with pytest.raises(ValueError, match="hand-eye"):
        make_backend(RobotBridgeConfig(backend="panda", robot_host="172.16.0.2"))
    calibrated = RobotBridgeConfig(backend="panda", robot_host="172.16.0.2", T_base_camera=(
        0.0, -1.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.8, 0.0, 0.0, 0.0, 1.0))
    if importlib.util.find_spec("panda_py") is None:
        with pytest.raises(ValueError, match="panda-python"):
            make_backend(calibrated)


def test_command_before_start_is_an_error() -> None:
    from services.robot_bridge.backend import BackendError

    be = _backend(FakePanda())
    with pytest.raises(BackendError):
        be.command(np.eye(4))
    with pytest.raises(BackendError):
        be.step()
    be.close()  # closing an idle backend is harmless
    assert math.isfinite(be.read().t_s)
