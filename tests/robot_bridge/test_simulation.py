"""Articulating synthetic demonstrations' objects in simulation (the demo hook)."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.protocol import KinematicModel, PrismaticParams, RevoluteParams
from services.common.se3 import so3_exp
from services.robot_bridge.client import format_result
from services.robot_bridge.simulation import (
    ObjectInCamera,
    articulate_in_simulation,
    default_hand_eye,
    grasp_in_camera,
    object_in_camera,
)
from services.synthetic.generator import generate

K_EFF = 1.0 / (1.0 / 1000.0 + 1.0 / 20000.0)


def _truth_model(obj: ObjectInCamera, point_shift: np.ndarray | None = None) -> KinematicModel:
    """The true joint as a camera-frame model (P = 1), optionally with a shifted axis."""
    probs = {"rigid": 0.0, "prismatic": 0.0, "revolute": 0.0, "disconnected": 0.0}
    probs[obj.joint_type] = 1.0
    if obj.joint_type == "revolute":
        p = obj.point + (0.0 if point_shift is None else point_shift)
        return KinematicModel(type="revolute", probabilities=probs, revolute=RevoluteParams(
            axis=obj.axis, point=p, q=obj.demonstrated, dq=0.0, covariance=np.zeros((7, 7))))
    ref = np.eye(4)
    ref[:3, 3] = obj.grasp
    return KinematicModel(type="prismatic", probabilities=probs, reference_pose=ref,
                          prismatic=PrismaticParams(axis=obj.axis, q=obj.demonstrated, dq=0.0,
                                                    covariance=np.zeros((4, 4))))


@pytest.mark.parametrize("name", ["key", "window_lock", "bolt"])
def test_true_model_of_a_demonstration_succeeds(name: str) -> None:
    obj = object_in_camera(generate(name, 3, 0))
    sim = articulate_in_simulation(_truth_model(obj), obj)
    assert sim.result.success, sim.result
    assert sim.result.peak_force_n < 15.0
    if name == "bolt":
        assert abs(sim.amount) == pytest.approx(obj.demonstrated)
    else:
        assert abs(sim.amount) == pytest.approx(math.pi)
        assert sim.object_base is not None
        # the robot grasps the key on its axis and the window lock 6 cm from it
        assert sim.object_base.lever_m == pytest.approx(0.0 if name == "key" else 0.06, abs=1e-6)
    assert format_result(sim.result).startswith("articulate: SUCCESS (ok)")


def test_camera_frame_errors_reach_the_robot_unchanged() -> None:
    """A camera-frame axis 1 cm off the key gives the same force as 1 cm off in the base frame."""
    obj = object_in_camera(generate("key", 3, 1))
    g = grasp_in_camera(obj)
    sim = articulate_in_simulation(_truth_model(obj, 0.01 * g[:3, 0]), obj)
    assert sim.plan is not None and sim.object_base is not None
    true_axis, planned = sim.object_base.axis_base, sim.plan.joint
    assert abs(float(planned.axis @ true_axis)) == pytest.approx(1.0, abs=1e-9)
    d = planned.point - sim.object_base.point_base
    assert np.linalg.norm(d - (d @ true_axis) * true_axis) == pytest.approx(0.01, abs=1e-9)
    assert sim.result.success
    # quasi-static K_eff * 2 delta plus the few newtons of friction and damping of the key
    assert sim.result.peak_force_n == pytest.approx(K_EFF * 0.02, rel=0.25)


def test_any_reachable_hand_eye_works() -> None:
    """Object placed by another calibration (camera turned 20 deg about the base z axis)."""
    obj = object_in_camera(generate("window_lock", 3, 2))
    T_bc = default_hand_eye(obj)
    turn = np.eye(4)
    turn[:3, :3] = so3_exp(np.array([0.0, 0.0, math.radians(20.0)]))
    sim = articulate_in_simulation(_truth_model(obj), obj, T_base_camera=turn @ T_bc)
    assert sim.result.success, sim.result
    far = np.eye(4)
    far[:3, 3] = (2.0, 0.0, 0.0)  # 2 m away: nothing to grasp
    assert articulate_in_simulation(_truth_model(obj), obj,
                                    T_base_camera=far @ T_bc).result.reason == "workspace"


def test_refusals_reach_the_demo_result() -> None:
    obj = object_in_camera(generate("key", 3, 0))
    unsure = _truth_model(obj)
    probs = {"rigid": 0.5, "prismatic": 0.0, "revolute": 0.5, "disconnected": 0.0}
    unsure = KinematicModel(type="revolute", probabilities=probs, revolute=unsure.revolute)
    assert articulate_in_simulation(unsure, obj).result.reason == "low_confidence"
    rigid = KinematicModel(type="rigid", probabilities={**probs, "rigid": 1.0, "revolute": 0.0})
    assert articulate_in_simulation(rigid, obj).result.reason == "unsupported_type"
