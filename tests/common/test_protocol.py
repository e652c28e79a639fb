"""Wire protocol: bit-exact round trips and strict, field-naming rejection of bad payloads."""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.common import protocol as p
from tests.common import samples

ALL = samples.all_messages()


@pytest.mark.parametrize("message", ALL, ids=lambda m: type(m).__name__)
def test_round_trip_is_bit_exact(message: p.Message) -> None:
    wire = message.to_msgpack()
    decoded = type(message).from_msgpack(wire)
    assert decoded.to_msgpack() == wire
    assert decoded == message
    json.dumps(decoded.to_json_obj())  # JSON form always serialisable


def test_arrays_keep_bits_and_nan() -> None:
    msg = samples.hand_landmarks()
    out = p.HandLandmarks.from_msgpack(msg.to_msgpack())
    a, b = msg.hands[0].points, out.hands[0].points
    assert a.tobytes() == b.tobytes()
    assert np.isnan(b[3]).all()
    assert b.dtype.str == "<f4"


def test_decoding_does_not_copy_arrays_twice() -> None:
    out = p.HandBody.from_msgpack(samples.hand_body().to_msgpack())
    assert not out.pose.flags.writeable  # a frombuffer view, not a copy


@given(st.binary(max_size=300))
@settings(max_examples=300, deadline=None)
def test_garbage_raises_protocol_error(data: bytes) -> None:
    for cls in p.MESSAGE_TYPES:
        with pytest.raises(p.ProtocolError):
            cls.from_msgpack(data)


@given(st.recursive(st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats()
                    | st.text(max_size=5) | st.binary(max_size=20),
                    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c,
                                                                         max_size=5),
                    max_leaves=20))
@settings(max_examples=300, deadline=None)
def test_random_msgpack_structures_raise_protocol_error(obj: object) -> None:
    data = msgpack.packb(obj, use_bin_type=True)
    for cls in p.MESSAGE_TYPES:
        with pytest.raises(p.ProtocolError):
            cls.from_msgpack(data)


