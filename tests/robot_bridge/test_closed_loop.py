"""Closed-loop articulation in simulation: refinement, re-planning, compliance, aborts, robot/body."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.protocol import HandBody
from services.evaluation.robot_perturbations import run_case
from services.robot_bridge import refinement as rf


@pytest.fixture(scope="module")
def key_10deg_10mm() -> tuple[object, object]:
    """Open and closed loop on the key with its axis tilted 10 deg and moved 10 mm."""
    return run_case("key", 10.0, 10.0, 0, 10, closed=False), run_case("key", 10.0, 10.0, 0, 10,
                                                                       closed=True)


def test_closed_loop_succeeds_with_less_force_and_a_better_axis(key_10deg_10mm) -> None:
    (open_row, _), (closed_row, sim) = key_10deg_10mm
    assert closed_row.success, closed_row.reason
    assert closed_row.peak_force_n < open_row.peak_force_n
    assert closed_row.mean_force_n < open_row.mean_force_n
    # Refined axis ends closer to the truth than the perturbed start (10 deg, 10 mm).
    assert closed_row.final_axis_error_deg < 1.0 < open_row.final_axis_error_deg
    assert closed_row.final_position_error_mm < 1.0 < open_row.final_position_error_mm
    assert sim.execution.refinement.replans > 0
    assert sim.execution.refinement.engaged_at_s is not None


def test_replanned_command_is_continuous(key_10deg_10mm) -> None:
    """Second differences of consecutive commanded positions stay at the open-loop plan's scale:
    a 1 mm step at one re-plan would show as 1e-3 m; the minimum-jerk blends keep them tiny."""
    (_, open_sim), (_, closed_sim) = key_10deg_10mm
    d2_open = np.abs(np.diff(np.asarray(open_sim.execution.trace.command_position), 2, axis=0))
    d2_closed = np.abs(np.diff(np.asarray(closed_sim.execution.trace.command_position), 2,
                               axis=0))
    assert d2_closed.max() < 1e-5
    assert d2_closed.max() < 50.0 * max(d2_open.max(), 1e-7)
    # Bounded jerk: third differences over the 1 ms tick. A 1 um step anywhere would read as
    # 1000 m/s^3; the blends stay below 50 m/s^3 (measured 3.6; the Panda allows 6500).
    dt = 1e-3
    cmd = np.asarray(closed_sim.execution.trace.command_position)
    assert np.abs(np.diff(cmd, 3, axis=0)).max() / dt ** 3 < 50.0


def test_a_jumping_refined_model_aborts_with_its_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    """After engagement the robot's estimate is turned by 30 deg at once: ``model_jump``."""
    original = rf.Refiner.robot_estimate
    from dataclasses import replace

    from services.common.se3 import so3_exp

    def jumping(self, stamp_ns, T, cov):  # type: ignore[no-untyped-def]
        model = original(self, stamp_ns, T, cov)
        if self.engaged_at_s is None or model is None or model.revolute is None:
            return model
        a = np.asarray(model.revolute.axis)
        turned = so3_exp(math.radians(30.0) * np.cross(a, [1.0, 0.0, 0.0])
                         / np.linalg.norm(np.cross(a, [1.0, 0.0, 0.0]))) @ a
        return replace(model, revolute=replace(model.revolute, axis=turned))

    monkeypatch.setattr(rf.Refiner, "robot_estimate", jumping)
    row, sim = run_case("key", 10.0, 10.0, 0, 10, closed=True)
    assert not row.success
    assert row.reason == "model_jump"
    assert "deg/s" in sim.execution.detail


def test_robot_body_validates_against_the_protocol() -> None:
    T_base_camera = np.eye(4)
    T_base_camera[:3, 3] = [0.5, 0.0, 0.4]
    T_base_ee = np.eye(4)
    T_base_ee[:3, 3] = [0.4, 0.1, 0.3]
    body = rf.robot_body(123, "camera", np.linalg.inv(T_base_camera), T_base_ee, np.zeros(6))
    back = HandBody.from_msgpack(body.to_msgpack())
    np.testing.assert_allclose(back.pose[:3, 3], [-0.1, 0.1, -0.1], atol=1e-12)
    assert back.motion_model == "kinematic"
    assert back.covariance[0, 0] == pytest.approx(rf.ROBOT_POSITION_STD_M ** 2)


