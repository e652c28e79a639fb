"""``ArticulateResult.detail`` and ``plan`` (additive, optional on the wire), and the JSON form of
messages read back (``Message.from_json_obj``)."""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest

from services.common import protocol as p
from tests.common import samples


def _plan() -> p.ArticulatePlan:
    return p.ArticulatePlan(
        joint_type="revolute", axis=np.array([0.0, 0.6, 0.8]), point=np.array([0.5, 0.0, 0.3]),
        amount=-3.0, duration_s=6.0, hold_s=0.5, peak_linear_speed_m_per_s=0.01,
        peak_angular_speed_rad_per_s=0.94, force_limit_n=60.0, wrist_torque_limit_nm=12.0,
        max_linear_speed_m_per_s=0.25, max_angular_speed_rad_per_s=2.0)


def _result(**extra: object) -> p.ArticulateResult:
    return p.ArticulateResult(success=False, reason="too_fast", articulated=0.0,
                              peak_force_n=0.0, mean_force_n=0.0, duration_s=0.0,
                              **extra)  # type: ignore[arg-type]


def test_detail_and_plan_round_trip_bit_exact() -> None:
    result = _result(detail="peak speed 2.2 rad/s exceeds 2.0 rad/s; use a longer duration",
                     plan=_plan())
    wire = result.to_msgpack()
    decoded = p.ArticulateResult.from_msgpack(wire)
    assert decoded.to_msgpack() == wire
    assert decoded.detail == result.detail
    assert decoded.plan is not None and decoded.plan.amount == -3.0
    assert np.array_equal(decoded.plan.axis, [0.0, 0.6, 0.8])
    json.dumps(decoded.to_json_obj())


def test_a_result_without_detail_or_plan_still_decodes() -> None:
    """What a bridge from before ``detail`` sends."""
    old = {"schema": "handkse.ArticulateResult/1", "seq": 0, "stamp_ns": 0,
           "frame_id": "camera", "success": True, "reason": "ok", "articulated": 1.0,
           "peak_force_n": 3.0, "mean_force_n": 2.0, "duration_s": 2.5}
    decoded = p.ArticulateResult.from_msgpack(msgpack.packb(old))
    assert (decoded.detail, decoded.plan) == ("", None)
    assert decoded.articulated == 1.0


def test_bad_detail_or_plan_is_named() -> None:
    obj = msgpack.unpackb(_result(plan=_plan()).to_msgpack())
    for change, message in (
            ({"detail": 3}, "ArticulateResult.detail: expected str"),
            ({"plan": {**obj["plan"], "joint_type": "screw"}},
             "ArticulateResult.plan.joint_type: 'screw' is not one of"),
            ({"plan": {**obj["plan"], "axis": p.encode_array(np.array([0.0, 0.0, 2.0]))}},
             "ArticulateResult.plan.axis: axis must be unit length"),
            ({"plan": {**obj["plan"], "duration_s": -1.0}},
             r"ArticulateResult.plan.duration_s: -1.0 outside \[0.0, inf\]")):
        with pytest.raises(p.ProtocolError, match=message):
            p.ArticulateResult.from_msgpack(msgpack.packb({**obj, **change}))


def test_json_form_reads_back() -> None:
    model = samples.kinematic_model()
    doc = json.loads(json.dumps(model.to_json_obj()))
    assert p.KinematicModel.from_json_obj(doc) == model
    request = p.ArticulateRequest(amount=1.0, duration_s=2.0, model=model)
    doc = json.loads(json.dumps(request.to_json_obj()))
    assert p.ArticulateRequest.from_json_obj(doc) == request


def test_json_form_is_validated_like_the_wire() -> None:
    doc = json.loads(json.dumps(samples.kinematic_model().to_json_obj()))
    doc["revolute"]["axis"] = [0.0, 0.0]
    with pytest.raises(p.ProtocolError, match=r"KinematicModel.revolute.axis: shape must be \[3\]"):
        p.KinematicModel.from_json_obj(doc)
    doc["revolute"]["axis"] = ["x", 0.0, 1.0]
    with pytest.raises(p.ProtocolError, match=r"revolute.axis: expected nested lists of numbers"):
        p.KinematicModel.from_json_obj(doc)
    with pytest.raises(p.ProtocolError, match="KinematicModel: expected a map"):
        p.KinematicModel.from_json_obj([1, 2])


def test_the_wire_never_takes_lists_for_arrays() -> None:
    obj = msgpack.unpackb(samples.kinematic_model().to_msgpack())
    obj["reference_pose"] = np.eye(4).tolist()
    with pytest.raises(p.ProtocolError, match="reference_pose: expected an array map"):
        p.KinematicModel.from_msgpack(msgpack.packb(obj))
