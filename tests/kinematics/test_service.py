"""The kinematics service: node tests on the in-memory bus, then the process over a real router.

The node tests drive a ``KinematicsNode`` through the fake bus and check only what the node
shows on the wire: the KinematicModel messages it publishes, its ``get`` answer, its ``stats``
and its ``reset`` answer.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.common.bus import Bus, QueryRequest
from services.common.keys import Keys
from services.common.protocol import Ack, HandBody, KinematicModel, LandmarkStates
from services.common.se3 import se3_exp, skew
from services.common.service import Service
from services.common.state_file import StateFile, read_state
from services.kinematics.config import KinematicsConfig
from services.kinematics.service import SNAPSHOT_VERSION as STATE_VERSION
from services.kinematics.service import KinematicsNode
from services.synthetic.generator import generate
from services.synthetic.replay import landmark_messages
from services.tracker.config import TrackerConfig
from services.tracker.service import TrackerNode
from tests.common.documents import with_field
from tests.common.fake_bus import FakeBus
from tests.common.service_harness import ServiceHarness, drain
from tests.conftest import Processes, output_of, wait_routed, wait_until, zenoh_args

KEYS = Keys("kin")
AXIS = np.array([0.0, 0.6, 0.8])
POINT = np.array([0.1, 0.0, 0.0])  # on the axis; the closest point to the origin


def revolute_bodies(n: int, start: int = 0) -> list[HandBody]:
    """Exact hand poses of a revolute motion, 30 Hz, grasp 10 cm from the axis."""
    T0 = np.eye(4)
    T0[:3, 3] = POINT + 0.1 * np.cross(AXIS, [1.0, 0.0, 0.0]) / np.linalg.norm(
        np.cross(AXIS, [1.0, 0.0, 0.0])) + np.array([0.0, 0.0, 0.6])
    screw = np.concatenate([-skew(AXIS) @ POINT, AXIS])
    bodies = []
    for i in range(start, start + n):
        q = 1.2 * i / 120
        bodies.append(HandBody(
            seq=i, stamp_ns=1_000_000_000 + i * 33_333_333, initialized=True,
            pose=se3_exp(q * screw) @ T0, twist=np.zeros(6),
            covariance=np.eye(12) * 1e-8, motion_model="constant_velocity",
            landmarks=LandmarkStates(points=np.zeros((21, 3), "<f4"),
                                     variance=np.zeros(21, "<f4"), status=np.ones(21, "|u1"))))
    return bodies


def _assert_the_revolute_joint(model: KinematicModel) -> None:
    assert model.type == "revolute" and model.probabilities["revolute"] > 0.9
    assert model.revolute is not None
    assert min(np.linalg.norm(model.revolute.axis - AXIS),
               np.linalg.norm(model.revolute.axis + AXIS)) < 1e-3
    assert np.linalg.norm(model.revolute.point - POINT) < 1e-3


class FakeKinematics(ServiceHarness):
    """A kinematics node on the fake bus, with the models it publishes in :attr:`models`."""

    def __init__(self, bus: FakeBus | None = None, state_file: Path | None = None,
                 clock: Callable[[], int] = time.time_ns) -> None:
        super().__init__("kinematics", KEYS, bus)
        self.node = KinematicsNode(self.service, KinematicsConfig(), state_file, clock=clock)
        self.models = self.record(KEYS.kinematics_model, KinematicModel)

    def bodies(self, *bodies: HandBody | bytes) -> None:
        self.send(KEYS.hand_body, *bodies)

    def query(self, parameters: str = "") -> bytes:
        selector = KEYS.kinematics_model + (f"?{parameters}" if parameters else "")
        replies = self.bus.get(selector)
        assert [key for key, _ in replies] == [KEYS.kinematics_model]
        return replies[0][1]

    def model(self) -> KinematicModel:
        return KinematicModel.from_msgpack(self.query())


def _same_model(a: KinematicModel, b: KinematicModel) -> bool:
    """Same content (sequence numbers aside)."""
    return dataclasses.replace(a, seq=0).to_msgpack() == dataclasses.replace(b, seq=0).to_msgpack()


def test_the_model_answers_before_any_data() -> None:
    node = FakeKinematics()
    assert node.model().updates == 0
    as_json = json.loads(node.query("format=json"))
    assert as_json["updates"] == 0 and as_json["schema"] == "handkse.KinematicModel/1"
    assert node.models == []


def test_bodies_in_models_out_and_the_joint_is_found() -> None:
    node = FakeKinematics()
    bodies = revolute_bodies(120)
    node.bodies(*bodies)

    models = node.models
    assert [m.updates for m in models] == list(range(1, 121))  # one model per update
    assert [m.seq for m in models] == list(range(120))
    assert [m.stamp_ns for m in models] == [b.stamp_ns for b in bodies]
    _assert_the_revolute_joint(models[-1])
    assert node.query() == models[-1].to_msgpack()  # get answers the latest model
    as_json = json.loads(node.query("format=json"))
    assert as_json["updates"] == 120 and len(as_json["reference_pose"]) == 4
    assert as_json["type"] == "revolute"
    stats = node.stats()
    assert (stats.received, stats.published, stats.rejected) == (120, 120, {})
    assert "update" in stats.latency_ms


def test_bad_bodies_are_counted_and_not_published() -> None:
    node = FakeKinematics()
    bodies = revolute_bodies(12)
    skew_pose = bodies[10].pose.copy()
    skew_pose[:3, :3] *= 1.1  # not a rotation
    node.bodies(*bodies[:10])
    node.bodies(b"\x00garbage")
    node.bodies(dataclasses.replace(bodies[10], pose=skew_pose))
    node.bodies(bodies[9])  # again: a duplicate stamp
    assert len(node.models) == 10
    node.bodies(*bodies[10:])

    clean = FakeKinematics()
    clean.bodies(*bodies)
    assert node.models[-1].updates == 12 and _same_model(node.models[-1], clean.models[-1])
    stats = node.stats()
    assert stats.received == 15 and stats.published == 12
    assert sum(stats.rejected.values()) == 3
    assert stats.rejected["bad_msgpack"] == 1 and stats.rejected["duplicate_stamp"] == 1


def test_each_rejected_body_is_counted_under_its_own_reason() -> None:
    node = FakeKinematics()
    bodies = revolute_bodies(10)
    node.bodies(*bodies, bodies[9], bodies[9], bodies[3])
    assert node.stats().rejected == {"duplicate_stamp": 2, "out_of_order": 1}


def test_a_body_without_a_pose_yet_is_ignored() -> None:
    node = FakeKinematics()
    waiting = dataclasses.replace(revolute_bodies(1)[0], initialized=False, pose=np.eye(4))
    node.bodies(waiting)
    stats = node.stats()
    assert (stats.received, stats.published, stats.rejected) == (1, 0, {})
    assert node.model().updates == 0


def test_a_frame_change_mid_demonstration_is_refused() -> None:
    """One body in "world" amid "camera" ones is refused and counted; the demonstration goes on as
    if it had not come (no update lost); a run of them is refused body by body."""
    node = FakeKinematics()
    bodies = revolute_bodies(60)
    node.bodies(*bodies[:30], dataclasses.replace(bodies[30], frame_id="world"), *bodies[31:50])
    clean = FakeKinematics()
    clean.bodies(*bodies[:30], *bodies[31:50])

    assert node.stats().rejected == {"frame_changed": 1}
    assert [m.frame_id for m in node.models] == ["camera"] * 49
    assert all(map(_same_model, node.models, clean.models))
    node.bodies(*(dataclasses.replace(b, frame_id="world") for b in bodies[50:]))
    assert node.stats().rejected == {"frame_changed": 11}
    assert len(node.models) == 49 and node.model().updates == 49


def test_a_new_demonstration_adopts_the_frame_of_its_first_body() -> None:
    node = FakeKinematics()
    bodies = revolute_bodies(40)
    node.bodies(*bodies[:30])
    assert node.reset().ok
    node.bodies(*(dataclasses.replace(b, frame_id="world") for b in bodies[30:]))
    assert node.stats().rejected == {}
    assert [(m.frame_id, m.updates) for m in node.models[30:]] == [("world", i) for i in range(1, 11)]
    assert node.model().frame_id == "world"


def test_a_body_stamped_far_ahead_cannot_freeze_the_model() -> None:
    """Stamp 2^63 - 1 (or an hour ahead of the stream) is refused as far_future and never becomes
    the latest stamp: every later real body is used."""
    bodies = revolute_bodies(120)
    node = FakeKinematics()
    node.bodies(*bodies[:50], dataclasses.replace(bodies[50], stamp_ns=2**63 - 1),
                dataclasses.replace(bodies[50], stamp_ns=bodies[50].stamp_ns + 3600 * 10**9),
                *bodies[50:])
    clean = FakeKinematics()
    clean.bodies(*bodies)
    assert node.stats().rejected == {"far_future": 2}
    assert len(node.models) == 120 and _same_model(node.models[-1], clean.models[-1])
    _assert_the_revolute_joint(node.model())


class FakeClock:
    """A receive clock the test moves: 30 Hz by default, from a wall clock in 2025."""

    def __init__(self) -> None:
        self.now = 1_750_000_000 * 10**9

    def __call__(self) -> int:
        self.now += 33_333_333
        return self.now


def test_a_tracking_gap_is_fine_a_jump_of_the_stream_only_after_a_second() -> None:
    """A gap of a minute in the stamps while the receive clock moved on too is a loss of tracking
    (used); a minute's jump while the clock did not move is refused as far_future until the
    stream has stayed there for stamps.resync_s (1 s), then it is the stream."""
    clock = FakeClock()
    node = FakeKinematics(clock=clock)
    bodies = revolute_bodies(120)
    node.bodies(*bodies[:40])
    clock.now += 60 * 10**9
    minute = 60 * 10**9
    node.bodies(*(dataclasses.replace(b, stamp_ns=b.stamp_ns + minute) for b in bodies[40:60]))
    assert node.stats().rejected == {} and node.model().updates == 60
    node.bodies(*(dataclasses.replace(b, stamp_ns=b.stamp_ns + 2 * minute) for b in bodies[60:]))
    far = node.stats().rejected["far_future"]
    assert 29 <= far <= 31  # 1 s of the stream at 30 Hz
    assert node.model().updates == 120 - far and node.model().stamp_ns == bodies[-1].stamp_ns + 2 * minute


@pytest.mark.parametrize("offset_m", [0.05, 1000.0])
def test_one_outlier_body_leaves_the_verdict_unchanged(offset_m: float) -> None:
    """An in-order body 5 cm or 1 km off a converged revolute joint is counted as an outlier and
    not used: the verdict stays "revolute, P = 1" and the estimate equals the clean run's."""
    bodies = revolute_bodies(130)
    node = FakeKinematics()
    node.bodies(*bodies[:100])
    assert node.model().probabilities["revolute"] == pytest.approx(1.0)
    bad = bodies[100].pose.copy()
    bad[:3, 3] += (offset_m, 0.0, 0.0)
    node.bodies(dataclasses.replace(bodies[100], pose=bad))
    assert node.stats().rejected == {"outlier": 1} and node.model().updates == 100
    node.bodies(*bodies[101:])
    clean = FakeKinematics()
    clean.bodies(*bodies[:100], *bodies[101:])
    assert _same_model(node.model(), clean.model())
    _assert_the_revolute_joint(node.model())
    assert node.model().probabilities["revolute"] == pytest.approx(1.0)


