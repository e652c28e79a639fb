"""The tracker service: node tests on the in-memory bus, then the process over a real router.

The node tests drive a ``TrackerNode`` through the fake bus and check only what the node shows on
the wire: the HandBody messages it publishes, its ``stats`` and its ``reset`` answer.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from services.common.bus import Bus
from services.common.keys import Keys
from services.common.protocol import HandBody, HandLandmarks, KinematicModel
from services.common.se3 import se3_exp
from services.synthetic.generator import generate
from services.synthetic.replay import landmark_messages
from services.tracker.config import TrackerConfig
from services.tracker.service import TrackerNode, observations
from tests.common.service_harness import ServiceHarness
from tests.conftest import Processes, output_of, wait_routed, wait_until, zenoh_args

KEYS = Keys("trk")


class FakeTracker(ServiceHarness):
    """A tracker node on the fake bus, with the hand bodies it publishes in :attr:`bodies`."""

    def __init__(self) -> None:
        super().__init__("tracker", KEYS)
        TrackerNode(self.service, TrackerConfig())
        self.bodies = self.record(KEYS.hand_body, HandBody)

    def landmarks(self, *messages: HandLandmarks | bytes) -> None:
        self.send(KEYS.hand_landmarks, *messages)


@pytest.fixture(scope="module")
def valve() -> list[HandLandmarks]:
    return landmark_messages(generate("valve", 3, 0))


def _same_bodies(a: list[HandBody], b: list[HandBody]) -> bool:
    """Same estimates (sequence numbers aside)."""
    return len(a) == len(b) and all(
        x.stamp_ns == y.stamp_ns and x.initialized == y.initialized
        and np.array_equal(x.pose, y.pose) and np.array_equal(x.covariance, y.covariance)
        for x, y in zip(a, b, strict=True))


def test_every_frame_gives_a_hand_body_with_its_stamp(valve: list[HandLandmarks]) -> None:
    frames = valve[:60]
    node = FakeTracker()
    node.landmarks(*frames)

    bodies = node.bodies
    stats = node.stats()
    stamps = [b.stamp_ns for b in bodies]
    assert stamps == sorted(stamps) and set(stamps) <= {f.stamp_ns for f in frames}  # carried
    assert len(bodies) + sum(stats.skipped.values()) == len(frames)  # published, or counted
    assert [b.seq for b in bodies] == list(range(len(bodies)))
    assert sum(b.initialized for b in bodies) > 40
    last = bodies[-1]
    assert last.frame_id == "camera" and np.isfinite(last.pose).all()
    assert set(np.unique(last.landmarks.status)) <= {0, 1, 2, 3}
    # state messages (congestion control BLOCK), never dropped like camera frames
    assert all(not p.frame for p in node.bus.puts if p.key == KEYS.hand_body)
    assert (stats.received, stats.published, stats.rejected) == (len(frames), len(bodies), {})
    assert "step" in stats.latency_ms


def test_an_idle_second_hand_changes_no_published_body(valve: list[HandLandmarks]) -> None:
    """With an idle second hand in view (labelled like the manipulating one) the node publishes
    the same hand bodies, held-back frames late but in stamp order, with their body epoch; the
    wait is counted (choosing_hand)."""
    frames = valve[:80]
    clean = FakeTracker()
    clean.landmarks(*frames)
    two = landmark_messages(generate("valve", 3, 0, idle_hand="same"))[:80]
    assert all(len(m.hands) == 2 for m in two)
    node = FakeTracker()
    node.landmarks(*two)
    assert _same_bodies(clean.bodies, node.bodies)
    assert [b.seq for b in node.bodies] == list(range(len(node.bodies)))
    assert {b.body_epoch for b in node.bodies} == {0}
    assert node.stats().skipped.get("choosing_hand", 0) > 0
    assert "second_hand_moving" not in node.stats().skipped


def test_bad_input_is_counted_and_does_not_disturb_tracking(valve: list[HandLandmarks]) -> None:
    frames = valve[:60]
    clean = FakeTracker()
    clean.landmarks(*frames)
    node = FakeTracker()
    node.landmarks(*frames[:21])
    node.landmarks(b"\x81\xa6schema\xc0", frames[0])  # a nil schema, then a frame out of order
    node.send(KEYS.kinematics_model, b"not a model")
    node.landmarks(*frames[21:])

    assert _same_bodies(node.bodies, clean.bodies)
    stats = node.stats()
    assert stats.received == len(frames) + 3
    assert stats.rejected == {"bad_field": 1, "out_of_order_stamp": 1, "bad_msgpack": 1}
    assert stats.published == len(node.bodies)


def test_a_frame_without_a_hand_is_skipped_not_published(valve: list[HandLandmarks]) -> None:
    node = FakeTracker()
    node.landmarks(*valve[:30])
    published, skipped = node.stats().published, node.stats().skipped
    empty = dataclasses.replace(valve[29], stamp_ns=valve[29].stamp_ns + 1, hands=())
    node.landmarks(empty)

    stats = node.stats()
    assert stats.published == published and stats.rejected == {}
    assert stats.skipped == {**skipped, "no_hand": skipped.get("no_hand", 0) + 1}
    assert node.bodies[-1].stamp_ns == valve[29].stamp_ns


def test_a_kinematic_model_is_accepted_and_a_broken_one_counted() -> None:
    node = FakeTracker()
    model = KinematicModel(type="unknown", probabilities={"rigid": 0.25, "prismatic": 0.25,
                                                          "revolute": 0.25,
                                                          "disconnected": 0.25})
    node.send(KEYS.kinematics_model, model)
    assert (node.stats().received, node.stats().rejected) == (1, {})
    node.send(KEYS.kinematics_model, model.to_msgpack()[:-3])
    assert node.stats().received == 2 and sum(node.stats().rejected.values()) == 1
    assert node.bodies == []


def test_reset_starts_over_as_a_fresh_tracker(valve: list[HandLandmarks]) -> None:
    node = FakeTracker()
    node.landmarks(*valve[:60])
    before = len(node.bodies)
    assert node.bodies[-1].initialized

    ack = node.reset()
    node.landmarks(*valve[60:])

    fresh = FakeTracker()
    fresh.landmarks(*valve[60:])
    assert ack.ok, ack.message
    assert not node.bodies[before].initialized  # the body is acquired again
    assert _same_bodies(node.bodies[before:], fresh.bodies)
    assert [b.seq for b in node.bodies] == list(range(len(node.bodies)))  # seq keeps counting


def test_world_landmarks_with_a_camera_pose_are_tracked_in_the_world_frame() -> None:
    """A moving camera: the detector publishes world points with ``T_world_camera``; the tracker
    gets camera-frame points back plus the pose, so its depth noise follows the real viewing
    rays, and tracks (and publishes) in "world"."""
    frames = landmark_messages(generate("key", 3, 0))[:30]
    T_wc = se3_exp(np.array([0.3, -0.2, 1.0, 0.2, 0.5, -0.1]))
    moved = [dataclasses.replace(msg, frame_id="world", T_world_camera=T_wc, hands=tuple(
        dataclasses.replace(h, points=(h.points @ T_wc[:3, :3].T + T_wc[:3, 3]).astype("<f4"))
        for h in msg.hands)) for msg in frames]
    for msg, world in zip(frames, moved, strict=True):
        np.testing.assert_allclose(observations(world)[0].points, msg.hands[0].points, atol=1e-5,
                                   equal_nan=True)
    static = observations(dataclasses.replace(frames[0], T_world_camera=T_wc))  # camera frame
    np.testing.assert_array_equal(static[0].points, frames[0].hands[0].points.astype(float))

    node = FakeTracker()
    node.landmarks(*moved)
    assert node.bodies and all(b.frame_id == "world" for b in node.bodies)
    assert node.bodies[-1].initialized
    camera = FakeTracker()
    camera.landmarks(*frames)
    # The same track seen from the world: the body origin (centroid of the inliers) is the
    # camera run's moved by T_wc. Both runs see the same points up to the float32 rounding of
    # world coordinates (~1e-7 m), which 30 frames of filtering grow to ~1e-6 m, not 0.1 mm.
    assert [b.stamp_ns for b in node.bodies] == [b.stamp_ns for b in camera.bodies]
    for world, cam in zip(node.bodies, camera.bodies, strict=True):
        if cam.initialized:
            assert np.linalg.norm(world.pose[:3, 3] - (T_wc @ cam.pose)[:3, 3]) < 1e-4


# --- the service process over a real router ---


def test_landmarks_in_hand_body_out_bad_input_counted(procs: Processes, router: str,
                                                      client_bus: Bus,
                                                      valve: list[HandLandmarks]) -> None:
    bodies: list[HandBody] = []
    client_bus.subscribe(KEYS.hand_body, lambda k, p: bodies.append(HandBody.from_msgpack(p)))
    wait_routed(client_bus)  # before the tracker connects, so it learns the subscription
    tracker = procs.start("tracker", "--rig", KEYS.rig, *zenoh_args(router), name="tracker")
    wait_until(lambda: KEYS.alive("tracker") in client_bus.alive(KEYS.alive_all), 20,
               what=f"tracker liveliness; log: {output_of(tracker)}")

    frames = valve[:60]
    for i, msg in enumerate(frames):
        client_bus.put(KEYS.hand_landmarks, msg.to_msgpack())
        if i == 20:  # bad input in the middle of the stream
            client_bus.put(KEYS.hand_landmarks, b"\x81\xa6schema\xc0")
            client_bus.put(KEYS.hand_landmarks, frames[0].to_msgpack())  # out of order
            client_bus.put(KEYS.kinematics_model, b"not a model")
    wait_until(lambda: bool(bodies) and bodies[-1].stamp_ns == frames[-1].stamp_ns, 20,
               what="hand body of the last frame")
    empty = dataclasses.replace(frames[-1], stamp_ns=frames[-1].stamp_ns + 1, hands=())
    client_bus.put(KEYS.hand_landmarks, empty.to_msgpack())  # valid, but no hand: skipped

    # the process publishes what the node does on the fake bus, message for message
    node = FakeTracker()
    node.landmarks(*frames, empty)
    assert _same_bodies(bodies, node.bodies)
    assert [b.seq for b in bodies] == list(range(len(bodies)))

    def stats_now() -> dict:  # type: ignore[type-arg]
        return dict(json.loads(client_bus.get(KEYS.stats("tracker") + "?format=json")[0][1]))

    wait_until(lambda: stats_now()["received"] == len(frames) + 4, 10, what="all received")
    stats = stats_now()
    assert stats["skipped"] == node.stats().skipped and stats["skipped"]["no_hand"] >= 1
    assert stats["rejected"] == {"bad_field": 1, "bad_msgpack": 1, "out_of_order_stamp": 1}
    assert "step" in stats["latency_ms"]
    assert tracker.poll() is None


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
    wait_routed(client_bus)  # before any tracker connects
    uninterrupted = FakeTracker()
    uninterrupted.landmarks(*frames)
    reference = {b.stamp_ns: b.pose for b in uninterrupted.bodies if b.initialized}

    def run_tracker(part: list, state: str | None) -> dict[int, np.ndarray]:  # type: ignore[type-arg]
        extra = ["--state-file", state] if state else []
        p = procs.start("tracker", "--rig", KEYS.rig, *zenoh_args(router), *extra,
                        name="tracker")
        wait_until(lambda: KEYS.alive("tracker") in client_bus.alive(KEYS.alive_all), 20,
                   what=f"tracker liveliness; log: {output_of(p)}")
        bodies.clear()
        for msg in part:
            client_bus.put(KEYS.hand_landmarks, msg.to_msgpack())
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
