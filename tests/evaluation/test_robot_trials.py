"""The simulated robot trials (``handkse robot-trials``): baseline models, one trial, the report."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.protocol import KinematicModel
from services.evaluation.robot_plots import read_rows, read_traces
from services.evaluation.robot_trials import (
    REPORT_FILES,
    demonstrated_extent,
    model_from_estimate,
    run_trial,
    table_markdown,
    write_report,
)
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.simulation import object_in_camera
from services.synthetic.generator import generate


@pytest.mark.parametrize("name", ["window_lock", "flap_latch", "bolt"])
def test_demonstrated_extent_of_a_baseline_estimate(name: str) -> None:
    """The opening stroke seen in the landmarks, even when the human turned back afterwards."""
    demo = generate(name, 3, 0)
    obj = object_in_camera(demo)
    points = np.asarray(demo.points, float)
    for flip in (1.0, -1.0):
        axis = flip * obj.axis
        extent = demonstrated_extent(obj.joint_type, axis, obj.point, points)
        assert 0.5 < extent / (flip * obj.demonstrated) < 1.5
        model = model_from_estimate(obj.joint_type, axis, obj.point, demo)
        q = model.revolute.q if model.revolute is not None else model.prismatic.q  # type: ignore[union-attr]
        assert q == pytest.approx(extent)
        assert KinematicModel.from_msgpack(model.to_msgpack()) == model
    assert model_from_estimate("rigid", np.zeros(3), np.zeros(3), demo).type == "rigid"


def test_one_trial_and_the_report(tmp_path: Path) -> None:
    row, trace = run_trial("key", 4, "regal", RobotBridgeConfig())
    assert row.object == "key" and row.method == "regal" and row.type_est == "revolute"
    assert len(trace["t_s"]) == len(trace["force_n"]) > 100
    rows = [row]
    md = table_markdown(rows, ["regal"], "test")
    assert "| Regal et al.-style |" in md and ("1/1" in md or "0/1" in md)
    write_report(rows, {("key", 4, "regal"): trace}, ["regal"], tmp_path, 4, 70.0, "test")
    for name in REPORT_FILES:
        assert (tmp_path / name).stat().st_size > 0
    # the figures can be redrawn from the files alone
    assert read_rows(tmp_path / "results.csv") == rows
    back = read_traces(tmp_path / "traces.json")[("key", 4, "regal")]
    assert len(back["t_s"]) == len(trace["t_s"]) and back["stop_s"] == pytest.approx(
        trace["stop_s"], abs=1e-3)


def test_one_closed_loop_trial() -> None:
    """``--closed-loop``: the same task, refined from the robot's own motion, still succeeds
    within the limits (a good baseline estimate, the key)."""
    row, trace = run_trial("key", 4, "regal", RobotBridgeConfig(), closed_loop=True)
    assert row.success, row.reason
    assert abs(row.articulated_deg) > 170.0 and 0.0 < row.peak_force_n < 70.0
    assert len(trace["t_s"]) > 100
