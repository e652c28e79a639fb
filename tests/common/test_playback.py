"""What ``handkse replay`` publishes: source topics by default, rig remap, wall-clock stamps,
loops with resets, standing by for a live camera; in process and over a real router."""

from __future__ import annotations

import dataclasses
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from services.common.bus import QueryAnswer, QueryRequest
from services.common.errors import UserError
from services.common.keys import Keys
from services.common.playback import (
    SOURCE_TOPICS,
    PlaybackOptions,
    play,
    restamped,
    select_topics,
    target_rig,
    topic_of,
    wall_clock_offset,
)
from services.common.protocol import Ack, HandLandmarks, peek_envelope, restamp
from services.common.recording import RecordedMessage, read_recording, write_recording
from services.synthetic.generator import generate
from services.synthetic.replay import demonstration_recording
from tests.common import samples
from tests.common.fake_bus import FakeBus, FakeNetwork
from tests.conftest import Processes, output_of, wait_until, zenoh_args

T0 = 1_000_000_000_000


def _session(rig: str = "rec", n: int = 12) -> list[tuple[str, bytes, int]]:
    """A recorded session: frames, landmarks, bodies and models, interleaved, 33 ms apart;
    every message carries the stamp of its frame, the log time comes 5 ms later."""
    keys = Keys(rig)
    out = []
    for i in range(n):
        stamp = T0 + i * 33_000_000
        frame = dataclasses.replace(samples.rgbd_frame(i), seq=i, stamp_ns=stamp)
        lm = dataclasses.replace(samples.hand_landmarks(i), seq=i, stamp_ns=stamp)
        body = dataclasses.replace(samples.hand_body(i), seq=i, stamp_ns=stamp)
        model = dataclasses.replace(samples.kinematic_model(i), seq=i, stamp_ns=stamp)
        out += [(keys.camera_rgbd, frame.to_msgpack(), stamp + 5_000_000),
                (keys.hand_landmarks, lm.to_msgpack(), stamp + 6_000_000),
                (keys.hand_body, body.to_msgpack(), stamp + 7_000_000),
                (keys.kinematics_model, model.to_msgpack(), stamp + 8_000_000)]
    return out


def _recorded(msgs: list[tuple[str, bytes, int]], tmp_path: Path) -> list[RecordedMessage]:
    path = tmp_path / "session.mcap"
    write_recording(path, msgs)
    return list(read_recording(path))


def _stamp(payload: bytes) -> int:
    stamp = peek_envelope(payload)[1]
    assert stamp is not None
    return stamp


# --- restamping ---


def test_restamp_moves_the_envelope_stamp_and_nothing_else() -> None:
    for msg in samples.all_messages(3):
        moved = restamp(msg.to_msgpack(), 5_000)
        if msg.stamp_ns > 0:
            assert moved == dataclasses.replace(msg, stamp_ns=msg.stamp_ns + 5_000).to_msgpack()
        else:  # a placeholder stamp is no capture time: it stays 0
            assert moved == msg.to_msgpack()
    assert restamp(b"\xc1 not msgpack", 5) == b"\xc1 not msgpack"


def test_restamped_keeps_relative_timing_of_every_topic(tmp_path: Path) -> None:
    recorded = _recorded(_session(), tmp_path)
    offset = 123_456_789_000
    moved = list(restamped(recorded, offset))
    assert [m.key for m in moved] == [m.key for m in recorded]
    for old, new in zip(recorded, moved, strict=True):
        assert _stamp(new.payload) == _stamp(old.payload) + offset
        assert new.log_time_ns == old.log_time_ns + offset
        assert new.publish_time_ns == old.publish_time_ns + offset


def test_wall_clock_offset_stamps_never_run_ahead_of_publishing(tmp_path: Path) -> None:
    recorded = _recorded(_session(), tmp_path)
    now = 1_700_000_000_000_000_000
    first, last = recorded[0].publish_time_ns, recorded[-1].publish_time_ns
    t0 = recorded[0].log_time_ns
    # rate 1: the first message is stamped at its publish time, the lowest-latency one
    assert wall_clock_offset(recorded, 1.0, now) == now - first
    # as fast as possible: everything is published at `now`; the newest stamp is `now`
    assert wall_clock_offset(recorded, 0.0, now) + last == now
    for rate in (0.25, 1.0, 3.0):
        offset = wall_clock_offset(recorded, rate, now)
        ahead = [m.publish_time_ns + offset - (now + (m.log_time_ns - t0) / rate)
                 for m in recorded]
        assert max(ahead) == pytest.approx(0.0, abs=1.0)
    # a loop's next pass starts after the previous one ended
    assert wall_clock_offset(recorded, 0.0, now, not_before_ns=now + 10) == now + 10 - first


# --- selection and rigs ---


def test_default_topics_are_the_sources(tmp_path: Path) -> None:
    recorded = _recorded(_session(), tmp_path)
    chosen = select_topics(recorded, None, "session.mcap")
    assert {topic_of(m.key) for m in chosen} == set(SOURCE_TOPICS)
    assert len(chosen) == len(recorded) // 2
    bodies = select_topics(recorded, ("hand/body",), "session.mcap")
    assert {m.key for m in bodies} == {"handkse/rec/hand/body"}
    with pytest.raises(UserError, match=r"--topics: hand/bdy not in session.mcap; it has: "
                                        r"camera/rgbd, hand/landmarks, hand/body"):
        select_topics(recorded, ("hand/bdy",), "session.mcap")
    results = [m for m in recorded if topic_of(m.key) not in SOURCE_TOPICS]
    with pytest.raises(UserError, match=r"none of the source topics.*--all-topics"):
        select_topics(results, None, "results.mcap")


