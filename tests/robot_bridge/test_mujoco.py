"""The simulated Panda articulating objects: true models, axis errors, aborts, refusals.

Every simulated run goes through :func:`_run`, which also checks that no torque sent exceeded
Franka's joint torque limits and no torque rate exceeded 1000 N m/s.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.protocol import ArticulateRequest, KinematicModel, RevoluteParams
from services.common.se3 import so3_exp
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.executor import Bridge, Execution, execute
from services.robot_bridge.mujoco_backend import (
    BOLT_STROKE_M,
    WINDOW_LOCK_LEVER_M,
    MujocoBackend,
    nominal_grasp_pose,
    preset_object,
)
from services.robot_bridge.panda_scene import (
    Q_GRASP_RAD,
    TAU_MAX_NM,
    TAU_RATE_MAX_NM_PER_S,
    ObjectSpec,
    scene_xml,
)
from services.robot_bridge.trajectory import ArticulationPlan, JointInBase

CONFIG = RobotBridgeConfig()
G = CONFIG.gains()
K_EFF = 1.0 / (1.0 / CONFIG.translational_stiffness_n_per_m + 1.0 / CONFIG.grasp_stiffness_n_per_m)


def _run(backend: MujocoBackend, plan: ArticulationPlan,
         config: RobotBridgeConfig = CONFIG) -> Execution:
    ex = execute(backend, plan, config)
    tr = ex.trace.arrays()
    assert tr["tau_ratio"].max() <= 1.0 + 1e-12, "a torque above Franka's limit was sent"
    assert tr["tau_rate_nm_per_s"].max() <= TAU_RATE_MAX_NM_PER_S + 1e-6, \
        "a torque rate above 1000 N m/s was sent"
    return ex


def _plan(backend: MujocoBackend, amount: float, duration_s: float, *, tilt_deg: float = 0.0,
          tilt_about: int = 1, offset_m: float = 0.0) -> ArticulationPlan:
    """Plan along the object's true joint, optionally tilted/offset about/along a TCP axis."""
    obj = backend.obj
    assert obj is not None
    T0 = backend.read().T_base_ee.copy()
    axis = so3_exp(math.radians(tilt_deg) * T0[:3, tilt_about]) @ obj.axis_base
    point = obj.point_base + offset_m * T0[:3, 1]
    return ArticulationPlan(JointInBase(obj.joint_type, axis, point), T0, amount, duration_s)


def test_scene_is_generated_without_files() -> None:
    xml = scene_xml(preset_object("window_lock"))
    assert "mesh" not in xml and "file=" not in xml
    for tau in TAU_MAX_NM:
        assert f'ctrlrange="{-tau} {tau}"' in xml
    be = MujocoBackend(preset_object("window_lock"))
    assert np.allclose(be.read().q, Q_GRASP_RAD, atol=1e-6)
    assert np.allclose(be.read().T_base_ee, nominal_grasp_pose(), atol=1e-9)
    assert be.obj is not None and be.obj.lever_m == pytest.approx(WINDOW_LOCK_LEVER_M)


@pytest.mark.parametrize("name", ["key", "window_lock"])
def test_true_model_turns_180_degrees_gently(name: str) -> None:
    be = MujocoBackend(preset_object(name))
    ex = _run(be, _plan(be, math.pi, 6.0))
    assert ex.success, (ex.reason, ex.detail)
    assert math.degrees(ex.articulated) >= 0.97 * 180.0
    assert ex.peak_force_n < 15.0
    assert ex.trace.arrays()["tau_ratio"].max() < 0.5


def test_true_model_slides_the_bolt_its_full_stroke() -> None:
    be = MujocoBackend(preset_object("bolt"))
    ex = _run(be, _plan(be, BOLT_STROKE_M, 2.0))
    assert ex.success, (ex.reason, ex.detail)
    assert ex.articulated >= 0.97 * BOLT_STROKE_M
    assert ex.peak_force_n < 15.0


def test_centre_offset_force_matches_k_eff_times_path_deviation() -> None:
    """Key, axis 1 cm off the grasp: the commanded circle misses the key by up to 2 cm."""
    delta = 0.01
    be = MujocoBackend(preset_object("key"))
    ex = _run(be, _plan(be, math.pi, 6.0, offset_m=delta))
    predicted = K_EFF * 2.0 * delta * math.sin(math.pi / 2.0)
    assert ex.success, (ex.reason, ex.detail)
    assert ex.peak_force_n == pytest.approx(predicted, rel=0.15)


def test_axis_tilt_force_matches_k_eff_times_path_deviation() -> None:
    """Window lock (6 cm lever), axis tilted 15 deg about the axis across the lever."""
    alpha = math.radians(15.0)
    be = MujocoBackend(preset_object("window_lock"))
    ex = _run(be, _plan(be, math.pi, 6.0, tilt_deg=15.0, tilt_about=1))
    predicted = K_EFF * 2.0 * WINDOW_LOCK_LEVER_M * math.sin(alpha)
    assert ex.success, (ex.reason, ex.detail)
    assert ex.peak_force_n == pytest.approx(predicted, rel=0.15)


