"""What the bridge does with a model: its uncertainty, its frame, and progress per request.

A simulated Panda holds the key at the nominal grasp; the requests go through
:class:`~services.robot_bridge.executor.Bridge` exactly as the service sends them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.protocol import (
    ArticulateRequest,
    KinematicModel,
    PrismaticParams,
    RevoluteParams,
)
from services.common.se3 import se3_inverse, so3_exp
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.executor import Bridge
from services.robot_bridge.mujoco_backend import MujocoBackend, preset_object
from services.robot_bridge.safety import check_uncertainty
from services.robot_bridge.simulation import grasp_in_camera, object_in_camera
from services.robot_bridge.trajectory import ArticulationPlan, joint_in_base
from services.synthetic.generator import generate

REVOLUTE = {"rigid": 0.0, "prismatic": 0.0, "revolute": 1.0, "disconnected": 0.0}
PRISMATIC = {"rigid": 0.0, "prismatic": 1.0, "revolute": 0.0, "disconnected": 0.0}


def _revolute(axis: np.ndarray, point: np.ndarray, covariance: np.ndarray | None = None,
              frame_id: str = "camera") -> KinematicModel:
    axis = np.asarray(axis, float)
    point = np.asarray(point, float)
    return KinematicModel(frame_id=frame_id, type="revolute", probabilities=REVOLUTE,
                          revolute=RevoluteParams(
                              axis=axis, point=point - (point @ axis) * axis, q=0.0, dq=0.0,
                              covariance=np.zeros((7, 7)) if covariance is None else covariance))


def _key() -> tuple[MujocoBackend, Bridge]:
    backend = MujocoBackend(preset_object("key"))
    return backend, Bridge(backend, RobotBridgeConfig())


def _true_key_model(backend: MujocoBackend, covariance: np.ndarray | None = None
                    ) -> KinematicModel:
    """The key's true axis; the default calibration is the identity (camera = base)."""
    assert backend.obj is not None
    return _revolute(backend.obj.axis_base, backend.obj.point_base, covariance)


QUARTER = ArticulateRequest(amount=math.pi / 4, duration_s=2.0, dry_run=True)


# --- uncertainty ---


def test_a_certain_type_with_a_huge_covariance_is_refused() -> None:
    backend, bridge = _key()
    vague = _true_key_model(backend, 1e6 * np.eye(7))
    assert vague.probabilities["revolute"] == 1.0
    refusal = bridge.plan(QUARTER, vague, None)
    assert not isinstance(refusal, ArticulationPlan)
    assert refusal.reason == "uncertain_model"
    assert "axis direction 1-sigma 57295.78 deg exceeds 5.00 deg" in refusal.detail
    result = bridge.articulate(ArticulateRequest(amount=math.pi / 4, duration_s=2.0), vague,
                               now_ns=None)
    assert (result.success, result.reason) == (False, "uncertain_model")
    assert bridge.last_execution is None  # nothing moved
    assert isinstance(bridge.plan(QUARTER, _true_key_model(backend), None), ArticulationPlan)


def test_axis_position_at_the_grasp_is_bounded() -> None:
    backend, bridge = _key()
    cov = np.zeros((7, 7))
    cov[2:5, 2:5] = 0.02 ** 2 * np.eye(3)  # the axis 2 cm uncertain, its direction exact
    refusal = bridge.plan(QUARTER, _true_key_model(backend, cov), None)
    assert not isinstance(refusal, ArticulationPlan)
    assert refusal.reason == "uncertain_model"
    assert "axis position 1-sigma at the grasp 20.0 mm exceeds 10.0 mm" in refusal.detail
    cov[2:5, 2:5] = 0.005 ** 2 * np.eye(3)
    assert isinstance(bridge.plan(QUARTER, _true_key_model(backend, cov), None),
                      ArticulationPlan)
    strict = Bridge(backend, RobotBridgeConfig(max_axis_position_std_m=0.004))
    assert strict.plan(QUARTER, _true_key_model(backend, cov), None).reason == \
        "uncertain_model"  # type: ignore[union-attr]


def test_a_prismatic_model_with_a_huge_covariance_is_refused() -> None:
    backend, bridge = _key()
    T0 = backend.read().T_base_ee
    model = KinematicModel(type="prismatic", probabilities=PRISMATIC, reference_pose=T0,
                           prismatic=PrismaticParams(axis=T0[:3, 2].copy(), q=0.0, dq=0.0,
                                                     covariance=1e6 * np.eye(4)))
    refusal = bridge.plan(ArticulateRequest(amount=0.01, duration_s=2.0, dry_run=True), model,
                          None)
    assert refusal.reason == "uncertain_model"  # type: ignore[union-attr]