@pytest.mark.parametrize("message", ALL, ids=lambda m: type(m).__name__)
def test_truncated_payloads_are_rejected(message: p.Message) -> None:
    wire = message.to_msgpack()
    for cut in sorted({1, 2, len(wire) // 3, len(wire) // 2, len(wire) - 1}):
        with pytest.raises(p.ProtocolError):
            type(message).from_msgpack(wire[:cut])


def _mutate(message: p.Message, path: list[str], value: object) -> bytes:
    obj = msgpack.unpackb(message.to_msgpack(), raw=False)
    target = obj
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return msgpack.packb(obj, use_bin_type=True)


def _array(a: np.ndarray) -> dict[str, object]:
    return p.encode_array(a)


BAD_CASES = [
    ("wrong schema", samples.hand_body(), ["schema"], "handkse.HandLandmarks/1", "schema"),
    ("unknown major", samples.hand_body(), ["schema"], "handkse.HandBody/2", "major version"),
    ("negative seq", samples.hand_body(), ["seq"], -1, "seq"),
    ("bad frame", samples.hand_body(), ["frame_id"], "base", "frame_id"),
    ("wrong dtype", samples.hand_body(), ["pose"], _array(np.eye(4, dtype="<f4")), "pose"),
    ("wrong shape", samples.hand_body(), ["twist"], _array(np.zeros(5)), "twist"),
    ("nan pose", samples.hand_body(), ["pose"], _array(np.full((4, 4), np.nan)), "pose"),
    ("not rigid", samples.hand_body(), ["pose"], _array(2 * np.eye(4)), "pose"),
    ("bad status", samples.hand_body(), ["landmarks", "status"],
     _array(np.full(21, 9, "|u1")), "status"),
    ("bad motion model", samples.hand_body(), ["motion_model"], "teleport", "motion_model"),
    ("length mismatch", samples.hand_body(), ["twist"],
     {"dtype": "<f8", "shape": [6], "data": b"\0" * 47}, "twist"),
    ("non unit axis", samples.kinematic_model(), ["revolute", "axis"],
     _array(np.array([1.0, 1.0, 0.0])), "axis"),
    ("probabilities", samples.kinematic_model(), ["probabilities", "rigid"], 0.9,
     "probabilities"),
    ("unknown type", samples.kinematic_model(), ["type"], "helical", "type"),
    ("visibility range", samples.hand_landmarks(), ["hands", 0, "visibility"],
     _array(np.full(21, 2.0, "<f4")), "visibility"),
    ("inf landmark", samples.hand_landmarks(), ["hands", 0, "points"],
     _array(np.full((21, 3), np.inf, "<f4")), "points"),
    ("object dtype", samples.hand_landmarks(), ["hands", 0, "visibility"],
     {"dtype": "|O", "shape": [21], "data": b"\0" * 168}, "visibility"),
    ("raw image size", samples.rgbd_frame(), ["color", "data"], b"\0" * 10, "color.data"),
]


@pytest.mark.parametrize(("name", "message", "path", "value", "field"), BAD_CASES,
                         ids=[c[0] for c in BAD_CASES])
def test_invalid_fields_are_named(name: str, message: p.Message, path: list[str],
                                  value: object, field: str) -> None:
    with pytest.raises(p.ProtocolError, match=field):
        type(message).from_msgpack(_mutate(message, path, value))


def _bad_pose(kind: str) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (0.1, 0.2, 0.6)
    if kind == "skewed":
        T[:3, :3] *= 1.01
    elif kind == "reflected":
        T[0, 0] = -1.0
    else:  # an inexact bottom row
        T[3, 2] = 1e-12
    return T


@pytest.mark.parametrize(("kind", "problem"), [
    ("skewed", "not orthonormal"), ("reflected", "determinant"), ("bottom", "bottom row")])
@pytest.mark.parametrize(("message", "path"), [
    (samples.hand_body(), ["pose"]), (samples.kinematic_model(), ["reference_pose"]),
    (samples.hand_landmarks(), ["T_world_camera"])], ids=["body", "model", "landmarks"])
def test_non_rigid_poses_are_rejected_at_decode(kind: str, problem: str, message: p.Message,
                                                path: list[str]) -> None:
    """Decoding is where handkse checks that a pose is rigid (services.common.se3.check_pose);
    the libraries that receive decoded messages do not check again."""
    field = f"{type(message).__name__}.{path[0]}: not a rigid transform: "
    with pytest.raises(p.ProtocolError, match=field + ".*" + problem) as info:
        type(message).from_msgpack(_mutate(message, path, _array(_bad_pose(kind))))
    assert info.value.reason == "bad_field"


def test_unknown_extra_keys_are_ignored() -> None:
    msg = samples.kinematic_model()
    obj = msgpack.unpackb(msg.to_msgpack(), raw=False)
    obj["future_field"] = {"anything": [1, 2, 3]}
    obj["revolute"]["also_new"] = "x"
    out = p.KinematicModel.from_msgpack(msgpack.packb(obj, use_bin_type=True))
    assert out == msg


def test_error_reason_labels() -> None:
    with pytest.raises(p.ProtocolError) as e:
        p.HandBody.from_msgpack(b"\xc1")
    assert e.value.reason == "bad_msgpack"
    with pytest.raises(p.ProtocolError) as e:
        p.HandBody.from_msgpack(samples.hand_landmarks().to_msgpack())
    assert e.value.reason == "wrong_schema"


def test_documents_round_trip_with_writable_arrays() -> None:
    doc = {"x": np.arange(6.0).reshape(2, 3), "n": [1, {"y": np.zeros(2, "<u2")}], "s": "a"}
    out = p.unpack_document(p.pack_document(doc))
    assert np.array_equal(out["x"], doc["x"]) and out["x"].flags.writeable
    assert out["n"][1]["y"].dtype == np.dtype("<u2")
    assert out["s"] == "a"


def test_peek_envelope() -> None:
    msg = samples.hand_body()
    assert p.peek_envelope(msg.to_msgpack()) == ("handkse.HandBody/1", 123)
    assert p.peek_envelope(b"garbage") == (None, None)


def test_a_required_array_sent_as_nil_is_a_bad_field() -> None:
    doc = msgpack.unpackb(samples.hand_body().to_msgpack(), raw=False)
    doc["pose"] = None
    with pytest.raises(p.ProtocolError) as info:
        p.HandBody.from_msgpack(msgpack.packb(doc, use_bin_type=True))
    assert info.value.reason == "bad_field" and "pose" in str(info.value)


# Payloads an attacker found to escape ProtocolError (ValueError, SyntaxError, OverflowError,
# TypeError from numpy and int()): each must be a ProtocolError with a reason, naming the field.
ESCAPES = [
    ("5000-digit version", ["schema"], "handkse.HandBody/" + "1" * 5000, "schema", "wrong_version"),
    ("dtype of digits", ["twist"], {"dtype": "9" * 5000, "shape": [6], "data": b"\0" * 48},
     "twist", "bad_field"),
    ("structured dtype", ["twist"], {"dtype": "f8,f8", "shape": [3], "data": b"\0" * 48},
     "twist", "bad_field"),
    ("sub-array dtype", ["twist"], {"dtype": "(2)f8", "shape": [3], "data": b"\0" * 48},
     "twist", "bad_field"),
    ("dtype not a string", ["twist"], {"dtype": 8, "shape": [6], "data": b"\0" * 48},
     "twist", "bad_field"),
    ("infinite dimension", ["twist"], {"dtype": "<f8", "shape": [float("inf"), 3], "data": b""},
     "twist", "bad_field"),
    ("huge shape", ["twist"], {"dtype": "<f8", "shape": [2**40, 2**40], "data": b""},
     "twist", "bad_field"),
    ("bool dimension", ["twist"], {"dtype": "<f8", "shape": [True], "data": b"\0" * 8},
     "twist", "bad_field"),
    ("shape not a list", ["twist"], {"dtype": "<f8", "shape": 6, "data": b"\0" * 48},
     "twist", "bad_field"),
]


@pytest.mark.parametrize(("name", "path", "value", "field", "reason"), ESCAPES,
                         ids=[c[0] for c in ESCAPES])
def test_malformed_payloads_are_protocol_errors(name: str, path: list[str], value: object,
                                                field: str, reason: str) -> None:
    with pytest.raises(p.ProtocolError, match=field) as e:
        p.HandBody.from_msgpack(_mutate(samples.hand_body(), path, value))
    assert e.value.reason == reason