def test_refinement_from_the_robot_alone(key_10deg_10mm) -> None:
    """No camera stream and no bus in the loop: the 10 deg-off prior fails the consistency gate
    (never fused), so the refined axis comes from the robot's own grasp poses alone."""
    _, (closed_row, sim) = key_10deg_10mm
    assert sim.execution.refinement.prior_fused == 0
    assert closed_row.final_axis_error_deg < 1.0


def test_a_diverging_refined_model_aborts_with_its_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    """After engagement the robot's estimate reports 10x its 1-sigma (the joint no longer explains
    the grasp's motion): ``model_diverged``, with the numbers, before the turn is done."""
    original = rf.Refiner.robot_estimate
    from dataclasses import replace

    def diverging(self, stamp_ns, T, cov):  # type: ignore[no-untyped-def]
        model = original(self, stamp_ns, T, cov)
        if self.engaged_at_s is None or model is None or model.revolute is None:
            return model
        grown = np.asarray(model.revolute.covariance) * 100.0
        return replace(model, revolute=replace(model.revolute, covariance=grown))

    monkeypatch.setattr(rf.Refiner, "robot_estimate", diverging)
    row, sim = run_case("key", 10.0, 10.0, 0, 10, closed=True)
    assert not row.success
    assert row.reason == "model_diverged"
    assert "1-sigma grew" in sim.execution.detail
    assert row.articulated_deg < 170.0
    assert row.peak_force_n <= 70.0


def _plan(axis: list[float]) -> object:
    from services.robot_bridge.trajectory import ArticulationPlan, JointInBase

    a = np.asarray(axis, float) / np.linalg.norm(axis)
    T0 = np.eye(4)
    T0[:3, 3] = [0.5, 0.0, 0.3]
    return ArticulationPlan(JointInBase("revolute", a, np.array([0.5, -0.06, 0.3])), T0,
                            math.pi, 6.0, 0.5)


def test_overlapping_blends_keep_the_command_smooth() -> None:
    """Three re-plans 0.1 s apart, each blended over 0.3 s: the commanded pose moves continuously,
    its twist is its own derivative (no velocity step), and ended blends are dropped."""
    p0, p1, p2, p3 = (_plan([0.0, s, 1.0]) for s in (0.0, 0.02, 0.04, 0.06))
    path = rf._Blend(p0, p1, 2.0, 0.3)
    path = rf._Blend(path, p2, 2.1, 0.3)
    path = rf._Blend(path, p3, 2.2, 0.3)
    dt = 1e-3
    ts = np.arange(1.9, 2.7, dt)
    poses = [path.sample(float(t)) for t in ts]
    p = np.array([T[:3, 3] for T, _, _ in poses])
    v = np.array([tw[:3] for _, tw, _ in poses])
    fd = np.gradient(p, dt, axis=0)
    assert np.abs(fd[1:-1] - v[1:-1]).max() < 1e-3           # m/s: the twist matches the motion
    acc = np.diff(v, axis=0) / dt
    assert np.abs(acc).max() < 2.0                            # m/s^2: no velocity step
    assert np.linalg.norm(p[-1] - p3.sample(float(ts[-1]))[0][:3, 3]) < 1e-12
    assert rf._settled(path, 2.35).old.old is p1               # the first blend has ended
    assert rf._settled(path, 2.5) is p3


def _belief(tilt_deg: float, offset_m: float, dir_std_deg: float, pos_std_m: float,
            grasp: np.ndarray) -> object:
    """A revolute belief near the true axis (z through the origin), at ``grasp``."""
    from services.common.se3 import so3_exp
    from services.kinematics.filters import tangent_basis
    from services.robot_bridge.compliance import AxisBelief

    a = so3_exp(np.array([0.0, math.radians(tilt_deg), 0.0])) @ np.array([0.0, 0.0, 1.0])
    point = np.array([0.0, offset_m, float(grasp[2])])  # tilted about the grasp height
    foot = point + float((grasp - point) @ a) * a
    B = tangent_basis(a)
    cov = np.zeros((5, 5))
    cov[:2, :2] = np.eye(2) * math.radians(dir_std_deg) ** 2
    cov[2:, 2:] = B @ B.T * pos_std_m ** 2
    return AxisBelief(a, foot, cov)