def test_rig_is_kept_or_remapped_never_merged(tmp_path: Path) -> None:
    recorded = _recorded(_session("a"), tmp_path)
    assert target_rig(recorded, None, "f") == ("a", None)
    assert target_rig(recorded, "a", "f") == ("a", None)
    assert target_rig(recorded, "b", "f") == ("b", "b")
    two = [*recorded, dataclasses.replace(recorded[0], key="handkse/c/camera/rgbd")]
    assert target_rig(two, None, "f") == ("default", None)
    with pytest.raises(UserError, match="holds the rigs a, c: --rig b would merge them"):
        target_rig(two, "b", "f")


# --- passes on the in-memory bus ---


def test_loop_resets_before_each_pass_and_stands_by_for_a_camera() -> None:
    """A camera token that appears mid-pass stops the pass and resets the services; once the
    camera is gone the pass starts over; the stamps of later passes only grow."""
    net = FakeNetwork()
    keys = Keys("syn")
    demo = generate("bolt", 3, 0)
    messages = demonstration_recording(demo, "syn")
    player_bus, observer, camera = FakeBus(net), FakeBus(net), FakeBus(net)
    resets: list[str] = []
    for service in ("tracker", "kinematics"):
        def answer(_q: QueryRequest, s: str = service) -> QueryAnswer:
            resets.append(s)
            return QueryAnswer(Ack(ok=True, message="reset").to_msgpack())

        observer.declare_queryable(keys.reset(service), answer)
    stamps: list[int] = []
    token: list[object] = []

    def on_landmarks(_key: str, payload: bytes) -> None:
        stamps.append(HandLandmarks.from_msgpack(payload).stamp_ns)
        if len(stamps) == 10:  # a live camera comes up during the first pass
            token.append(camera.declare_token(keys.alive("camera")))

    observer.subscribe(keys.hand_landmarks, on_landmarks)
    stop = threading.Event()
    options = PlaybackOptions(rate=0, loop=False, reset=("tracker", "kinematics"),
                              standby_while=("camera",))
    result: list[int] = []
    player = threading.Thread(target=lambda: result.append(
        play(player_bus, keys, messages, options, stop)), daemon=True)
    player.start()
    wait_until(lambda: len(resets) == 4, 10, what="the resets after the interruption")
    time.sleep(0.3)  # standing by: nothing is published while the camera is alive
    assert len(stamps) == 10
    token[0].undeclare()  # type: ignore[attr-defined]
    player.join(20)
    assert not player.is_alive()
    assert resets == ["tracker", "kinematics"] * 3
    assert result == [10 + len(demo)]
    second = np.array(stamps[10:])
    assert second[0] > stamps[9]  # the new pass starts after the interrupted one
    np.testing.assert_array_equal(np.diff(second), np.diff(demo.stamps_ns))


# --- over a real router, as separate processes ---


def _record(procs: Processes, router: str, rig: str, count: int, out: Path
            ) -> subprocess.Popen[bytes]:
    rec = procs.start("record", str(out), "--rig", rig, "--count", str(count),
                      *zenoh_args(router), name="record")
    wait_until(lambda: "recording" in output_of(rec), 20, what="recorder ready")
    return rec


def test_replay_publishes_only_sources_remapped_and_restamped(procs: Processes, router: str,
                                                              tmp_path: Path) -> None:
    msgs = _session("rec", n=12)
    source, out = tmp_path / "session.mcap", tmp_path / "out.mcap"
    write_recording(source, msgs)
    sources = [(k, p, t) for k, p, t in msgs if topic_of(k) in SOURCE_TOPICS]
    rec = _record(procs, router, "other", len(sources), out)
    before = time.time_ns()
    play_ = procs.run("replay", str(source), "--rig", "other", "--wait-for", "recorder",
                      *zenoh_args(router))
    after = time.time_ns()
    assert play_.returncode == 0, play_.stdout + play_.stderr
    assert f"replayed {len(sources)} messages" in play_.stdout
    rec.wait(20)
    back = list(read_recording(out))
    # a replayed hand/body or model would have taken the place of a source message
    assert Counter(m.key for m in back) == Counter(k.replace("/rec/", "/other/")
                                                  for k, _, _ in sources)
    offsets = set()
    for topic in SOURCE_TOPICS:
        have = sorted(_stamp(m.payload) for m in back if topic_of(m.key) == topic)
        want = sorted(_stamp(p) for k, p, _ in sources if topic_of(k) == topic)
        offsets |= {h - w for h, w in zip(have, want, strict=True)}
    assert len(offsets) == 1  # one offset for every message: relative timing kept exactly
    stamps = [_stamp(m.payload) for m in back]
    assert before <= min(stamps) and max(stamps) <= after  # on the wall clock, never ahead


def test_replay_synthetic_restamps_unless_told_to_keep(procs: Processes, router: str,
                                                        tmp_path: Path) -> None:
    demo = generate("bolt", 3, 0)
    for keep in (False, True):
        out = tmp_path / f"keep-{keep}.mcap"
        rec = _record(procs, router, "syn", len(demo), out)
        before = time.time_ns()
        play_ = procs.run("replay", "--synthetic", "bolt", "--rig", "syn", "--rate", "0",
                          "--wait-for", "recorder", *(["--keep-stamps"] if keep else []),
                          *zenoh_args(router))
        after = time.time_ns()
        assert play_.returncode == 0, play_.stdout + play_.stderr
        rec.wait(20)
        stamps = np.array([HandLandmarks.from_msgpack(m.payload).stamp_ns
                           for m in read_recording(out)])
        if keep:
            np.testing.assert_array_equal(stamps, demo.stamps_ns)
        else:
            np.testing.assert_array_equal(np.diff(stamps), np.diff(demo.stamps_ns))
            assert before <= stamps[-1] <= after  # rate 0: the last is stamped when sent
