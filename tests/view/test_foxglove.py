"""Recordings Foxglove can show: ``handkse export`` and ``handkse record --foxglove``, decoded
back through the channels' own protobuf schemas with the ``mcap`` reader."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.common.keys import Keys
from services.common.protocol import Message
from services.common.recording import read_recording, write_recording
from services.common.se3 import se3_exp
from services.view import geometry as geo
from tests.common import samples
from tests.conftest import Processes, output_of, wait_until, zenoh_args

pytest.importorskip("foxglove", reason="the Foxglove export needs the 'view' extra (foxglove-sdk)")
decoder = pytest.importorskip("mcap_protobuf.decoder",
                              reason="decoding needs mcap-protobuf-support (dev extra)")

from mcap.reader import make_reader  # noqa: E402

KEYS = Keys("fox")
ROOT = "/handkse/fox/foxglove"


def _source_messages() -> list[tuple[str, Message]]:
    """A small demonstration: frames, landmarks, bodies, a revolute then a prismatic model, a
    robot state; stamps increasing, one frame per 33 ms."""
    out: list[tuple[str, Message]] = []
    t0 = 5_000_000_000
    revolute = dataclasses.replace(samples.kinematic_model(1), frame_id="camera")
    prismatic = dataclasses.replace(samples.kinematic_model(2), type="prismatic")
    for i in range(6):
        stamp = t0 + i * 33_000_000
        frame = dataclasses.replace(samples.rgbd_frame(i), stamp_ns=stamp, T_world_camera=None)
        landmarks = dataclasses.replace(samples.hand_landmarks(i), stamp_ns=stamp, seq=i)
        body = dataclasses.replace(samples.hand_body(i), stamp_ns=stamp, seq=i, frame_id="camera",
                                   pose=se3_exp(np.array([0.01 * i, 0, 0.5, 0, 0.1 * i, 0])))
        model = dataclasses.replace(revolute if i < 4 else prismatic, stamp_ns=stamp, seq=i,
                                    updates=10 + i)
        out += [(KEYS.camera_rgbd, frame), (KEYS.hand_landmarks, landmarks),
                (KEYS.hand_body, body), (KEYS.kinematics_model, model)]
    out.append((KEYS.robot_state, dataclasses.replace(samples.robot_state(), stamp_ns=t0)))
    return out


def _decoded(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Topic -> ``[(publish time, decoded protobuf message), ...]`` of the non-msgpack channels."""
    out: dict[str, list[tuple[int, Any]]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[decoder.DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        topics = [c.topic for c in summary.channels.values() if c.message_encoding != "msgpack"]
        for schema, channel, message, proto in reader.iter_decoded_messages(topics=topics):
            assert schema is not None and schema.encoding == "protobuf"
            assert schema.name == proto.DESCRIPTOR.full_name  # decoded through its own schema
            out.setdefault(channel.topic, []).append((message.publish_time, proto))
    return out


def _xyz(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z])


def _rotation(q: Any) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _check_foxglove_channels(path: Path, messages: list[tuple[str, Message]]) -> None:
    channels = _decoded(path)
    for name in ("tf", "hand/trail", "hand/landmarks", "hand/body", "model", "camera/image",
                 "camera/calibration", "camera/landmarks"):
        assert f"{ROOT}/{name}" in channels, (name, sorted(channels))
    by_stamp = {(key, m.stamp_ns): m for key, m in messages}

    for stamp, update in channels[f"{ROOT}/hand/landmarks"]:
        hand = by_stamp[KEYS.hand_landmarks, stamp].hands[0]  # type: ignore[attr-defined]
        (entity,) = update.entities
        finite = hand.points[np.isfinite(hand.points).all(axis=1)]
        spheres = np.array([_xyz(s.pose.position) for s in entity.spheres])
        np.testing.assert_allclose(spheres, finite, atol=1e-7)
        assert entity.frame_id == "camera"

    body_transforms = [(s, tf) for s, tf in channels[f"{ROOT}/tf"] if tf.child_frame_id == "hand"]
    assert len(body_transforms) == 6
    for stamp, tf in body_transforms:
        body = by_stamp[KEYS.hand_body, stamp]
        np.testing.assert_allclose(_xyz(tf.translation), body.pose[:3, 3], atol=1e-12)  # type: ignore[attr-defined]
        np.testing.assert_allclose(_rotation(tf.rotation), body.pose[:3, :3], atol=1e-12)  # type: ignore[attr-defined]
        assert tf.parent_frame_id == "camera"
    assert [len(p.poses) for _, p in channels[f"{ROOT}/hand/trail"]] == [1, 2, 3, 4, 5, 6]

    for stamp, update in channels[f"{ROOT}/model"]:
        model = by_stamp[KEYS.kinematics_model, stamp]
        (entity,) = update.entities
        assert entity.id == "joint" and model.type in entity.texts[0].text  # type: ignore[attr-defined]
        if model.type == "revolute":  # type: ignore[attr-defined]
            r = model.revolute  # type: ignore[attr-defined]
            a, b = (_xyz(p) for p in entity.lines[0].points)
            np.testing.assert_allclose((b - a) / np.linalg.norm(b - a), r.axis, atol=1e-12)
            np.testing.assert_allclose(np.cross(a - r.point, r.axis), 0.0, atol=1e-12)
            assert not entity.arrows
        else:
            p = model.prismatic  # type: ignore[attr-defined]
            (arrow,) = entity.arrows
            np.testing.assert_allclose(_xyz(arrow.pose.position),
                                       model.reference_pose[:3, 3], atol=1e-12)  # type: ignore[attr-defined]
            np.testing.assert_allclose(_rotation(arrow.pose.orientation)[:, 0], p.axis, atol=1e-12)
            g = geo.joint_geometry(model)  # type: ignore[arg-type]
            assert g is not None and len(entity.lines) == len(g.cone) + 1  # cone + stroke

    (stamp, image), *_ = channels[f"{ROOT}/camera/image"]
    frame = by_stamp[KEYS.camera_rgbd, stamp]
    assert image.encoding == "bgr8" and image.data == frame.color.data  # type: ignore[attr-defined]
    (_, calibration), *_ = channels[f"{ROOT}/camera/calibration"]
    assert calibration.K[0] == frame.intrinsics.fx  # type: ignore[attr-defined]
    ee = [tf for _, tf in channels[f"{ROOT}/tf"] if tf.child_frame_id == "ee"]
    assert len(ee) == 1


def test_export_adds_foxglove_channels_and_keeps_the_raw_ones(procs: Processes,
                                                              tmp_path: Path) -> None:
    messages = _source_messages()
    source, exported = tmp_path / "source.mcap", tmp_path / "foxglove.mcap"
    write_recording(source, ((k, m.to_msgpack(), m.stamp_ns + 1000) for k, m in messages))
    result = procs.run("export", str(source), str(exported))
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"exported {len(messages)} messages" in result.stdout
    assert ([(m.key, m.payload, m.log_time_ns) for m in read_recording(exported)]
            == [(m.key, m.payload, m.log_time_ns) for m in read_recording(source)])
    _check_foxglove_channels(exported, messages)


def test_export_skips_payloads_that_do_not_decode(procs: Processes, tmp_path: Path) -> None:
    source, exported = tmp_path / "bad.mcap", tmp_path / "out.mcap"
    good = samples.hand_landmarks()
    write_recording(source, [(KEYS.hand_landmarks, b"\xc1 not msgpack", 1),
                             (KEYS.hand_landmarks, good.to_msgpack(), 2)])
    result = procs.run("export", str(source), str(exported))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "did not decode: {'bad_msgpack': 1}" in result.stdout
    assert len(_decoded(exported)[f"{ROOT}/hand/landmarks"]) == 1


def test_record_foxglove_writes_the_channels_live(procs: Processes, router: str,
                                                  tmp_path: Path) -> None:
    messages = _source_messages()
    source, out = tmp_path / "source.mcap", tmp_path / "live.mcap"
    write_recording(source, ((k, m.to_msgpack(), m.stamp_ns) for k, m in messages))
    z = [*zenoh_args(router), "--rig", KEYS.rig]
    rec = procs.start("record", str(out), "--foxglove", "--count", str(len(messages)), *z,
                      name="record")
    wait_until(lambda: "recording" in output_of(rec) or rec.poll() is not None, 30,
               what="recorder ready")
    # Real time (a frame per 33 ms), as a camera sends: camera frames are published with
    # CongestionControl.DROP (docs/deployment.md#congestion-control), and six back to back as
    # fast as possible may lose one on a loaded machine (seen once in 20 runs).
    play = procs.run("replay", str(source), "--rate", "1", "--all-topics", "--keep-stamps",
                     "--wait-for", "recorder", *z)
    assert play.returncode == 0, play.stdout + play.stderr
    assert rec.wait(30) == 0, output_of(rec)
    assert len(list(read_recording(out))) == len(messages)
    _check_foxglove_channels(out, messages)