def test_fusion_stays_between_the_beliefs() -> None:
    """A camera prior 3 deg and 4 mm off and a sharper robot estimate 0.5 deg off, tilted toward
    the lever: they agree, and the fused axis lies between them. (Fusing each foot with its
    along-axis coordinate pinned to its own axis refused this pair as disagreeing, and on the
    window lock extrapolated the fused axis 6-8 mm beyond both.)"""
    grasp = np.array([0.06, 0.0, 0.3])
    prior = _belief(3.0, 0.004, 2.3, 0.005, grasp)
    robot = _belief(-0.5, 0.0, 0.3, 0.0025, grasp)
    fused = rf.fuse(prior, robot, 3.0)
    assert fused is not robot  # they agree within the gate: fused

    def distance_at_grasp(b: object) -> float:
        f = b.foot + float((grasp - b.foot) @ b.axis) * b.axis  # type: ignore[attr-defined]
        return float(np.hypot(f[0], f[1]))

    z = np.array([0.0, 0.0, 1.0])
    angle = math.degrees(math.acos(float(fused.axis @ z)))
    assert angle < 3.0
    assert distance_at_grasp(fused) <= max(distance_at_grasp(prior), distance_at_grasp(robot))
    assert fused.position_std() < robot.position_std()


def test_closed_loop_stays_in_simulation() -> None:
    """On a real arm's backend (panda-py, faked) a refinement config runs open loop: its inline
    feed and re-plan ticks would overrun a 1 kHz control loop."""
    from services.evaluation.robot_perturbations import perturbed_model
    from services.robot_bridge.config import RobotBridgeConfig
    from services.robot_bridge.executor import Bridge
    from services.robot_bridge.pandapy_backend import PandaPyBackend
    from services.robot_bridge.simulation import grasp_in_camera, object_in_camera
    from services.robot_bridge.trajectory import ArticulationPlan, JointInBase
    from services.synthetic.generator import generate
    from tests.robot_bridge import fake_panda_py

    config = RobotBridgeConfig()
    obj = object_in_camera(generate("key", 3, 0))
    model = perturbed_model(obj, 10.0, 10.0, 0.0, grasp_in_camera(obj)[:3, 3])
    backend = PandaPyBackend(fake_panda_py.FakePanda(), fake_panda_py.controllers, config)
    T0 = backend.read().T_base_ee.copy()
    plan = ArticulationPlan(JointInBase("revolute", T0[:3, 2].copy(), T0[:3, 3].copy()), T0,
                            math.pi, 6.0)
    assert Bridge(backend, config, rf.RefinementConfig())._refiner(plan, model) is None


def test_the_service_runs_closed_loop_only_when_configured() -> None:
    """``robot_bridge.closed_loop`` (``handkse robot-bridge --closed-loop``) hands the service's
    bridge a refinement config; without it the service articulates open loop."""
    import argparse

    from services.common.service import Service
    from services.robot_bridge.config import RobotBridgeConfig
    from services.robot_bridge.factory import make_backend
    from services.robot_bridge.service import RobotBridgeNode, add_arguments
    from tests.common.fake_bus import FakeBus
    from tests.robot_bridge.test_stale_model import KEYS

    for closed, expected in ((False, type(None)), (True, rf.RefinementConfig)):
        config = RobotBridgeConfig(closed_loop=closed)
        node = RobotBridgeNode(Service("robot_bridge", FakeBus(), KEYS), make_backend(config),
                               config)
        assert isinstance(node.bridge.refinement, expected)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert parser.parse_args(["--closed-loop"]).closed_loop is True
    assert parser.parse_args([]).closed_loop is False
