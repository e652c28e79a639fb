"""Synthetic demonstrations as bus traffic: ``handkse replay --synthetic`` and MCAP files."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from services.common.protocol import HandLandmarks
from services.common.recording import read_recording
from services.synthetic.generator import generate
from services.synthetic.replay import landmark_messages
from tests.conftest import Processes


def test_messages_carry_the_stream_exactly() -> None:
    demo = generate("bolt", 3, 0)
    msgs = landmark_messages(demo)
    assert [m.stamp_ns for m in msgs] == demo.stamps_ns.tolist()
    for i in (0, len(msgs) // 2, len(msgs) - 1):
        back = HandLandmarks.from_msgpack(msgs[i].to_msgpack())
        np.testing.assert_array_equal(back.hands[0].points, demo.points[i])
        np.testing.assert_array_equal(back.hands[0].visibility, demo.visibility[i])


def test_save_as_mcap(procs: Processes, tmp_path: Path) -> None:
    """``--save`` writes what a replay would publish: re-stamped to now by default."""
    demo = generate("key", 2, 0)
    for keep in (True, False):
        out = tmp_path / f"key-{keep}.mcap"
        before = time.time_ns()
        result = procs.run("replay", "--synthetic", "key", "--participant", "2", "--save",
                           str(out), "--rig", "lab", *(["--keep-stamps"] if keep else []))
        after = time.time_ns()
        assert result.returncode == 0, result.stderr
        recorded = list(read_recording(out))
        assert len(recorded) == len(demo)
        assert {r.key for r in recorded} == {"handkse/lab/hand/landmarks"}
        assert recorded[0].schema == "handkse.HandLandmarks/1"
        stamps = np.array([HandLandmarks.from_msgpack(r.payload).stamp_ns for r in recorded])
        assert [r.publish_time_ns for r in recorded] == stamps.tolist()
        assert [r.log_time_ns for r in recorded] == stamps.tolist()
        if keep:
            assert stamps.tolist() == demo.stamps_ns.tolist()
        else:
            assert before <= stamps[0] <= after
            np.testing.assert_array_equal(np.diff(stamps), np.diff(demo.stamps_ns))


def test_messages_carry_both_hands_and_empty_frames() -> None:
    demo = generate("slide_latch", 6, 2, variant="whole", gap="dropout", idle_hand="same")
    msgs = landmark_messages(demo)
    assert [m.stamp_ns for m in msgs] == demo.stamps_ns.tolist()
    assert demo.present is not None and demo.second is not None
    for i in (0, int(np.flatnonzero(~demo.present)[0]), len(msgs) - 1):
        back = HandLandmarks.from_msgpack(msgs[i].to_msgpack())
        want = demo.detections(i)
        assert [h.handedness for h in back.hands] == [h.handedness for h in want]
        assert len(back.hands) == int(demo.present[i]) + 1
        for got, exp in zip(back.hands, want, strict=True):
            np.testing.assert_array_equal(got.points, exp.points)
            assert got.score == float(exp.score)
    # Both hands report the same label here ("same"), scores decide the order.
    two = [HandLandmarks.from_msgpack(m.to_msgpack()) for m in msgs if len(m.hands) == 2]
    assert two and all(m.hands[0].score >= m.hands[1].score for m in two)
    alone = generate("slide_latch", 6, 2, variant="whole", gap="dropout")
    empty = [m for m in landmark_messages(alone) if not m.hands]
    assert len(empty) == int((~alone.present).sum()) > 0
