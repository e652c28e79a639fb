"""The Rerun entity layout (services/view/rerun_scene.py), in process, into an ``.rrd`` file."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from services.common.keys import Keys
from services.common.protocol import Message
from tests.common import samples

rr = pytest.importorskip("rerun", reason="handkse view needs the 'view' extra (rerun-sdk)")

from services.view import rerun_scene as scene  # noqa: E402 - after the skip
from tests.view.rrd import at, read_entities  # noqa: E402

KEYS = Keys("scene")


def _log(path: Path, messages: list[tuple[str, bytes]],
         options: scene.SceneOptions | None = None) -> scene.RerunScene:
    rec = rr.RecordingStream("handkse-test")
    rec.set_sinks(rr.FileSink(str(path)))
    s = scene.RerunScene(rec, options)
    for key, payload in messages:
        s.handle(key, payload)
    rec.flush(timeout_sec=10.0)
    rec.disconnect()
    return s


def _payloads(*items: tuple[str, Message]) -> list[tuple[str, bytes]]:
    return [(k, m.to_msgpack()) for k, m in items]


def test_camera_image_pinhole_and_projected_landmarks(tmp_path: Path) -> None:
    frame = dataclasses.replace(samples.rgbd_frame(), stamp_ns=10, T_world_camera=None)
    hand = dataclasses.replace(samples.hand_landmarks().hands[0], pixels=None)
    landmarks = dataclasses.replace(samples.hand_landmarks(), stamp_ns=10, hands=(hand,))
    _log(tmp_path / "a.rrd", _payloads((KEYS.camera_rgbd, frame), (KEYS.hand_landmarks, landmarks)))
    entities = read_entities(tmp_path / "a.rrd")
    k = frame.intrinsics
    image = entities[f"/{scene.IMAGE}"]
    assert at(image, 10, "Pinhole:resolution") == [[k.width, k.height]]
    assert at(image, 10, "Image:buffer") is not None
    pixels = np.array(at(entities[f"/{scene.IMAGE_LANDMARKS}"], 10, "Points2D:positions"))
    p = hand.points[np.isfinite(hand.points).all(axis=1)].astype(float)
    in_front = p[:, 2] > 0
    np.testing.assert_allclose(pixels[:, 0], k.fx * p[in_front, 0] / p[in_front, 2] + k.cx,
                               rtol=1e-5)


def test_robot_pose_force_and_limit(tmp_path: Path) -> None:
    state = dataclasses.replace(samples.robot_state(), stamp_ns=77)
    _log(tmp_path / "r.rrd", _payloads((KEYS.robot_state, state)),
         scene.SceneOptions(force_limit_n=55.0))
    entities = read_entities(tmp_path / "r.rrd")
    translation = at(entities[f"/{scene.ROBOT_EE}"], 77, "Transform3D:translation")[0]
    np.testing.assert_allclose(translation, state.T_base_ee[:3, 3], atol=1e-6)
    assert state.T_base_target is not None
    target = at(entities[f"/{scene.ROBOT_TARGET}"], 77, "Transform3D:translation")[0]
    np.testing.assert_allclose(target, state.T_base_target[:3, 3], atol=1e-6)
    force = at(entities[f"/{scene.FORCE}"], 77, "Scalars:scalars")[0]
    assert force == pytest.approx(float(np.linalg.norm(state.wrench[:3])))
    assert at(entities[f"/{scene.FORCE_LIMIT}"], 77, "Scalars:scalars") == [55.0]


def test_bad_payloads_are_counted_and_noted_not_fatal(tmp_path: Path) -> None:
    body = samples.hand_body()
    s = _log(tmp_path / "b.rrd", [(KEYS.hand_body, b"\xc1garbage"),
                                  (KEYS.hand_body, samples.hand_landmarks().to_msgpack()),
                                  (KEYS.hand_body, body.to_msgpack()),
                                  (KEYS.root + "/robot/articulate", b"ignored")])
    assert s.counters.rejected == {"bad_msgpack": 1, "wrong_schema": 1}
    assert s.counters.logged == {"hand/body": 1}
    entities = read_entities(tmp_path / "b.rrd")
    texts = [r["TextLog:text"][0] for r in entities[f"/{scene.ERROR_LOG}"]]
    assert len(texts) == 2 and "not valid msgpack" in texts[0]
    assert f"/{scene.BODY}" in entities


def test_a_type_change_clears_the_previous_axis(tmp_path: Path) -> None:
    revolute = dataclasses.replace(samples.kinematic_model(), stamp_ns=1)
    prismatic = dataclasses.replace(samples.kinematic_model(), type="prismatic", stamp_ns=2)
    rigid = dataclasses.replace(samples.kinematic_model(), type="rigid", stamp_ns=3)
    _log(tmp_path / "m.rrd", _payloads((KEYS.kinematics_model, revolute),
                                       (KEYS.kinematics_model, prismatic),
                                       (KEYS.kinematics_model, rigid)))
    entities = read_entities(tmp_path / "m.rrd")
    axis = entities[f"/{scene.AXIS}"]
    assert at(axis, 1, "LineStrips3D:strips") is not None
    assert at(axis, 2, "Clear:is_recursive") == [False]
    assert at(entities[f"/{scene.ARROW}"], 2, "Arrows3D:vectors") is not None
    assert at(entities[f"/{scene.ARROW}"], 3, "Clear:is_recursive") == [False]
    texts = [r["TextLog:text"][0] for r in entities[f"/{scene.MODEL_LOG}"]]
    assert [t.split()[1] for t in texts] == ["revolute", "prismatic", "rigid"]