def test_axis_error_beyond_70_newtons_aborts_and_the_arm_stops() -> None:
    """A 20 cm slide with its axis estimated 30 deg off: the path leaves the slide by 10 cm."""
    T0 = nominal_grasp_pose()
    obj = ObjectSpec("slide", "prismatic", T0[:3, 1].copy(), T0[:3, 3].copy(), T0,
                     range=(-0.01, 0.3), armature=0.2, damping=2.0, frictionloss=1.0)
    be = MujocoBackend(obj)
    ex = _run(be, _plan(be, 0.2, 4.0, tilt_deg=30.0, tilt_about=0))
    assert not ex.success and ex.reason == "force_limit"
    assert 70.0 <= ex.peak_force_n < 72.0  # aborted on the first tick above the limit
    tr = ex.trace.arrays()
    assert ex.trace.stopped_at_s is not None and ex.trace.stopped_at_s < 4.0
    assert tr["t_s"][-1] == pytest.approx(ex.trace.stopped_at_s + CONFIG.settle_s, abs=0.01)
    after = tr["t_s"] > ex.trace.stopped_at_s + 0.02
    assert tr["force_n"][after].max() < CONFIG.force_limit_n  # holding does not pull again
    last = tr["t_s"] > ex.trace.stopped_at_s + CONFIG.settle_s - 0.1
    assert tr["joint_speed_rad_per_s"][last].max() < 0.02     # the arm has stopped
    assert tr["tcp_speed_m_per_s"][last].max() < 0.005
    assert tr["force_n"][-1] < 10.0                           # and let go of the pull
    # the target stopped advancing at the abort
    assert tr["progress"][-1] == pytest.approx(tr["progress"][np.argmax(~(tr["t_s"] <
                                               ex.trace.stopped_at_s))], abs=1e-9)


def test_mis_estimated_key_axis_aborts_on_wrist_torque() -> None:
    """A key's force barely reacts to axis tilt; the wrist torque catches it.

    See docs/robot_bridge.md#gains-and-errors.
    """
    be = MujocoBackend(preset_object("key"))
    ex = _run(be, _plan(be, math.pi, 6.0, tilt_deg=40.0))
    assert not ex.success and ex.reason in ("torque_limit", "torque_saturation")
    assert ex.peak_force_n < CONFIG.force_limit_n


def _true_key_model(stamp_ns: int, p_revolute: float = 0.99) -> KinematicModel:
    """The key's true axis as a model in the camera frame (identity hand-eye: camera = base)."""
    T0 = nominal_grasp_pose()
    axis, point = T0[:3, 2], T0[:3, 3]
    point = point - (point @ axis) * axis
    probs = {"rigid": 1.0 - p_revolute, "prismatic": 0.0, "revolute": p_revolute,
             "disconnected": 0.0}
    return KinematicModel(stamp_ns=stamp_ns, type="revolute", probabilities=probs,
                          revolute=RevoluteParams(axis=axis, point=point, q=2.0, dq=0.0,
                                                  covariance=np.zeros((7, 7))))


def test_bridge_refuses_stale_low_confidence_and_unreachable_models() -> None:
    be = MujocoBackend(preset_object("key"))
    bridge = Bridge(be, CONFIG)
    now = time.time_ns()
    req = ArticulateRequest(amount=math.pi, duration_s=6.0)
    stale = bridge.articulate(req, _true_key_model(now - 600 * 10**9), now_ns=now)
    assert (stale.success, stale.reason) == (False, "stale_model")
    unsure = bridge.articulate(req, _true_key_model(now, 0.5), now_ns=now)
    assert (unsure.success, unsure.reason) == (False, "low_confidence")
    none = bridge.articulate(req, None, now_ns=now)
    assert none.reason == "no_model"
    # q7 starts near its lower limit: turning the other way does not fit joint 7
    backwards = bridge.articulate(ArticulateRequest(amount=-math.pi, duration_s=6.0),
                                  _true_key_model(now), now_ns=now)
    assert backwards.reason == "joint7_range"
    fast = bridge.articulate(ArticulateRequest(amount=math.pi, duration_s=1.0),
                             _true_key_model(now), now_ns=now)
    assert fast.reason == "too_fast"
    # half a turn about an axis across the approach (TCP y), 5 cm behind the TCP: beyond the
    # arm's joint ranges (inverse kinematics along the planned path)
    axis = nominal_grasp_pose()[:3, 1]
    point = nominal_grasp_pose()[:3, 3] - 0.05 * nominal_grasp_pose()[:3, 2]
    across = KinematicModel(stamp_ns=now, type="revolute", probabilities=_true_key_model(
        now).probabilities, revolute=RevoluteParams(axis=axis, point=point - (point @ axis) * axis,
                                                    q=1.0, dq=0.0, covariance=np.zeros((7, 7))))
    limits = bridge.articulate(req, across, now_ns=now)
    assert limits.reason == "joint_limits"
    dry = bridge.articulate(ArticulateRequest(amount=math.pi, duration_s=6.0, dry_run=True),
                            _true_key_model(now), now_ns=now)
    assert dry.success and dry.reason == "dry_run" and dry.duration_s == pytest.approx(6.5)
    assert be.read().t_s == 0.0  # nothing moved


def test_bridge_articulates_with_a_request() -> None:
    be = MujocoBackend(preset_object("key"))
    now = time.time_ns()
    result = Bridge(be, CONFIG).articulate(
        ArticulateRequest(amount=math.pi / 2, duration_s=2.0, force_limit_n=60.0),
        _true_key_model(now), now_ns=now)
    assert result.success and result.reason == "ok"
    assert result.articulated == pytest.approx(math.pi / 2, rel=0.03)
    assert 0.0 < result.mean_force_n <= result.peak_force_n < 15.0
    assert result.duration_s == pytest.approx(2.5, abs=0.01)