def test_reset_starts_a_new_demonstration() -> None:
    node = FakeKinematics()
    bodies = revolute_bodies(120)
    node.bodies(*bodies[:60])
    ack = node.reset()
    published_before = len(node.models)
    node.bodies(*bodies[60:90])

    fresh = FakeKinematics()
    fresh.bodies(*bodies[60:90])
    assert ack.ok, ack.message
    assert all(m.updates <= 30 for m in node.models[published_before:])
    assert node.model().updates == 30 and _same_model(node.model(), fresh.models[-1])


@pytest.mark.parametrize(("name", "joint"), [("valve", "revolute"), ("slider", "prismatic")])
def test_tracker_and_kinematics_nodes_on_one_bus_find_the_joint(name: str, joint: str) -> None:
    """The pipeline in one process: landmarks -> tracker node -> kinematics node -> back to the
    tracker, each service loop run in turn after every frame (as the services would)."""
    bus = FakeBus()
    tracker = ServiceHarness("tracker", KEYS, bus)
    TrackerNode(tracker.service, TrackerConfig())
    kinematics = FakeKinematics(bus)
    bodies = tracker.record(KEYS.hand_body, HandBody)
    frames = landmark_messages(generate(name, 3, 0))
    for frame in frames:
        tracker.send(KEYS.hand_landmarks, frame)
        drain(kinematics.service)
    drain(tracker.service)  # takes in the last model

    assert tracker.stats().received == len(frames) + len(kinematics.models)
    assert tracker.stats().rejected == {} and kinematics.stats().rejected == {}
    assert kinematics.stats().received == len(bodies)
    final = kinematics.model()
    assert final.type == joint and final.updates == sum(b.initialized for b in bodies)


