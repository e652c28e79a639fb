"""The kinematics service over a real Zenoh router: as a separate process, and in-process (the
node's handlers called directly, on a real session) for what must be exact per message."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from services.common.bus import Bus, QueryRequest
from services.common.keys import Keys
from services.common.protocol import Ack, HandBody, KinematicModel, LandmarkStates
from services.common.se3 import se3_exp, skew
from services.common.service import Service
from services.kinematics.config import KinematicsConfig
from services.kinematics.service import KinematicsNode
from tests.conftest import Processes, output_of, wait_until, zenoh_args

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


def _start(procs: Processes, router: str, state: Path):  # type: ignore[no-untyped-def]
    p = procs.start("kinematics", "--rig", KEYS.rig, "--state-file", str(state),
                    *zenoh_args(router), name="kinematics")
    wait_until(lambda: "kinematics ready" in output_of(p), 20, what="kinematics start")
    return p


def _model(bus: Bus) -> KinematicModel:
    return KinematicModel.from_msgpack(bus.get(KEYS.kinematics_model)[0][1])


def test_model_published_queried_reset_and_restored(procs: Processes, router: str,
                                                    client_bus: Bus, tmp_path: Path) -> None:
    state = tmp_path / "kin.state"
    kin = _start(procs, router, state)
    wait_until(lambda: KEYS.alive("kinematics") in client_bus.alive(KEYS.alive_all), 20,
               what="kinematics liveliness")
    models: list[KinematicModel] = []
    client_bus.subscribe(KEYS.kinematics_model,
                         lambda k, p: models.append(KinematicModel.from_msgpack(p)))
    time.sleep(0.2)
    assert _model(client_bus).updates == 0  # answers before any data

    bodies = revolute_bodies(120)
    for b in bodies[:60]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    client_bus.put(KEYS.hand_body, b"\x00garbage")
    wait_until(lambda: len(models) >= 60 and models[-1].updates == 60, 20, what="60 updates")
    assert [m.seq for m in models] == sorted(m.seq for m in models)

    queried = _model(client_bus)
    assert queried.updates == 60
    as_json = json.loads(client_bus.get(KEYS.kinematics_model + "?format=json")[0][1])
    assert as_json["updates"] == 60 and as_json["schema"] == "handkse.KinematicModel/1"
    assert len(as_json["reference_pose"]) == 4

    # kill -9 mid-demonstration; the restarted service continues from the snapshot
    kin.kill()
    kin.wait(5)
    assert state.exists()
    _start(procs, router, state)
    wait_until(lambda: KEYS.alive("kinematics") in client_bus.alive(KEYS.alive_all), 20,
               what="restarted kinematics")
    assert _model(client_bus).updates == 60
    for b in bodies[60:]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    wait_until(lambda: _model(client_bus).updates == 120, 20, what="120 updates")
    final = _model(client_bus)
    assert final.type == "revolute" and final.probabilities["revolute"] > 0.9
    assert final.revolute is not None
    assert min(np.linalg.norm(final.revolute.axis - AXIS),
               np.linalg.norm(final.revolute.axis + AXIS)) < 1e-3
    assert np.linalg.norm(final.revolute.point - POINT) < 1e-3

    stats = json.loads(client_bus.get(KEYS.stats("kinematics") + "?format=json")[0][1])
    assert stats["received"] == 60 and stats["published"] >= 60

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


def test_each_rejected_body_is_counted_under_its_own_reason(client_bus: Bus) -> None:
    """Regression: the reason counted for a rejected body was once the most frequent reason so
    far, so an out-of-order body after five duplicates was counted as a sixth duplicate."""
    service, node = _node(client_bus)
    bodies = revolute_bodies(10)
    for b in bodies:
        node.on_body(b)
    for _ in range(5):
        node.on_body(bodies[-1])
    node.on_body(bodies[3])
    assert service.rejected == {"duplicate_stamp": 5, "out_of_order": 1}
    assert service.published == 10 and _answer(node).updates == 10


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