@pytest.mark.parametrize("name", ["key", "window_lock"])
def test_the_estimators_models_pass_the_bounds(name: str) -> None:
    """What our pipeline publishes at the end of the robot-trials demonstrations (and the
    demo's key) is within the default bounds, at the robot's grasp."""
    from services.evaluation.robot_trials import PARTICIPANT, estimate

    c = RobotBridgeConfig()
    for seed in range(5):
        demo = generate(name, PARTICIPANT, seed)
        model = estimate("ours", demo)
        assert model.type == "revolute"
        assert model.probabilities["revolute"] >= c.min_type_probability
        grasp = grasp_in_camera(object_in_camera(demo))[:3, 3]
        refusal = check_uncertainty(model, grasp,
                                    max_direction_std_rad=math.radians(
                                        c.max_axis_direction_std_deg),
                                    max_position_std_m=c.max_axis_position_std_m)
        assert refusal is None, (seed, refusal)


# --- frames ---


def test_a_world_model_maps_through_the_world_calibration() -> None:
    backend = MujocoBackend(preset_object("key"))
    assert backend.obj is not None
    T_base_world = np.eye(4)
    T_base_world[:3, :3] = so3_exp(np.array([0.2, -0.4, 1.1]))
    T_base_world[:3, 3] = (0.3, -0.2, 0.1)
    T_world_base = se3_inverse(T_base_world)
    axis_w = T_world_base[:3, :3] @ backend.obj.axis_base
    point_w = T_world_base[:3, :3] @ backend.obj.point_base + T_world_base[:3, 3]
    in_world = _revolute(axis_w, point_w, frame_id="world")

    uncalibrated = Bridge(backend, RobotBridgeConfig())
    refusal = uncalibrated.plan(QUARTER, in_world, None)
    assert refusal.reason == "uncalibrated_frame"  # type: ignore[union-attr]
    assert "robot_bridge.T_base_world is not set" in refusal.detail  # type: ignore[union-attr]

    config = RobotBridgeConfig(T_base_world=tuple(T_base_world.ravel()))
    plan = Bridge(backend, config).plan(QUARTER, in_world, None)
    assert isinstance(plan, ArticulationPlan)
    assert np.allclose(plan.joint.axis, backend.obj.axis_base, atol=1e-9)
    d = plan.joint.point - backend.obj.point_base
    assert np.linalg.norm(d - (d @ plan.joint.axis) * plan.joint.axis) < 1e-9
    # the same numbers labelled "camera" go through T_base_camera (identity): another axis,
    # which the arm cannot follow from this grasp
    as_camera = _revolute(axis_w, point_w, frame_id="camera")
    T_base_camera = config.base_T_frame("camera")
    assert T_base_camera is not None
    assert np.allclose(joint_in_base(as_camera, T_base_camera).axis, axis_w)
    assert not np.allclose(axis_w, backend.obj.axis_base, atol=0.1)
    assert not isinstance(Bridge(backend, config).plan(QUARTER, as_camera, None),
                          ArticulationPlan)
    # the real thing: a world-frame model of the key turns it
    done = Bridge(backend, config).articulate(
        ArticulateRequest(amount=0.3, duration_s=1.5), in_world, now_ns=None)
    assert done.success, done


def test_config_checks_the_world_calibration() -> None:
    assert RobotBridgeConfig().base_T_frame("world") is None
    assert np.allclose(RobotBridgeConfig().base_T_frame("camera"), np.eye(4))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="T_base_world needs 16 numbers"):
        RobotBridgeConfig(T_base_world=(1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="T_base_world is not a rigid transform"):
        RobotBridgeConfig(T_base_world=(2.0,) + (0.0,) * 14 + (1.0,))


# --- progress per request ---


def test_progress_and_success_are_those_of_this_request() -> None:
    """The key turned by +0.3 twice reports 0.3 each time (not 0.6), a -0.3 request back
    succeeds, and a request about a wrong axis that barely moves the key is not a success."""
    backend, bridge = _key()
    model = _true_key_model(backend)
    obj = backend.obj
    assert obj is not None

    def turn(amount: float, along: KinematicModel) -> tuple[bool, str, float, float]:
        q0 = backend.read().object_joint
        r = bridge.articulate(ArticulateRequest(amount=amount, duration_s=1.5), along,
                              now_ns=None)
        moved = backend.read().object_joint
        assert q0 is not None and moved is not None
        return r.success, r.reason, r.articulated, moved - q0

    for _ in range(2):
        ok, reason, articulated, moved = turn(0.3, model)
        assert (ok, reason) == (True, "ok")
        assert articulated == pytest.approx(0.3, abs=0.01)
        assert moved == pytest.approx(articulated, abs=1e-3)
    ok, reason, articulated, moved = turn(-0.3, model)
    assert (ok, reason) == (True, "ok") and articulated == pytest.approx(-0.3, abs=0.01)
    # the key stands at +0.3: about the TCP's x axis through the key, the hand turns 0.3 rad
    # (the grasp gives) while the key hardly moves
    across = backend.read().T_base_ee[:3, 0]
    for sign in (1.0, -1.0):
        ok, reason, articulated, moved = turn(0.3, _revolute(sign * across, obj.point_base))
        assert abs(moved) < 0.02
        assert not ok and reason == "incomplete", (reason, articulated)
        assert abs(articulated) < 0.02