# --- the service process over a real router ---


def _start(procs: Processes, router: str, state: Path, client: Bus):  # type: ignore[no-untyped-def]
    p = procs.start("kinematics", "--rig", KEYS.rig, "--state-file", str(state),
                    *zenoh_args(router), name="kinematics")
    wait_until(lambda: KEYS.alive("kinematics") in client.alive(KEYS.alive_all), 20,
               what=f"kinematics liveliness; log: {output_of(p)}")
    return p


def _kill(p: subprocess.Popen[bytes], client: Bus) -> None:
    """kill -9, then wait until its liveliness token is gone (else the next ``_start`` could take
    the dead process's token for the new one's)."""
    p.kill()
    p.wait(5)
    wait_until(lambda: KEYS.alive("kinematics") not in client.alive(KEYS.alive_all), 20,
               what="the killed process's token to vanish")


def _model(bus: Bus) -> KinematicModel:
    return KinematicModel.from_msgpack(bus.get(KEYS.kinematics_model)[0][1])


def _stats(bus: Bus) -> dict:  # type: ignore[type-arg]
    return dict(json.loads(bus.get(KEYS.stats("kinematics") + "?format=json")[0][1]))


def test_the_process_publishes_answers_and_resets(procs: Processes, router: str,
                                                  client_bus: Bus, tmp_path: Path) -> None:
    models: list[KinematicModel] = []
    client_bus.subscribe(KEYS.kinematics_model,
                         lambda k, p: models.append(KinematicModel.from_msgpack(p)))
    wait_routed(client_bus)  # before the service connects, so it learns the subscription
    kin = _start(procs, router, tmp_path / "kin.state", client_bus)
    assert _model(client_bus).updates == 0  # answers before any data

    bodies = revolute_bodies(120)
    for b in bodies[:60]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    client_bus.put(KEYS.hand_body, b"\x00garbage")
    wait_until(lambda: _stats(client_bus)["received"] == 61, 20, what="61 bodies received")
    wait_until(lambda: bool(models) and models[-1].updates == 60, 20, what="60 updates")

    node = FakeKinematics()  # the process publishes what the node does, message for message
    node.bodies(*bodies[:60], b"\x00garbage")
    assert len(models) == 60 and all(map(_same_model, models, node.models))
    assert [m.seq for m in models] == list(range(60))
    assert _same_model(_model(client_bus), models[-1])
    as_json = json.loads(client_bus.get(KEYS.kinematics_model + "?format=json")[0][1])
    assert as_json["updates"] == 60 and as_json["schema"] == "handkse.KinematicModel/1"
    stats = _stats(client_bus)
    assert stats["published"] == 60 and stats["rejected"] == {"bad_msgpack": 1}

    ack = Ack.from_msgpack(client_bus.get(KEYS.reset("kinematics"))[0][1])
    assert ack.ok, ack.message
    for b in bodies[60:65]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    wait_until(lambda: _model(client_bus).updates == 5, 20, what="5 updates after the reset")
    assert kin.poll() is None


