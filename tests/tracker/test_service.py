"""The tracker service over a real Zenoh router, as a separate process."""

from __future__ import annotations

import json
import time

import numpy as np

from services.common.bus import Bus
from services.common.keys import Keys
from services.common.protocol import HandBody, KinematicModel
from services.synthetic.generator import generate
from services.synthetic.replay import landmark_messages
from tests.conftest import Processes, output_of, wait_until, zenoh_args

KEYS = Keys("trk")


def test_landmarks_in_hand_body_out_bad_input_counted(procs: Processes, router: str,
                                                      client_bus: Bus) -> None:
    tracker = procs.start("tracker", "--rig", KEYS.rig, *zenoh_args(router), name="tracker")
    wait_until(lambda: KEYS.alive("tracker") in client_bus.alive(KEYS.alive_all), 20,
               what=f"tracker liveliness; log: {output_of(tracker)}")
    bodies: list[HandBody] = []
    client_bus.subscribe(KEYS.hand_body, lambda k, p: bodies.append(HandBody.from_msgpack(p)))
    time.sleep(0.2)

    frames = landmark_messages(generate("valve", 3, 0))[:60]
    for i, msg in enumerate(frames):
        client_bus.put(KEYS.hand_landmarks, msg.to_msgpack())
        if i == 20:  # bad input in the middle of the stream
            client_bus.put(KEYS.hand_landmarks, b"\x81\xa6schema\xc0")
            client_bus.put(KEYS.hand_landmarks, frames[0].to_msgpack())  # out of order
            client_bus.put(KEYS.kinematics_model, b"not a model")
    wait_until(lambda: bodies and bodies[-1].stamp_ns == frames[-1].stamp_ns, 20,
               what="hand body of the last frame")

    stamps = {f.stamp_ns for f in frames}
    assert all(b.stamp_ns in stamps for b in bodies)  # stamps carried through unchanged
    assert [b.seq for b in bodies] == list(range(len(bodies)))
    assert sum(b.initialized for b in bodies) > 40
    last = bodies[-1]
    assert last.frame_id == "camera" and np.isfinite(last.pose).all()
    assert set(np.unique(last.landmarks.status)) <= {0, 1, 2, 3}

    stats = json.loads(client_bus.get(KEYS.stats("tracker") + "?format=json")[0][1])
    assert stats["received"] == len(frames) + 3
    assert stats["rejected"].get("bad_field", 0) + stats["rejected"].get("wrong_schema", 0) >= 1
    assert stats["rejected"].get("bad_msgpack", 0) >= 1
    assert stats["rejected"].get("out_of_order_stamp", 0) == 1
    assert "step" in stats["latency_ms"]
    assert tracker.poll() is None


def test_model_from_kinematics_reaches_the_tracker(procs: Processes, router: str,
                                                   client_bus: Bus) -> None:
    """A published KinematicModel is accepted (not rejected) by the tracker."""
    tracker = procs.start("tracker", "--rig", KEYS.rig, *zenoh_args(router), name="tracker")
    wait_until(lambda: KEYS.alive("tracker") in client_bus.alive(KEYS.alive_all), 20,
               what=f"tracker liveliness; log: {output_of(tracker)}")
    model = KinematicModel(type="unknown", probabilities={"rigid": 0.25, "prismatic": 0.25,
                                                          "revolute": 0.25,
                                                          "disconnected": 0.25})
    client_bus.put(KEYS.kinematics_model, model.to_msgpack())

    def received() -> int:
        return int(json.loads(client_bus.get(KEYS.stats("tracker") + "?format=json")[0][1])
                   ["received"])

    wait_until(lambda: received() == 1, 10, what="model received")
    stats = json.loads(client_bus.get(KEYS.stats("tracker") + "?format=json")[0][1])
    assert stats["rejected"] == {}
