"""Perturbed starting models (``handkse robot-trials --perturbed``): the perturbation, one trial,
the report, and the command line."""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.evaluation import robot_perturbations as rp
from services.evaluation.robot_trials import DEFAULT_CASES_TEXT
from services.robot_bridge.simulation import grasp_in_camera, object_in_camera
from services.synthetic.generator import generate
from tests.conftest import Processes


@pytest.mark.parametrize("name", rp.OBJECTS)
@pytest.mark.parametrize("tilt_deg,offset_mm", [(10.0, 0.0), (0.0, 10.0), (20.0, 5.0)])
def test_the_perturbation_is_the_one_asked_for(name: str, tilt_deg: float,
                                                offset_mm: float) -> None:
    """The model's axis is ``tilt_deg`` off the truth and ``offset_mm`` from it at the grasp,
    in every direction, and it claims the confidence our estimator publishes."""
    obj = object_in_camera(generate(name, 3, 0))
    grasp = grasp_in_camera(obj)[:3, 3]
    a, c = np.asarray(obj.axis), np.asarray(obj.point)
    radial = (grasp - c) - float((grasp - c) @ a) * a
    lever_mm = float(np.linalg.norm(radial)) * 1e3
    for k in range(4):
        model = rp.perturbed_model(obj, tilt_deg, offset_mm, 2.0 * math.pi * k / 4, grasp)
        rev = model.revolute
        assert rev is not None and model.type == "revolute"
        b = np.asarray(rev.axis)
        assert math.degrees(math.acos(min(1.0, float(a @ b)))) == pytest.approx(tilt_deg,
                                                                                abs=1e-6)
        angle, dist = rp._errors(b, np.asarray(rev.point), a, c, grasp)
        assert angle == pytest.approx(tilt_deg, abs=1e-6)
        # The offset is perpendicular to the true axis at the foot; the tilt about that foot
        # moves the perturbed axis' own foot only to second order ((lever + offset) sin^2 tilt).
        second = (lever_mm + offset_mm) * math.sin(math.radians(tilt_deg)) ** 2
        assert dist == pytest.approx(offset_mm, abs=1.2 * second + 1e-6)
        assert float(np.asarray(rev.point) @ b) == pytest.approx(0.0, abs=1e-12)
        assert np.all(np.linalg.eigvalsh(np.asarray(rev.covariance)) > -1e-12)


def test_one_case_open_and_closed_loop_and_the_report(tmp_path: Path) -> None:
    """One small case (window lock, axis moved 5 mm): both loops run under the same limits;
    open loop keeps the perturbed axis, closed loop refines it; the report round-trips."""
    rows = rp.run_perturbed(("window_lock",), ((0.0, 5.0),), n_directions=1)
    assert [(r.object, r.loop, r.direction) for r in rows] == [
        ("window_lock", "open", 0), ("window_lock", "closed", 0)]
    open_row, closed_row = rows
    assert open_row.reason in ("ok", "force_limit", "torque_saturation", "incomplete",
                               "tracking_error", "joint_limits")
    assert open_row.final_axis_error_deg == pytest.approx(0.0, abs=1e-6)
    assert open_row.final_position_error_mm == pytest.approx(5.0, abs=0.5)
    assert closed_row.success, closed_row.reason
    assert closed_row.articulated_deg > 170.0
    assert 0.0 < closed_row.peak_force_n <= 70.0
    assert closed_row.final_position_error_mm < open_row.final_position_error_mm
    assert math.isnan(open_row.refined_axis_error_90_deg)
    assert closed_row.robot_axis_error_90_deg < 1.0
    table, csv_path = rp.write_report(rows, tmp_path, "test", "Machine: test.")
    assert _comparable(rp.read_rows(csv_path)) == _comparable(rows)
    md = table.read_text()
    assert md.startswith("# test\n\nMachine: test.\n")
    assert "| window_lock | 0 | 5 | closed | 1/1 |" in md


def _comparable(rows: list[rp.PerturbedRow]) -> list[dict[str, object]]:
    """Rows as dicts with NaN as None (NaN != NaN)."""
    return [{k: None if isinstance(v, float) and math.isnan(v) else v
             for k, v in asdict(r).items()} for r in rows]


def test_cases_on_the_command_line() -> None:
    assert rp.parse_cases(DEFAULT_CASES_TEXT) == rp.CASES
    assert rp.parse_cases("10:10, 20:0") == ((10.0, 10.0), (20.0, 0.0))
    for bad in ("10", "a:b", "-5:0", "nan:1", ""):
        with pytest.raises(ValueError, match="perturbed case"):
            rp.parse_cases(bad)


def test_robot_trials_perturbed_command(procs: Processes, tmp_path: Path) -> None:
    """``handkse robot-trials --perturbed`` as a user runs it, kept to one case, one direction,
    one object: the table and the CSV of both loops."""
    out = tmp_path / "perturbed"
    result = procs.run("robot-trials", "--perturbed", "--cases", "0:5", "--directions", "1",
                       "--objects", "key", "--jobs", "1", "--out", str(out), timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    rows = rp.read_rows(out / rp.CSV_FILE)
    assert [(r.object, r.tilt_deg, r.offset_mm, r.loop) for r in rows] == [
        ("key", 0.0, 5.0, "open"), ("key", 0.0, 5.0, "closed")]
    md = (out / rp.TABLE_FILE).read_text()
    assert "Machine: " in md and "| key | 0 | 5 | open |" in md
    assert "| key | 0 | 5 | closed |" in result.stdout
    bad = procs.run("robot-trials", "--perturbed", "--objects", "door", "--out", str(out))
    assert bad.returncode != 0 and "door" in bad.stderr