def test_a_killed_process_continues_from_its_state_file(procs: Processes, router: str,
                                                        client_bus: Bus, tmp_path: Path) -> None:
    state = tmp_path / "kin.state"
    kin = _start(procs, router, state, client_bus)
    bodies = revolute_bodies(120)
    for b in bodies[:60]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    wait_until(lambda: _model(client_bus).updates == 60, 20, what="60 updates")
    # the writer thread saves off the update path: kill only once the file holds all 60
    wait_until(lambda: _saved_updates(state) == 60, 20, what="60 updates in the state file")

    # kill -9 mid-demonstration; the restarted service continues from the snapshot
    _kill(kin, client_bus)
    assert state.exists()
    _start(procs, router, state, client_bus)
    assert _model(client_bus).updates == 60
    for b in bodies[60:]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    wait_until(lambda: _model(client_bus).updates == 120, 20, what="120 updates")
    _assert_the_revolute_joint(_model(client_bus))
    stats = _stats(client_bus)
    assert stats["received"] == 60 and stats["published"] == 60

    ack = Ack.from_msgpack(client_bus.get(KEYS.reset("kinematics"))[0][1])
    assert ack.ok
    empty = _model(client_bus)
    assert (empty.updates, empty.stamp_ns, empty.type) == (0, 0, "unknown")
    # the reset published nothing (the Ack comes after the reset ran)
    after = json.loads(client_bus.get(KEYS.stats("kinematics") + "?format=json")[0][1])
    assert after["published"] == stats["published"]


