"""Pure parts of the robot bridge: controller law, trajectory, safety clamps, config.

Tolerances (docs/testing.md#tolerances): 1e-9 for closed forms on O(1) values (margin 1e5 over
round-off); 1e-7 for a 6x6 solve with the Panda's Jacobian (condition number up to ~1e3 here);
1e-6 for finite differences (truncation error of the step).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import math
import sys

import numpy as np
import pytest

from services.common.protocol import (
    ArticulateRequest,
    KinematicModel,
    PrismaticParams,
    ProtocolError,
    RevoluteParams,
)
from services.common.se3 import quat_wxyz_from_matrix, so3_exp, so3_log
from services.kinematics.filters import tangent_basis
from services.robot_bridge.config import RobotBridgeConfig, config_from_args
from services.robot_bridge.controller import (
    ImpedanceGains,
    impedance_wrench,
    lead_target,
    nullspace_torque,
    orientation_error,
    quat_xyzw_from_matrix,
)
from services.robot_bridge.safety import (
    SaturationWatch,
    check_amount,
    check_model,
    check_uncertainty,
    clamp_torque,
    clamp_twist,
    tracking_violation,
    wrench_violation,
)
from services.robot_bridge.trajectory import (
    MIN_JERK_PEAK_RATE,
    ArticulationPlan,
    JointInBase,
    flipped_grasp_q7,
    joint_in_base,
    min_jerk,
    plan_checks,
    twist_angle,
)

TAU_MAX = np.array([87.0] * 4 + [12.0] * 3)
RNG = np.random.default_rng(7)


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def _model(kind: str = "revolute", p_type: float = 0.99, stamp_ns: int = 0) -> KinematicModel:
    probs = {"rigid": 0.0, "prismatic": 0.0, "revolute": 0.0, "disconnected": 0.0}
    if kind in probs:
        probs[kind] = p_type
        other = "rigid" if kind != "rigid" else "revolute"
        probs[other] = 1.0 - p_type
    else:
        probs["disconnected"] = 1.0
    rev = RevoluteParams(axis=np.array([0.0, 0.0, 1.0]), point=np.array([0.1, 0.0, 0.0]), q=1.0,
                         dq=0.0, covariance=np.zeros((7, 7)))
    pri = PrismaticParams(axis=np.array([1.0, 0.0, 0.0]), q=0.03, dq=0.0,
                          covariance=np.zeros((4, 4)))
    return KinematicModel(stamp_ns=stamp_ns, type=kind, probabilities=probs, revolute=rev,
                          prismatic=pri)


# --- controller ---


def test_orientation_error_is_two_sin_half_angle_and_rotvec_for_small_angles() -> None:
    for angle in (1e-4, 0.3, 1.5, 2.5, 3.0):
        axis = RNG.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = so3_exp(RNG.normal(size=3))
        R_target = so3_exp(angle * axis) @ R
        e = orientation_error(R_target, R)
        assert np.allclose(e, 2.0 * math.sin(angle / 2.0) * axis, atol=1e-9)
    R = so3_exp(np.array([0.1, -0.2, 0.3]))
    small = np.array([1e-3, -2e-3, 5e-4])
    assert np.allclose(orientation_error(so3_exp(small) @ R, R), small, atol=1e-8)


def test_impedance_wrench_matches_panda_py_form() -> None:
    """panda-py: F = -K_p [p - p_d, -R vec(q^-1 q_d)] - D v, with K_p rot = 2 k_rot."""
    g = ImpedanceGains(800.0, 40.0, 0.9, 0.5)
    R = so3_exp(RNG.normal(size=3))
    R_d = so3_exp(0.4 * np.array([0.6, 0.0, 0.8])) @ R
    p, p_d = RNG.normal(size=3), RNG.normal(size=3)
    twist = RNG.normal(size=6)
    q = quat_wxyz_from_matrix(R)
    q_d = quat_wxyz_from_matrix(R_d)
    if q @ q_d < 0:
        q = -q
    # vec(q^-1 q_d) (Hamilton product of the conjugate of q with q_d)
    w1, v1 = q[0], -q[1:]
    w2, v2 = q_d[0], q_d[1:]
    vec = w1 * v2 + w2 * v1 + np.cross(v1, v2)
    error = np.concatenate([p - p_d, -(R @ vec)])
    K = g.panda_py_impedance()
    D = g.damping_ratio * 2.0 * np.sqrt(K)
    expected = -K @ error - D @ twist
    got = impedance_wrench(p_d, R_d, None, p, R, twist, g)
    assert np.allclose(got, expected, atol=1e-9)


def test_lead_target_reproduces_the_feed_forward() -> None:
    g = ImpedanceGains()
    T_d = _pose(so3_exp(RNG.normal(size=3)), RNG.normal(size=3))
    T = _pose(so3_exp(0.01 * RNG.normal(size=3)) @ T_d[:3, :3], T_d[:3, 3] + 0.01)
    v_d = np.array([0.05, -0.02, 0.01, 0.3, -0.2, 0.5])
    v = 0.5 * v_d
    with_ff = impedance_wrench(T_d[:3, 3], T_d[:3, :3], v_d, T[:3, 3], T[:3, :3], v, g)
    T_lead = lead_target(T_d, v_d, g)
    without = impedance_wrench(T_lead[:3, 3], T_lead[:3, :3], None, T[:3, 3], T[:3, :3], v, g)
    assert np.allclose(with_ff[:3], without[:3], atol=1e-9)       # exact for translation
    assert np.allclose(with_ff[3:], without[3:], rtol=0.05, atol=0.05)  # first order for rotation


def test_nullspace_torque_creates_no_task_wrench() -> None:
    g = ImpedanceGains()
    for _ in range(5):
        J = RNG.normal(size=(6, 7))
        tau = nullspace_torque(J, RNG.normal(size=7), RNG.normal(size=7), RNG.normal(size=7), g)
        # J pinv-projected: the part of tau in the range of J^T is removed
        assert np.allclose(np.linalg.solve(J @ J.T, J @ tau), 0.0, atol=1e-7)


def test_quaternion_order_is_xyzw() -> None:
    R = so3_exp(np.array([0.0, 0.0, 0.5]))
    assert np.allclose(quat_xyzw_from_matrix(R), [0.0, 0.0, math.sin(0.25), math.cos(0.25)])


def test_gains_are_validated() -> None:
    with pytest.raises(ValueError, match="translational"):
        ImpedanceGains(translational_n_per_m=0.0)


# --- trajectory ---


def test_min_jerk_profile() -> None:
    T = 4.0
    assert min_jerk(0.0, T) == (0.0, 0.0)
    assert min_jerk(T, T) == (1.0, 0.0)
    assert min_jerk(T / 2, T)[0] == pytest.approx(0.5)
    assert min_jerk(T / 2, T)[1] == pytest.approx(MIN_JERK_PEAK_RATE / T)
    for t in np.linspace(0.1, 3.9, 9):
        h = 1e-6
        fd = (min_jerk(t + h, T)[0] - min_jerk(t - h, T)[0]) / (2 * h)
        assert min_jerk(t, T)[1] == pytest.approx(fd, rel=1e-5)


@pytest.mark.parametrize("kind", ["revolute", "prismatic"])
def test_plan_twist_is_the_derivative_of_the_path(kind: str) -> None:
    axis = np.array([0.3, -0.2, 0.9])
    axis /= np.linalg.norm(axis)
    T0 = _pose(so3_exp(np.array([0.2, 1.0, -0.3])), np.array([0.5, 0.1, 0.4]))
    plan = ArticulationPlan(JointInBase(kind, axis, np.array([0.45, 0.12, 0.38])), T0,
                            -2.5 if kind == "revolute" else 0.1, 3.0)
    h = 1e-6
    for t in (0.4, 1.5, 2.7):
        Ta, _, _ = plan.sample(t - h)
        Tb, _, _ = plan.sample(t + h)
        T, twist, theta = plan.sample(t)
        assert np.allclose((Tb[:3, 3] - Ta[:3, 3]) / (2 * h), twist[:3], atol=1e-6)
        w = so3_log(Tb[:3, :3] @ Ta[:3, :3].T) / (2 * h)
        assert np.allclose(w, twist[3:], atol=1e-6)
        assert plan.progress_from_pose(T, theta) == pytest.approx(theta, abs=1e-9)
    if kind == "revolute":  # the path stays on the circle about the axis
        for t in np.linspace(0.0, 3.0, 7):
            d = plan.sample(t)[0][:3, 3] - plan.joint.point
            r = np.linalg.norm(d - (d @ axis) * axis)
            d0 = T0[:3, 3] - plan.joint.point
            assert r == pytest.approx(np.linalg.norm(d0 - (d0 @ axis) * axis))


def test_progress_unwraps_beyond_half_a_turn() -> None:
    axis = np.array([0.0, 0.0, 1.0])
    plan = ArticulationPlan(JointInBase("revolute", axis, np.zeros(3)), np.eye(4), 3.5, 1.0)
    prev = 0.0
    for theta in np.linspace(0.0, 3.5, 50):
        T = _pose(so3_exp(theta * axis), np.zeros(3))
        prev = plan.progress_from_pose(T, prev)
        assert prev == pytest.approx(theta, abs=1e-9)


def test_twist_angle_is_the_swing_twist_angle() -> None:
    """Against the quaternion form ``2 atan2(v . a, w)`` (w >= 0), at every Shepperd branch
    and at half turns."""
    rotations = [so3_exp(RNG.normal(size=3)) for _ in range(200)]
    rotations += [so3_exp(math.pi * np.eye(3)[i]) for i in range(3)]
    rotations += [so3_exp((math.pi - 1e-9) * np.array([0.0, 0.6, 0.8]))]
    for R in rotations:
        a = RNG.normal(size=3)
        a /= np.linalg.norm(a)
        q = quat_wxyz_from_matrix(R)
        expected = 2.0 * math.atan2(float(q[1:] @ a), float(q[0]))
        got = twist_angle(R, a)
        assert abs(math.remainder(got - expected, 2.0 * math.pi)) < 1e-9
    axis = np.array([0.0, 0.6, 0.8])
    for theta in (0.3, -2.0, 3.0):
        assert twist_angle(so3_exp(theta * axis), axis) == pytest.approx(theta, abs=1e-12)
    # a swing about a perpendicular axis adds no twist
    assert twist_angle(so3_exp(0.7 * np.array([1.0, 0.0, 0.0])), axis) == pytest.approx(0.0)


def test_joint_in_base_moves_the_model_through_the_hand_eye() -> None:
    T_bc = _pose(so3_exp(np.array([0.3, -1.2, 0.4])), np.array([0.2, -0.3, 0.9]))
    j = joint_in_base(_model("revolute"), T_bc)
    assert np.allclose(j.axis, T_bc[:3, :3] @ [0.0, 0.0, 1.0])
    assert np.allclose(j.point, T_bc[:3, :3] @ [0.1, 0.0, 0.0] + T_bc[:3, 3])
    jp = joint_in_base(_model("prismatic"), T_bc)
    assert jp.joint_type == "prismatic" and np.allclose(jp.axis, T_bc[:3, 0])
    with pytest.raises(ValueError):
        joint_in_base(_model("rigid"), T_bc)


def test_plan_checks_refuse_fast_far_and_joint7() -> None:
    axis = np.array([1.0, 0.0, 0.0])
    T0 = _pose(np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], float), np.array([0.5, 0.0, 0.4]))
    kw = {"max_linear_m_per_s": 0.25, "max_angular_rad_per_s": 2.0,
          "joint7_limits_rad": (-2.8973, 2.8973), "joint7_margin_rad": 0.1}
    joint = JointInBase("revolute", axis, T0[:3, 3])
    assert plan_checks(ArticulationPlan(joint, T0, math.pi, 6.0), -2.0, **kw) is None
    assert plan_checks(ArticulationPlan(joint, T0, math.pi, 1.0), -2.0,
                       **kw).reason == "too_fast"
    far = JointInBase("prismatic", np.array([1.0, 0.0, 0.0]), T0[:3, 3])
    assert plan_checks(ArticulationPlan(far, T0, 0.9, 10.0), -2.0,
                       **kw).reason == "workspace"
    # TCP z = +x: turning +pi about +x needs joint 7 +pi; from q7 = 2.0 it does not fit
    assert plan_checks(ArticulationPlan(joint, T0, math.pi, 6.0), 2.0,
                       **kw).reason == "joint7_range"
    assert flipped_grasp_q7(2.0, math.pi, (-2.8973, 2.8973), 0.1) == pytest.approx(2.0 - math.pi)
    assert flipped_grasp_q7(-2.35, math.pi, (-2.8973, 2.8973), 0.1) == -2.35
    assert flipped_grasp_q7(0.0, 6.0, (-2.8973, 2.8973), 0.1) is None


# --- safety ---


def test_clamp_torque_respects_magnitude_and_rate() -> None:
    dt, rate = 0.001, 1000.0
    prev = np.zeros(7)
    for _ in range(200):
        desired = RNG.normal(scale=60.0, size=7)
        cmd = clamp_torque(desired, prev, dt, TAU_MAX, rate)
        assert np.all(np.abs(cmd.tau) <= TAU_MAX + 1e-12)
        assert np.all(np.abs(cmd.tau - prev) <= rate * dt + 1e-12)
        assert cmd.saturated == bool(np.any(np.abs(desired) > TAU_MAX))
        prev = cmd.tau
    small = clamp_torque(np.full(7, 0.5), np.full(7, 0.4), dt, TAU_MAX, rate)
    assert np.allclose(small.tau, 0.5) and not small.saturated


def test_clamp_twist_scales_to_the_limits() -> None:
    out = clamp_twist(np.array([3.0, 4.0, 0.0, 0.0, 0.0, 5.0]), 1.0, 2.5)
    assert np.allclose(out, [0.6, 0.8, 0.0, 0.0, 0.0, 2.5])
    slow = np.array([0.1, 0.0, 0.0, 0.0, 0.2, 0.0])
    assert np.allclose(clamp_twist(slow, 1.0, 2.5), slow)


def test_check_model_reasons() -> None:
    kw = {"min_type_probability": 0.8, "max_age_s": 10.0}
    now = 100 * 10**9
    assert check_model(None, now_ns=now, **kw).reason == "no_model"
    for kind in ("rigid", "disconnected", "unknown"):
        assert check_model(_model(kind), now_ns=None, **kw).reason == "unsupported_type"
    assert check_model(_model("revolute", 0.6), now_ns=None, **kw).reason == "low_confidence"
    old = _model("revolute", stamp_ns=now - 11 * 10**9)
    assert check_model(old, now_ns=now, **kw).reason == "stale_model"
    future = _model("revolute", stamp_ns=now + 5 * 10**9)
    assert check_model(future, now_ns=now, **kw).reason == "stale_model"
    fresh = _model("revolute", stamp_ns=now - 10**9)
    assert check_model(fresh, now_ns=now, **kw) is None
    assert check_model(old, now_ns=None, **kw) is None  # offline: no age check


def _revolute_with(covariance: np.ndarray, axis: np.ndarray, point: np.ndarray
                   ) -> KinematicModel:
    probs = {"rigid": 0.0, "prismatic": 0.0, "revolute": 1.0, "disconnected": 0.0}
    return KinematicModel(type="revolute", probabilities=probs, revolute=RevoluteParams(
        axis=axis, point=point, q=0.0, dq=0.0, covariance=covariance))


BOUNDS = {"max_direction_std_rad": math.radians(5.0), "max_position_std_m": 0.01}


def test_check_uncertainty_looks_at_the_axis_where_the_robot_holds_it() -> None:
    """The published point is the axis' foot from the frame origin, here 0.6 m from the grasp:
    a direction known to 1 deg and a line known to 1 mm at the grasp pass, although the foot
    itself is ~10 mm uncertain; the same direction spread without that correlation does not."""
    axis = np.array([0.0, 0.6, 0.8])
    point = np.array([0.1, 0.0, 0.0])                 # foot of the axis from the origin
    grasp = point + 0.6 * axis + np.array([0.02, 0.0, 0.0])
    B = tangent_basis(axis)
    P = np.eye(3) - np.outer(axis, axis)
    s = float((grasp - point) @ axis)
    sigma_b, sigma_line = math.radians(1.0), 0.001
    # d_point = -s B d_b + e (e perpendicular noise): the axis pivots about the grasp
    J = np.zeros((7, 5))
    J[:2, :2] = np.eye(2) * sigma_b
    J[2:5, :2] = -s * B * sigma_b
    J[2:5, 2:5] = P * sigma_line
    pivoting = J @ J.T
    assert math.sqrt(np.linalg.eigvalsh(pivoting[2:5, 2:5]).max()) > 0.009
    assert check_uncertainty(_revolute_with(pivoting, axis, point), grasp, **BOUNDS) is None
    loose = pivoting.copy()
    loose[:2, 2:5] = loose[2:5, :2] = 0.0             # the same spreads, uncorrelated
    refusal = check_uncertainty(_revolute_with(loose, axis, point), grasp, **BOUNDS)
    assert refusal is not None and refusal.reason == "uncertain_model"
    assert "axis position 1-sigma at the grasp" in refusal.detail


def test_check_uncertainty_reasons() -> None:
    axis, point = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    grasp = np.array([0.0, 0.0, 0.3])
    assert check_uncertainty(_revolute_with(np.zeros((7, 7)), axis, point), grasp,
                             **BOUNDS) is None
    tilted = np.diag([math.radians(6.0) ** 2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    refusal = check_uncertainty(_revolute_with(tilted, axis, point), grasp, **BOUNDS)
    assert refusal is not None and refusal.detail.startswith(
        "axis direction 1-sigma 6.00 deg exceeds 5.00 deg")
    indefinite = np.zeros((7, 7))
    indefinite[0, 0] = indefinite[1, 1] = 1e-6
    indefinite[0, 1] = indefinite[1, 0] = 1e-3      # symmetric, non-negative diagonal
    refusal = check_uncertainty(_revolute_with(indefinite, axis, point), grasp, **BOUNDS)
    assert refusal is not None and "not positive semi-definite" in refusal.detail
    probs = {"rigid": 0.0, "prismatic": 1.0, "revolute": 0.0, "disconnected": 0.0}
    prismatic = KinematicModel(type="prismatic", probabilities=probs, prismatic=PrismaticParams(
        axis=axis, q=0.0, dq=0.0, covariance=np.diag([0.01, 0.01, 1.0, 1.0])))
    refusal = check_uncertainty(prismatic, grasp, **BOUNDS)
    assert refusal is not None and "axis direction 1-sigma 5.73 deg" in refusal.detail


def test_articulate_request_timeout_is_optional() -> None:
    plain = ArticulateRequest(amount=0.3, duration_s=2.0)
    assert "timeout_s" not in plain.to_dict()
    assert ArticulateRequest.from_msgpack(plain.to_msgpack()).timeout_s is None
    timed = ArticulateRequest(amount=0.3, duration_s=2.0, timeout_s=7.5)
    assert ArticulateRequest.from_msgpack(timed.to_msgpack()).timeout_s == 7.5
    for bad in (0.0, -1.0, math.inf):
        with pytest.raises(ProtocolError, match="timeout_s"):
            ArticulateRequest.from_msgpack(
                ArticulateRequest(amount=0.3, duration_s=2.0, timeout_s=bad).to_msgpack())


def test_check_amount() -> None:
    assert check_amount(0.0, 1.0, "revolute").reason == "invalid_request"
    assert check_amount(math.nan, 1.0, "revolute").reason == "invalid_request"
    assert check_amount(7.0, 1.0, "revolute").reason == "invalid_request"
    assert check_amount(1.5, 1.0, "prismatic").reason == "invalid_request"
    assert check_amount(-math.pi, 6.0, "revolute") is None


def test_wrench_tracking_and_saturation_checks() -> None:
    assert wrench_violation(np.array([40.0, 50.0, 30.0, 0, 0, 0]), 70.0, 12.0).reason == \
        "force_limit"
    assert wrench_violation(np.array([0, 0, 0, 0.0, 12.5, 0]), 70.0, 12.0).reason == \
        "torque_limit"
    assert wrench_violation(np.array([40.0, 0, 0, 5.0, 0, 0]), 70.0, 12.0) is None
    T = np.eye(4)
    T2 = _pose(so3_exp(np.array([0.0, 0.0, 0.7])), np.array([0.0, 0.05, 0.0]))
    assert tracking_violation(T, T2, 0.1, 0.6).reason == "tracking_error"
    assert tracking_violation(T, T2, 0.01, 1.0).reason == "tracking_error"
    assert tracking_violation(T, T2, 0.1, 1.0) is None
    watch = SaturationWatch(0.005, 0.001)
    assert [watch.update(s) is not None for s in (1, 1, 0, 1, 1, 1, 1, 1)] == \
        [False] * 7 + [True]


# --- config ---


def test_config_defaults_and_validation() -> None:
    c = RobotBridgeConfig()
    assert c.force_limit_n == 70.0 and np.allclose(c.base_T_camera(), np.eye(4))
    with pytest.raises(ValueError, match="reflex_force_threshold_n"):
        RobotBridgeConfig(force_limit_n=120.0)
    with pytest.raises(ValueError, match="rigid transform"):
        RobotBridgeConfig(T_base_camera=(2.0,) + (0.0,) * 14 + (1.0,))
    with pytest.raises(ValueError, match="backend"):
        RobotBridgeConfig(backend="ur5")
    with pytest.raises(ValueError, match="Cartesian limits"):
        RobotBridgeConfig(max_angular_speed_rad_per_s=3.0)
    assert (c.max_axis_direction_std_deg, c.max_axis_position_std_m) == (5.0, 0.01)
    for name in ("max_axis_direction_std_deg", "max_axis_position_std_m", "request_timeout_s"):
        with pytest.raises(ValueError, match=name):
            RobotBridgeConfig(**{name: 0.0})


def test_config_from_args_reads_overrides() -> None:
    args = argparse.Namespace(config=None, overrides=["robot_bridge.force_limit_n=50",
                                                      "robot_bridge.sim_object=\"bolt\""])
    c = config_from_args(args)
    assert c.force_limit_n == 50.0 and c.sim_object == "bolt"


def test_package_imports_without_panda_py() -> None:
    modules = ["executor", "service", "pandapy_backend", "backend", "factory"]
    if importlib.util.find_spec("mujoco") is not None:
        modules += ["simulation", "mujoco_backend"]
    for module in modules:
        importlib.import_module(f"services.robot_bridge.{module}")
    assert "panda_py" not in sys.modules
