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