def _node(bus: Bus) -> tuple[Service, KinematicsNode]:
    service = Service("kinematics", bus, Keys("kinnode"))
    return service, KinematicsNode(service, KinematicsConfig())


def _answer(node: KinematicsNode) -> KinematicModel:
    request = QueryRequest(key=node.service.keys.kinematics_model, parameters={}, payload=None)
    return KinematicModel.from_msgpack(node.answer_model(request).payload)


def test_reset_publishes_nothing_until_the_first_body(client_bus: Bus) -> None:
    """After a reset ``get`` answers the empty model (stamp 0, updates 0); the next model is
    published for the first body of the new demonstration, stamped with it (docs/protocol.md)."""
    service, node = _node(client_bus)
    bodies = revolute_bodies(30)
    for b in bodies[:10]:
        node.on_body(b)
    assert _answer(node).seq == 9
    node.reset()
    assert service.published == 10
    empty = _answer(node)
    assert (empty.updates, empty.stamp_ns, empty.type, empty.seq) == (0, 0, "unknown", 0)
    node.on_body(bodies[20])
    assert service.published == 11
    first = _answer(node)
    assert (first.updates, first.stamp_ns, first.seq) == (1, bodies[20].stamp_ns, 10)


# --- state files that do not hold a valid estimate ---


def _state_after(bodies: list[HandBody], path: Path) -> dict[str, Any]:
    """The state document a node writes after ``bodies``."""
    node = FakeKinematics(state_file=path)
    node.bodies(*bodies)
    assert node.node.state_file.flush()
    doc = StateFile(path, STATE_VERSION).load()
    assert doc is not None
    return doc




def test_a_state_file_written_after_a_far_stamp_restores_and_continues(tmp_path: Path) -> None:
    path = tmp_path / "kin.state"
    bodies = revolute_bodies(120)
    node = FakeKinematics(state_file=path)
    node.bodies(*bodies[:60], dataclasses.replace(bodies[60], stamp_ns=2**63 - 1))
    assert node.node.state_file.flush()
    assert node.stats().rejected == {"far_future": 1}

    restarted = FakeKinematics(state_file=path)
    assert restarted.model().updates == 60
    assert restarted.model().stamp_ns == bodies[59].stamp_ns  # not the poisoned stamp
    restarted.bodies(*bodies[60:])
    clean = FakeKinematics()
    clean.bodies(*bodies)
    assert restarted.stats().rejected == {}
    assert _same_model(restarted.model(), clean.model())


NAN_POSE = np.full((4, 4), np.nan)


@pytest.mark.parametrize(("path", "value", "message"), [
    ("estimator.open.estimator.updates", "many", "estimator.updates: expected an integer"),
    ("estimator.open.estimator.reference_pose", NAN_POSE,
     "estimator.reference_pose: contains NaN"),
    ("estimator.open.estimator.revolute.q", float("nan"),
     "estimator.revolute.q: nan is not finite"),
    ("estimator.frame_id", "mars", "estimator.frame_id: expected one of"),
    ("estimator.last_stamp_ns", 2**63 - 1, "estimator.last_stamp_ns: stamp 9223372036854775807"),
    ("estimator.open.estimator.selector", "history", "estimator.selector: expected a map"),
    ("estimator", [1, 2, 3], "estimator: expected a map"),
    ("stamps.anchor", [2**63 - 1, 2**63 - 1], "stamps.anchor"),
    ("stamps.anchor", "yesterday", "stamps.anchor"),
    ("stamps", ..., "expected the keys estimator and stamps"),
])
def test_a_state_file_with_a_bad_value_is_ignored_with_a_warning(
        tmp_path: Path, caplog: pytest.LogCaptureFixture, path: str, value: Any,
        message: str) -> None:
    """Wrong types, NaN, a bogus frame, a poisoned latest stamp: the service warns, naming the
    field, starts a new demonstration, and works."""
    state = tmp_path / "kin.state"
    bodies = revolute_bodies(90)
    StateFile(state, STATE_VERSION).save(with_field(_state_after(bodies[:60], state), path, value))
    with caplog.at_level(logging.WARNING, logger="services.kinematics.service"):
        node = FakeKinematics(state_file=state)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("ignoring the state file" in w and message in w for w in warnings), warnings
    assert node.model().updates == 0 and node.model().stamp_ns == 0
    node.bodies(*bodies[60:])
    assert node.stats().rejected == {} and node.model().updates == 30
    assert node.model().frame_id == "camera" and np.isfinite(node.model().reference_pose).all()


