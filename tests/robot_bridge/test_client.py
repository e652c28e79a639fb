"""``handkse articulate`` without a bus: defaults, the request, the printed block, model files.

The command over a real router and robot bridge process is in
:mod:`tests.robot_bridge.test_articulate_cli`.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest

from services.common.errors import UserError
from services.common.protocol import (
    ArticulatePlan,
    ArticulateResult,
    KinematicModel,
    PrismaticParams,
    RevoluteParams,
)
from services.robot_bridge.client import (
    ArticulateOptions,
    default_amount,
    format_result,
    load_model,
    request_for,
)
from tests.common import samples

PROBS = {"rigid": 0.0, "prismatic": 0.0, "revolute": 0.0, "disconnected": 0.0}


def _revolute(q: float) -> KinematicModel:
    return KinematicModel(type="revolute", probabilities={**PROBS, "revolute": 1.0},
                          revolute=RevoluteParams(axis=np.array([0.0, 0.0, 1.0]),
                                                  point=np.zeros(3), q=q, dq=0.0,
                                                  covariance=np.zeros((7, 7))))


def _prismatic(q: float) -> KinematicModel:
    return KinematicModel(type="prismatic", probabilities={**PROBS, "prismatic": 1.0},
                          prismatic=PrismaticParams(axis=np.array([1.0, 0.0, 0.0]), q=q,
                                                    dq=0.0, covariance=np.zeros((4, 4))))


def test_default_amount_is_the_papers_half_turn_or_the_demonstrated_stroke() -> None:
    assert default_amount(_revolute(2.07)) == math.pi
    assert default_amount(_revolute(-0.5)) == -math.pi
    assert default_amount(_prismatic(-0.084)) == -0.084
    with pytest.raises(UserError, match=r"too small to tell which way .* give --amount"):
        default_amount(_revolute(0.01))
    with pytest.raises(UserError, match=r"0.2 mm, too small for a stroke: give --amount"):
        default_amount(_prismatic(0.0002))
    with pytest.raises(UserError, match="the model is rigid, not a joint"):
        default_amount(KinematicModel(type="rigid", probabilities={**PROBS, "rigid": 1.0}))


def test_the_model_is_read_only_for_a_default() -> None:
    def no_model() -> KinematicModel:
        raise AssertionError("the model was read although amount and duration were given")

    given = request_for(ArticulateOptions(amount=0.5, duration_s=2.0, dry_run=True), no_model)
    assert (given.amount, given.duration_s, given.dry_run) == (0.5, 2.0, True)
    assert given.timeout_s == pytest.approx(3 * 2.0 + 10.0)
    assert abs(given.stamp_ns - time.time_ns()) < 10 * 10**9  # stamped when sent
    chosen = request_for(ArticulateOptions(timeout_s=30.0), lambda: _revolute(-1.0))
    assert chosen.amount == -math.pi and chosen.duration_s == pytest.approx(6.0)
    assert chosen.timeout_s == 30.0 and chosen.model is None
    stroke = request_for(ArticulateOptions(amount=0.05), lambda: _prismatic(0.08))
    assert stroke.duration_s == pytest.approx(2.5)  # 2 cm/s


PLAN = ArticulatePlan(joint_type="revolute", axis=np.array([0.0, 0.0, 1.0]),
                      point=np.array([0.5, 0.0, 0.4]), amount=-math.pi, duration_s=6.0,
                      hold_s=0.5, peak_linear_speed_m_per_s=0.0,
                      peak_angular_speed_rad_per_s=0.98, force_limit_n=70.0,
                      wrist_torque_limit_nm=12.0, max_linear_speed_m_per_s=0.25,
                      max_angular_speed_rad_per_s=2.0)


def _result(success: bool, reason: str, detail: str, *, moved: bool = False,
            plan: ArticulatePlan | None = PLAN) -> ArticulateResult:
    return ArticulateResult(stamp_ns=time.time_ns() - 3 * 10**9, success=success, reason=reason,
                            articulated=-1.2 if moved else 0.0, peak_force_n=75.0 if moved else 0,
                            mean_force_n=20.0 if moved else 0.0,
                            duration_s=2.0 if moved else (6.5 if success else 0.0),
                            detail=detail, plan=plan)


def _lines(text: str) -> dict[str, str]:
    rows = [line.split(None, 1) for line in text.splitlines()[1:]]
    return {name: rest for name, rest in rows}


def test_a_dry_run_prints_the_plan_and_its_limits() -> None:
    text = format_result(_result(True, "dry_run", "would articulate -180.0 deg in 6.0 s"))
    assert text.splitlines()[0] == "articulate (dry run): OK (dry_run)"
    rows = _lines(text)
    assert rows["joint"] == ("revolute, axis [+0.000, +0.000, +1.000] through "
                             "[+0.500, +0.000, +0.400] m (robot base frame)")
    assert rows["motion"] == ("-180.0 deg in 6.0 s, then 0.5 s hold; peak speed 0.000 m/s, "
                              "0.98 rad/s")
    assert rows["limits"] == "force 70.0 N, wrist torque 12.0 N m, speed 0.25 m/s and 2.00 rad/s"
    assert rows["model"].startswith("stamped 3.") and rows["model"].endswith("frame camera")
    assert "reached" not in rows


def test_a_refusal_prints_the_reason_and_what_to_do() -> None:
    text = format_result(_result(False, "stale_model", "model is 1796151190 s old (limit 120 "
                                 "s): replay with wall-clock stamps", plan=None))
    assert text.splitlines()[0] == "articulate: REFUSED (stale_model)"
    assert _lines(text)["detail"].startswith("model is 1796151190 s old")


def test_an_abort_prints_how_far_it_got_and_the_forces() -> None:
    text = format_result(_result(False, "force_limit", "|F| = 75.0 N exceeded 70.0 N",
                                 moved=True))
    assert text.splitlines()[0] == "articulate: FAILED (force_limit)"
    rows = _lines(text)
    assert rows["reached"] == "-68.8 deg of -180.0 deg"
    assert rows["force"] == "peak 75.0 N, mean 20.0 N"
    assert rows["duration"] == "2.0 s"


def test_a_success_prints_the_result() -> None:
    text = format_result(_result(True, "ok", "articulated -179.9 deg of -180.0 deg in 6.5 s"))
    assert text.splitlines()[0] == "articulate: SUCCESS (ok)"
    assert _lines(text)["reached"] == "+0.0 deg of -180.0 deg"


def test_model_files_json_and_msgpack(tmp_path: Path) -> None:
    model = samples.kinematic_model()
    as_json = tmp_path / "model.json"
    as_json.write_text(json.dumps(model.to_json_obj(), indent=2))
    as_msgpack = tmp_path / "model.msgpack"
    as_msgpack.write_bytes(model.to_msgpack())
    assert load_model(as_json) == model
    assert load_model(as_msgpack) == model
    with pytest.raises(UserError, match=r"--model-file .*missing.json does not exist"):
        load_model(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text('{"schema": "handkse.KinematicModel/1"}')
    with pytest.raises(UserError, match=r"is not a KinematicModel .*KinematicModel.seq: missing"):
        load_model(tmp_path / "bad.json")
    (tmp_path / "junk").write_bytes(b"\x00\x01junk")
    with pytest.raises(UserError, match="junk is not a KinematicModel"):
        load_model(tmp_path / "junk")
