"""The tracker's state file read back (issue 13, finding 8): a document that does not hold a valid
hand body model is ignored with a warning naming the fault, and the tracker starts fresh, in the
node on the fake bus and in a real ``handkse tracker --state-file`` process."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.common.bus import Bus
from services.common.keys import Keys
from services.common.protocol import HandBody, HandLandmarks
from services.common.service import Service
from services.common.snapshot import SnapshotError
from services.common.state_file import StateFile
from services.synthetic.generator import generate
from services.synthetic.replay import landmark_messages
from services.tracker.config import TrackerConfig
from services.tracker.service import SNAPSHOT_VERSION, TrackerNode
from services.tracker.state import (
    RememberedBody,
    body_document,
    body_from_document,
    epoch_from_document,
)
from tests.common.documents import with_field
from tests.common.service_harness import ServiceHarness
from tests.conftest import Processes, output_of, wait_routed, wait_until, zenoh_args

KEYS = Keys("trkstate")


class StatefulTracker(ServiceHarness):
    """A tracker node on the fake bus with a state file; its bodies in :attr:`bodies`."""

    def __init__(self, state_file: Path | None) -> None:
        super().__init__("tracker", KEYS)
        self.node = TrackerNode(self.service, TrackerConfig(), state_file)
        self.bodies = self.record(KEYS.hand_body, HandBody)

    def landmarks(self, *messages: HandLandmarks) -> None:
        self.send(KEYS.hand_landmarks, *messages)


@pytest.fixture(scope="module")
def key_frames() -> list[HandLandmarks]:
    return landmark_messages(generate("key", 3, 0))


@pytest.fixture(scope="module")
def written(key_frames: list[HandLandmarks], tmp_path_factory: pytest.TempPathFactory
            ) -> dict[str, Any]:
    """The document a tracker writes after 60 frames of a demonstration."""
    path = tmp_path_factory.mktemp("written") / "tracker.state"
    node = StatefulTracker(path)
    node.landmarks(*key_frames[:60])
    assert node.node.state_file.flush()
    doc = StateFile(path, SNAPSHOT_VERSION).load()
    assert doc is not None and doc["body"] is not None
    return doc


def _same_bodies(a: list[HandBody], b: list[HandBody]) -> bool:
    return len(a) == len(b) and all(
        x.stamp_ns == y.stamp_ns and x.initialized == y.initialized
        and np.array_equal(x.pose, y.pose) and np.array_equal(x.covariance, y.covariance)
        for x, y in zip(a, b, strict=True))




def _points_with(doc: dict[str, Any], row: int, values: list[float]) -> np.ndarray:
    points = np.array(doc["body"]["points"], dtype=float)
    points[row] = values
    return points


Fault = tuple[str, Callable[[dict[str, Any]], dict[str, Any]], str]


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], dict[str, Any]]:
    return lambda doc: with_field(doc, path, value)


def _row(row: int, values: list[float]) -> Callable[[dict[str, Any]], dict[str, Any]]:
    return lambda doc: with_field(doc, "body.points", _points_with(doc, row, values))


# (id, the fault, what the warning names)
DOCUMENT_FAULTS: list[Fault] = [
    ("body-str", _set("body", "a body"), "tracker.body: expected a map, got str"),
    ("body-list", _set("body", [1, 2, 3]), "tracker.body: expected a map, got list"),
    ("frame-int", _set("body.frame_id", 5),
     "tracker.body.frame_id: expected one of ['camera', 'world'], got int"),
    ("frame-bogus", _set("body.frame_id", "mars"),
     "tracker.body.frame_id: expected one of ['camera', 'world'], got str"),
    ("frame-bytes", _set("body.frame_id", b"camera"), "tracker.body.frame_id: expected one of"),
    ("frame-missing", _set("body.frame_id", ...),
     "tracker.body: expected the keys ['frame_id', 'points'] (missing ['frame_id']"),
    ("unknown-stamp", _set("body.last_stamp_ns", 2**63 - 1), "unknown ['last_stamp_ns']"),
    ("points-str", _set("body.points", "many"), "tracker.body.points: expected an array, got str"),
    ("points-map", _set("body.points", {"a": 1}), "tracker.body.points: expected an array, got dict"),
    ("points-strings", _set("body.points", [["a", "b", "c"]] * 21),
     "tracker.body.points: not a numeric array"),
    ("points-bool", _set("body.points", np.zeros((21, 3), dtype=bool)),
     "tracker.body.points: expected a numeric array"),
    ("shape-20", _set("body.points", np.zeros((20, 3))),
     "tracker.body.points: expected shape (21, 3), got (20, 3)"),
    ("shape-3", _set("body.points", np.zeros(3)), "tracker.body.points: expected shape (21, 3), got (3,)"),
    ("inf", _row(2, [np.inf, 0.0, 0.0]), "tracker.body.points: contains NaN or infinity"),
    ("partly-nan", _row(2, [np.nan, 0.0, 0.0]), "tracker.body.points: rows [2] are partly NaN"),
    ("huge", _set("body.points", np.full((21, 3), 1e300)), "tracker.body.points: a coordinate of 1e+300 m"),
    ("far", _row(7, [0.0, 0.0, 2.5]), "tracker.body.points: a coordinate of 2.5 m"),
    ("epoch-negative", _set("body_epoch", -1), "tracker.body_epoch: -1 is not a whole number"),
    ("epoch-str", _set("body_epoch", "1"), "tracker.body_epoch: '1' is not a whole number"),
    ("epoch-bool", _set("body_epoch", True), "tracker.body_epoch: True is not a whole number"),
]
# a valid document that the tracker refuses: a model without enough landmarks to register
NODE_FAULTS: list[Fault] = [
    *DOCUMENT_FAULTS,
    ("no-landmarks", _set("body.points", np.full((21, 3), np.nan)),
     "tracker.body.points: fewer than min_inliers = 6 landmarks in the model"),
]


# --- the document ---


def test_what_the_tracker_writes_reads_back(written: dict[str, Any]) -> None:
    body = body_from_document(written)
    assert isinstance(body, RememberedBody) and body.frame_id == "camera"
    assert body.points.shape == (21, 3) and np.isfinite(body.points).all(axis=1).sum() >= 6
    assert body.body_epoch == 0 and written["body_epoch"] == 0
    again = body_from_document(body_document((body.frame_id, body.points), 3))
    assert again is not None and again.frame_id == body.frame_id and again.body_epoch == 3
    np.testing.assert_array_equal(again.points, body.points)
    assert body_from_document(body_document(None, 2)) is None
    assert epoch_from_document(body_document(None, 2)) == 2


def test_a_file_written_before_the_epoch_was_kept_still_restores_its_body(
        written: dict[str, Any]) -> None:
    old = {"body": written["body"]}
    body = body_from_document(old)
    assert body is not None and body.body_epoch is None and epoch_from_document(old) is None


def test_a_restarted_tracker_continues_the_body_epoch_it_had(key_frames: list[HandLandmarks],
                                                             tmp_path: Path) -> None:
    """After a ``reset`` the tracker's body frame is epoch 1; killed and restarted from its
    state file, it re-acquires that body frame and keeps publishing epoch 1 (epoch 0 would
    tell the kinematics service that the body frame is new, and it would start again)."""
    state = tmp_path / "tracker.state"
    first = StatefulTracker(state)
    first.landmarks(*key_frames[:40])
    first.node.reset()
    first.landmarks(*key_frames[40:90])
    assert first.bodies[-1].initialized and first.bodies[-1].body_epoch == 1
    assert first.node.state_file.flush()
    restarted = StatefulTracker(state)
    restarted.landmarks(*key_frames[95:140])
    assert restarted.node.tracker.reacquire_attempts >= 1
    epochs = {b.body_epoch for b in restarted.bodies if b.initialized}
    assert epochs == {1}


def test_a_tracker_restarted_after_a_reset_numbers_its_next_body_frame_on(
        key_frames: list[HandLandmarks], tmp_path: Path) -> None:
    state = tmp_path / "tracker.state"
    first = StatefulTracker(state)
    first.landmarks(*key_frames[:40])
    first.node.reset()  # the file now holds no body, and epoch 0 as the last one used
    restarted = StatefulTracker(state)
    restarted.landmarks(*key_frames[40:80])
    assert {b.body_epoch for b in restarted.bodies if b.initialized} == {1}


def test_a_landmark_outside_the_model_is_a_row_of_nan(written: dict[str, Any]) -> None:
    body = body_from_document(_row(4, [np.nan] * 3)(written))
    assert body is not None and np.isnan(body.points[4]).all()
    others = np.arange(21) != 4
    np.testing.assert_array_equal(body.points[others],
                                  np.asarray(written["body"]["points"])[others])


@pytest.mark.parametrize(("fault", "message"), [(f, m) for _, f, m in DOCUMENT_FAULTS],
                         ids=[i for i, _, _ in DOCUMENT_FAULTS])
def test_a_bad_document_names_its_fault(written: dict[str, Any],
                                        fault: Callable[[dict[str, Any]], dict[str, Any]],
                                        message: str) -> None:
    with pytest.raises(SnapshotError) as err:
        body_from_document(fault(written))
    assert message in str(err.value)


def test_a_document_with_other_keys_is_refused(written: dict[str, Any]) -> None:
    with pytest.raises(SnapshotError, match=r"tracker: .*unknown \['estimator'\]"):
        body_from_document({**written, "estimator": {}})
    with pytest.raises(SnapshotError, match=r"tracker: .*missing \['body'\]"):
        body_from_document({})


# --- the node: a warning naming the fault, then a fresh start ---


def _warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


@pytest.mark.parametrize(("fault", "message"), [(f, m) for _, f, m in NODE_FAULTS],
                         ids=[i for i, _, _ in NODE_FAULTS])
def test_a_bad_state_file_is_ignored_with_a_warning_and_the_tracker_starts_fresh(
        written: dict[str, Any], key_frames: list[HandLandmarks], tmp_path: Path,
        caplog: pytest.LogCaptureFixture, fault: Callable[[dict[str, Any]], dict[str, Any]],
        message: str) -> None:
    state = tmp_path / "tracker.state"
    StateFile(state, SNAPSHOT_VERSION).save(fault(written))
    with caplog.at_level(logging.WARNING, logger="services.tracker.service"):
        node = StatefulTracker(state)
    warnings = _warnings(caplog)
    assert any("ignoring the state file" in w and message in w for w in warnings), warnings
    node.landmarks(*key_frames[60:120])
    fresh = StatefulTracker(None)
    fresh.landmarks(*key_frames[60:120])
    assert node.node.tracker.reacquire_attempts == 0  # no remembered body to register
    assert _same_bodies(node.bodies, fresh.bodies)
    assert node.stats().rejected == {} and node.bodies[-1].initialized


@pytest.mark.parametrize(("content", "message"), [
    (b"\xc1\xc1 not msgpack", "ignoring unreadable state file"),
    (b"\x91" * 200_000 + b"\xc0", "ignoring unreadable state file"),  # nested 200,000 deep
    (b"", "ignoring unreadable state file"),
])
def test_an_unreadable_state_file_is_ignored(key_frames: list[HandLandmarks], tmp_path: Path,
                                             caplog: pytest.LogCaptureFixture, content: bytes,
                                             message: str) -> None:
    state = tmp_path / "tracker.state"
    state.write_bytes(content)
    with caplog.at_level(logging.WARNING):
        node = StatefulTracker(state)
    assert any(message in w or "ignoring the state file" in w for w in _warnings(caplog)), \
        _warnings(caplog)
    node.landmarks(*key_frames[:40])
    assert node.bodies[-1].initialized


def test_a_state_file_of_another_version_or_layout_is_ignored(
        written: dict[str, Any], tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    state = tmp_path / "tracker.state"
    StateFile(state, SNAPSHOT_VERSION + 1).save(written)
    with caplog.at_level(logging.WARNING):
        StatefulTracker(state)
    assert f"expected {SNAPSHOT_VERSION}" in caplog.text
    caplog.clear()
    StateFile(state, SNAPSHOT_VERSION).save({"body": None, "version_2_field": 1})
    with caplog.at_level(logging.WARNING):
        StatefulTracker(state)
    assert "unknown ['version_2_field']" in caplog.text


def test_a_valid_state_file_is_still_restored(written: dict[str, Any],
                                              key_frames: list[HandLandmarks], tmp_path: Path,
                                              caplog: pytest.LogCaptureFixture) -> None:
    state = tmp_path / "tracker.state"
    StateFile(state, SNAPSHOT_VERSION).save(written)
    with caplog.at_level(logging.INFO, logger="services.tracker.service"):
        node = StatefulTracker(state)
    assert "restored the hand body model" in caplog.text and not _warnings(caplog)
    node.landmarks(*key_frames[60:120])
    tracker = node.node.tracker
    assert tracker.reacquire_attempts >= 1 and tracker.reacquisitions >= 1


def test_a_restore_error_of_any_kind_does_not_stop_the_start(tmp_path: Path,
                                                             caplog: pytest.LogCaptureFixture,
                                                             monkeypatch: pytest.MonkeyPatch
                                                             ) -> None:
    """Whatever reading the file raises (here a RecursionError from the decoder), the node warns
    and starts."""
    state = tmp_path / "tracker.state"
    StateFile(state, SNAPSHOT_VERSION).save({"body": None})

    def deep(_payload: bytes) -> Any:
        raise RecursionError("maximum recursion depth exceeded")

    monkeypatch.setattr("services.common.state_file.unpack_document", deep)
    with caplog.at_level(logging.WARNING):
        node = StatefulTracker(state)
    assert "ignoring the state file" in caplog.text and "RecursionError" in caplog.text
    assert isinstance(node.service, Service)


# --- the process ---


def test_a_tracker_process_with_a_corrupt_state_file_starts_and_tracks(
        procs: Processes, router: str, client_bus: Bus, written: dict[str, Any],
        key_frames: list[HandLandmarks], tmp_path: Path) -> None:
    """Fields of the wrong type, NaN in the model and a bogus frame: the process warns (one
    line naming the fault, no traceback), starts fresh, and publishes what a fresh tracker
    does; its next snapshot replaces the file with a valid one."""
    state = tmp_path / "tracker.state"
    corrupt = with_field(_row(0, [np.nan, 1.0, 2.0])(written), "body.frame_id", 17)
    StateFile(state, SNAPSHOT_VERSION).save(corrupt)
    bodies: list[HandBody] = []
    client_bus.subscribe(KEYS.hand_body, lambda k, p: bodies.append(HandBody.from_msgpack(p)))
    wait_routed(client_bus)
    tracker = procs.start("tracker", "--rig", KEYS.rig, "--state-file", str(state),
                          *zenoh_args(router), name="tracker")
    wait_until(lambda: KEYS.alive("tracker") in client_bus.alive(KEYS.alive_all)
               or tracker.poll() is not None, 30, what="tracker liveliness")
    assert tracker.poll() is None, output_of(tracker)
    log = output_of(tracker)
    assert "ignoring the state file" in log and "tracker.body.frame_id: expected one of" in log, \
        log
    assert "Traceback" not in log

    frames = key_frames[:60]
    for msg in frames:
        client_bus.put(KEYS.hand_landmarks, msg.to_msgpack())
    wait_until(lambda: bool(bodies) and bodies[-1].stamp_ns == frames[-1].stamp_ns, 30,
               what=f"hand body of the last frame; log: {output_of(tracker)}")
    fresh = StatefulTracker(None)
    fresh.landmarks(*frames)
    assert _same_bodies(bodies, fresh.bodies)
    assert tracker.poll() is None
    tracker.terminate()
    tracker.wait(20)
    restored = body_from_document(StateFile(state, SNAPSHOT_VERSION).load())
    assert restored is not None and restored.frame_id == "camera"
