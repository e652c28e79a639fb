"""The tracker service over a real Zenoh router, as a separate process."""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np

from services.common.bus import Bus
from services.common.keys import Keys
from services.common.protocol import HandBody, KinematicModel
from services.common.se3 import se3_exp
from services.synthetic.generator import generate
from services.synthetic.replay import landmark_messages
from services.tracker.config import TrackerConfig
from services.tracker.service import observations
from services.tracker.tracker import HandTracker
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
    empty = dataclasses.replace(frames[-1], stamp_ns=frames[-1].stamp_ns + 1, hands=())
    client_bus.put(KEYS.hand_landmarks, empty.to_msgpack())  # valid, but no hand: skipped

    stamps = {f.stamp_ns for f in frames}
    assert all(b.stamp_ns in stamps for b in bodies)  # stamps carried through unchanged
    assert [b.seq for b in bodies] == list(range(len(bodies)))
    assert sum(b.initialized for b in bodies) > 40
    last = bodies[-1]
    assert last.frame_id == "camera" and np.isfinite(last.pose).all()
    assert set(np.unique(last.landmarks.status)) <= {0, 1, 2, 3}

    def stats_now() -> dict:  # type: ignore[type-arg]
        return dict(json.loads(client_bus.get(KEYS.stats("tracker") + "?format=json")[0][1]))

    wait_until(lambda: stats_now()["received"] == len(frames) + 4, 10, what="all received")
    stats = stats_now()
    assert stats["skipped"] == {"no_hand": 1}
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


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    R = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip(0.5 * (np.trace(R) - 1.0), -1.0, 1.0))))


def test_a_restarted_tracker_continues_its_body_frame(procs: Processes, router: str,
                                                      client_bus: Bus, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """kill -9 mid-demonstration, restart with the same state file: the new body is re-acquired
    in the old body frame, so its poses match an uninterrupted run's (the key turns ~70 deg
    meanwhile, so a fresh centroid frame does not); without the state file they do not."""
    demo = generate("key", 3, 0)
    truth = {int(s): T for s, T in zip(demo.stamps_ns, demo.truth.T_camera_hand, strict=True)}
    frames = landmark_messages(demo)
    bodies: list[HandBody] = []
    client_bus.subscribe(KEYS.hand_body, lambda k, p: bodies.append(HandBody.from_msgpack(p)))
    uninterrupted = HandTracker(TrackerConfig())
    reference = {}
    for msg in frames:
        est = uninterrupted.step(msg.stamp_ns, observations(msg)).estimate
        if est is not None and est.initialized:
            reference[msg.stamp_ns] = est.pose

    def run_tracker(part: list, state: str | None) -> dict[int, np.ndarray]:  # type: ignore[type-arg]
        extra = ["--state-file", state] if state else []
        p = procs.start("tracker", "--rig", KEYS.rig, *zenoh_args(router), *extra,
                        name="tracker")
        wait_until(lambda: KEYS.alive("tracker") in client_bus.alive(KEYS.alive_all), 20,
                   what=f"tracker liveliness; log: {output_of(p)}")
        bodies.clear()
        for msg in part:
            client_bus.put(KEYS.hand_landmarks, msg.to_msgpack())
            time.sleep(0.002)
        wait_until(lambda: bool(bodies) and bodies[-1].stamp_ns == part[-1].stamp_ns, 20,
                   what="hand body of the last frame")
        p.kill()
        p.wait(10)
        wait_until(lambda: KEYS.alive("tracker") not in client_bus.alive(KEYS.alive_all), 20,
                   what="tracker gone")
        return {b.stamp_ns: b.pose for b in bodies if b.initialized}

    def offset_deg(poses: dict[int, np.ndarray]) -> float:
        """Median rotation between these poses' body frame and the uninterrupted run's."""
        return float(np.median([_angle_deg(np.linalg.inv(truth[s]) @ T,
                                           np.linalg.inv(truth[s]) @ reference[s])
                                for s, T in poses.items()]))

    state = str(tmp_path / "tracker.state")
    first = run_tracker(frames[:60], state)
    resumed = run_tracker(frames[60:], state)
    fresh = run_tracker(frames[60:], None)
    assert len(first) > 40 and len(resumed) > 80 and len(fresh) > 80
    print(f"body frame vs the uninterrupted run: before the kill {offset_deg(first):.1f} deg, "
          f"resumed {offset_deg(resumed):.1f} deg, fresh {offset_deg(fresh):.1f} deg")
    assert offset_deg(first) < 1.0  # the same tracker on the same frames
    assert offset_deg(resumed) < 10.0
    assert offset_deg(fresh) > 5.0 * offset_deg(resumed)


def test_world_landmarks_with_a_camera_pose_are_tracked_in_the_world_frame() -> None:
    """A moving camera: the detector publishes world points with ``T_world_camera``; the tracker
    gets camera-frame points back plus the pose, so its depth noise follows the real viewing
    rays, and tracks (and publishes) in "world"."""
    demo = generate("key", 3, 0)
    frames = landmark_messages(demo)[:30]
    T_wc = se3_exp(np.array([0.3, -0.2, 1.0, 0.2, 0.5, -0.1]))
    tracker = HandTracker(TrackerConfig())
    for msg in frames:
        moved = dataclasses.replace(msg, frame_id="world", T_world_camera=T_wc, hands=tuple(
            dataclasses.replace(h, points=(h.points @ T_wc[:3, :3].T + T_wc[:3, 3]).astype("<f4"))
            for h in msg.hands))
        back = observations(moved)
        np.testing.assert_allclose(back[0].points, msg.hands[0].points, atol=1e-5,
                                   equal_nan=True)
        est = tracker.step(moved.stamp_ns, back, T_world_camera=moved.T_world_camera).estimate
    assert est is not None and est.initialized and est.frame_id == "world"
    static = observations(dataclasses.replace(frames[0], T_world_camera=T_wc))  # camera frame
    np.testing.assert_array_equal(static[0].points, frames[0].hands[0].points.astype(float))
