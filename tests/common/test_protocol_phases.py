"""The contact-phase fields of KinematicModel, KinematicModelList and ArticulateRequest.segment
(docs/protocol.md): additive, validated, in msgpack and JSON."""

from __future__ import annotations

import dataclasses
import json

import msgpack
import pytest

from services.common import protocol as p
from services.robot_bridge.safety import Refusal, choose_segment
from tests.common import samples


def _phase(segment: int, start: int | None, end: int | None, phase: str = "free",
           first: int | None = None) -> p.KinematicModel:
    return dataclasses.replace(samples.kinematic_model(segment), segment=segment,
                               segment_start_ns=start, segment_end_ns=end, phase=phase,
                               first_segment=first)


def test_the_phase_fields_round_trip_and_stay_absent_when_unset() -> None:
    model = _phase(2, 1_000, 5_000, "contact", first=1)
    back = p.KinematicModel.from_msgpack(model.to_msgpack())
    assert (back.segment, back.segment_start_ns, back.segment_end_ns, back.phase,
            back.first_segment) == (2, 1_000, 5_000, "contact", 1)
    plain = samples.kinematic_model()
    wire = msgpack.unpackb(plain.to_msgpack(), raw=False)
    assert wire["segment"] == 0
    assert not {"segment_start_ns", "segment_end_ns", "phase", "first_segment"} & set(wire)
    # A producer that does not segment (the fields absent): still a valid KinematicModel/1.
    del wire["segment"]
    old = p.KinematicModel.from_msgpack(msgpack.packb(wire, use_bin_type=True))
    assert (old.segment, old.phase, old.segment_start_ns) == (0, None, None)


@pytest.mark.parametrize(("changes", "message"), [
    ({"segment": -1}, "segment: -1 is below 0"),
    ({"segment_start_ns": 10, "segment_end_ns": 5}, "segment_end_ns: 5 needs"),
    ({"segment_start_ns": None, "segment_end_ns": 5}, "segment_end_ns: 5 needs"),
    ({"phase": "holding"}, "phase: 'holding' is not one of"),
    ({"first_segment": 3}, "first_segment: 3 is after segment 2"),
])
def test_bad_phase_fields_are_rejected_naming_the_field(changes: dict[str, object],
                                                       message: str) -> None:
    wire = msgpack.unpackb(_phase(2, 1_000, 5_000).to_msgpack(), raw=False)
    wire.update(changes)
    with pytest.raises(p.ProtocolError, match=message) as info:
        p.KinematicModel.from_msgpack(msgpack.packb(wire, use_bin_type=True))
    assert info.value.reason == "bad_field"


def test_a_model_list_round_trips_in_msgpack_and_json_oldest_first() -> None:
    models = (_phase(0, 1_000, 2_000), _phase(1, 3_000, None, "contact", first=0))
    listed = p.KinematicModelList(seq=4, stamp_ns=3_500, models=models)
    back = p.KinematicModelList.from_msgpack(listed.to_msgpack())
    assert [m.to_msgpack() for m in back.models] == [m.to_msgpack() for m in models]
    as_json = json.loads(json.dumps(listed.to_json_obj()))
    assert as_json["schema"] == "handkse.KinematicModelList/1"
    assert [m["segment"] for m in as_json["models"]] == [0, 1]
    assert "segment_end_ns" not in as_json["models"][1]
    from_json = p.KinematicModelList.from_json_obj(as_json)
    assert [m.to_msgpack() for m in from_json.models] == [m.to_msgpack() for m in models]
    empty = p.KinematicModelList.from_msgpack(p.KinematicModelList().to_msgpack())
    assert empty.models == ()


def test_a_bad_model_in_a_list_is_named() -> None:
    wire = msgpack.unpackb(p.KinematicModelList(models=(_phase(0, 1, 2),)).to_msgpack(),
                           raw=False)
    wire["models"][0]["type"] = "hinge"
    with pytest.raises(p.ProtocolError, match=r"models\[0\]\.type"):
        p.KinematicModelList.from_msgpack(msgpack.packb(wire, use_bin_type=True))
    wire["models"] = {"not": "a list"}
    with pytest.raises(p.ProtocolError, match="models: expected a list"):
        p.KinematicModelList.from_msgpack(msgpack.packb(wire, use_bin_type=True))


def test_an_articulate_request_may_name_a_segment() -> None:
    request = p.ArticulateRequest(amount=0.3, duration_s=2.0, segment=1)
    assert p.ArticulateRequest.from_msgpack(request.to_msgpack()).segment == 1
    default = p.ArticulateRequest(amount=0.3, duration_s=2.0)
    assert "segment" not in msgpack.unpackb(default.to_msgpack(), raw=False)
    assert p.ArticulateRequest.from_msgpack(default.to_msgpack()).segment is None
    wire = msgpack.unpackb(request.to_msgpack(), raw=False)
    wire["segment"] = -2
    with pytest.raises(p.ProtocolError, match="segment"):
        p.ArticulateRequest.from_msgpack(msgpack.packb(wire, use_bin_type=True))


def test_the_bridge_refuses_an_open_or_missing_segment() -> None:
    models = (_phase(0, 1_000, 2_000), _phase(1, 3_000, None, "contact"))
    assert choose_segment(models, 0) is models[0]
    open_one = choose_segment(models, 1)
    assert isinstance(open_one, Refusal) and open_one.reason == "open_segment"
    missing = choose_segment(models, 5)
    assert isinstance(missing, Refusal) and missing.reason == "no_segment"
    assert "0, 1" in missing.detail