def test_a_state_file_of_an_older_version_is_ignored(tmp_path: Path,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    state = tmp_path / "kin.state"
    doc = _state_after(revolute_bodies(30), state)
    StateFile(state, 2).save(doc)  # the version before contact phases were kept
    with caplog.at_level(logging.WARNING):
        node = FakeKinematics(state_file=state)
    assert "version 2, expected 3" in caplog.text
    assert node.model().updates == 0


def _saved_updates(path: Path) -> int | None:
    """The updates of the open contact phase's estimate in the state file (the revolute bodies
    carry no landmarks: one phase, open from the first body)."""
    doc = read_state(path, STATE_VERSION)  # not a StateFile: it would remove the writer's .tmp
    if doc is None or doc["estimator"]["open"] is None:
        return None
    return int(doc["estimator"]["open"]["estimator"]["updates"])


def test_a_far_stamp_is_not_carried_across_a_restart(procs: Processes, router: str,
                                                     client_bus: Bus, tmp_path: Path) -> None:
    """The process refuses a body stamped 2^63 - 1; killed and restarted from its state file, it
    continues with the real stream."""
    state = tmp_path / "kin.state"
    kin = _start(procs, router, state, client_bus)
    bodies = revolute_bodies(90)
    for b in bodies[:30]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    client_bus.put(KEYS.hand_body, dataclasses.replace(bodies[30], stamp_ns=2**63 - 1).to_msgpack())
    wait_until(lambda: _stats(client_bus)["received"] == 31, 20, what="31 bodies received")
    # "received" counts on arrival, the refusal is counted once the loop has handled the body
    wait_until(lambda: _stats(client_bus)["rejected"] != {}, 20, what="the far body handled")
    assert _stats(client_bus)["rejected"] == {"far_future": 1}
    wait_until(lambda: _model(client_bus).updates == 30, 20, what="30 updates")
    # the writer thread saves off the update path: kill only once the file holds all 30
    wait_until(lambda: _saved_updates(state) == 30, 20, what="30 updates in the state file")

    _kill(kin, client_bus)
    _start(procs, router, state, client_bus)
    restored = _model(client_bus)
    assert (restored.updates, restored.stamp_ns) == (30, bodies[29].stamp_ns)
    for b in bodies[30:]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    wait_until(lambda: _model(client_bus).updates == 90, 20, what="90 updates")
    assert _stats(client_bus)["rejected"] == {}
    _assert_the_revolute_joint(_model(client_bus))


def test_a_corrupt_state_file_does_not_stop_the_process(procs: Processes, router: str,
                                                        client_bus: Bus, tmp_path: Path) -> None:
    """A state file whose fields have the wrong type: the process warns, starts fresh, works."""
    state = tmp_path / "kin.state"
    doc = _state_after(revolute_bodies(30), state)
    StateFile(state, STATE_VERSION).save(with_field(with_field(doc, "estimator.open.estimator.updates",
                                                     "many"),
                                               "estimator.open.estimator.revolute", "not a filter"))
    kin = _start(procs, router, state, client_bus)
    assert kin.poll() is None
    assert "ignoring the state file" in output_of(kin)
    assert "estimator.updates: expected an integer" in output_of(kin)
    assert _model(client_bus).updates == 0
    for b in revolute_bodies(10):
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    wait_until(lambda: _model(client_bus).updates == 10, 20, what="10 updates")
    assert kin.poll() is None
