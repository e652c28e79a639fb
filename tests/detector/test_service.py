"""The detector and camera services as separate processes over a real Zenoh router."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from services.common.bus import Bus
from services.common.keys import Keys
from services.common.protocol import HandLandmarks
from services.detector.sources import CapturedFrame, FolderWriter, encode_frame
from tests.conftest import Processes, output_of, wait_routed, wait_until, zenoh_args
from tests.detector.conftest import CATCHER_CROP, HAND_REGIONS, crop, intrinsics_for

KEYS = Keys("det")
SCALE = 3  # the catcher crop upscaled 3x: a 480x480 frame with a ~80 px hand


def start_module(procs: Processes, module: str, *args: str, name: str
                 ) -> subprocess.Popen[bytes]:
    """``python -m <module> ARGS`` as a child process that ``procs`` stops at teardown."""
    label = f"{name}-{len(procs.procs)}"
    p = procs.spawn(label, [sys.executable, "-m", module, *args])
    p.log_path = procs.log_path(label)  # type: ignore[attr-defined]
    return p


def frames(opencv_images: dict[str, np.ndarray]) -> list[CapturedFrame]:
    out = []
    for i, name in enumerate(("basketball1.png", "basketball2.png")):
        image = cv2.resize(crop(opencv_images[name], CATCHER_CROP), None, fx=SCALE, fy=SCALE,
                           interpolation=cv2.INTER_CUBIC)
        depth = np.full(image.shape[:2], 700, np.uint16)
        out.append(CapturedFrame(stamp_ns=1_700_000_000_000_000_000 + i * 33_333_333,
                                 color_bgr=np.asarray(image, np.uint8), depth=depth,
                                 depth_scale_m=0.001,
                                 intrinsics=intrinsics_for(image, f=600.0)))
    return out


def start_detector(procs: Processes, router: str, client_bus: Bus, models_dir: Path,
                   *extra: str) -> subprocess.Popen[str]:
    detector = start_module(procs, "services.detector", "--rig", KEYS.rig, *zenoh_args(router),
                            "--device", "cpu", "--models-dir", str(models_dir), *extra,
                            name="detector")
    wait_until(lambda: KEYS.alive("detector") in client_bus.alive(KEYS.alive_all)
               or detector.poll() is not None, 60,
               what=f"detector liveliness; log: {output_of(detector)}")
    assert detector.poll() is None, output_of(detector)
    return detector


def in_hand_region(message: HandLandmarks, name: str) -> bool:
    xmin, ymin, xmax, ymax = HAND_REGIONS[(name, CATCHER_CROP)]
    pixels = message.hands[0].pixels
    assert pixels is not None
    px = pixels / SCALE + np.array(CATCHER_CROP[:2])
    return bool(((px >= [xmin, ymin]) & (px <= [xmax, ymax])).all())


def test_rgbd_frame_in_hand_landmarks_out_with_the_same_stamp(
        procs: Processes, router: str, client_bus: Bus, models_dir: Path,
        opencv_images: dict[str, np.ndarray]) -> None:
    received: list[HandLandmarks] = []
    client_bus.subscribe(KEYS.hand_landmarks,
                         lambda k, p: received.append(HandLandmarks.from_msgpack(p)))
    wait_routed(client_bus)  # before the detector connects, so it learns the subscription
    detector = start_detector(procs, router, client_bus, models_dir)
    first, second = frames(opencv_images)

    # frame=False (BLOCK) so that no frame is lost in this client: the drops counted below must
    # be the detector's own (the camera service publishes with DROP, tested further down)
    client_bus.put(KEYS.camera_rgbd, b"not a frame")
    client_bus.put(KEYS.camera_rgbd, encode_frame(first, seq=0).to_msgpack())
    wait_until(lambda: any(m.stamp_ns == first.stamp_ns for m in received), 30,
               what=f"landmarks of the first frame; log: {output_of(detector)}")
    message = next(m for m in received if m.stamp_ns == first.stamp_ns)
    assert message.frame_id == "camera" and len(message.hands) == 1
    hand = message.hands[0]
    assert hand.score > 0.5 and in_hand_region(message, "basketball1.png")
    np.testing.assert_allclose(hand.points[:, 2], 0.7, atol=1e-6)  # flat 0.7 m depth
    assert (hand.visibility >= 0.0).all() and (hand.visibility <= 1.0).all()

    # a moving camera: the frame carries its pose and the landmarks come in the world frame
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 1.0]
    moving = dataclasses.replace(second, T_world_camera=T)
    client_bus.put(KEYS.camera_rgbd, encode_frame(moving, seq=1).to_msgpack())
    wait_until(lambda: any(m.stamp_ns == second.stamp_ns for m in received), 30,
               what="landmarks of the second frame")
    world = next(m for m in received if m.stamp_ns == second.stamp_ns)
    assert world.frame_id == "world"
    np.testing.assert_allclose(world.hands[0].points[:, 2], 1.7, atol=1e-6)

    # a burst faster than the detector: it skips to the newest frame and counts the skips
    stamps = [second.stamp_ns + (i + 1) * 1_000_000 for i in range(20)]
    for i, stamp in enumerate(stamps):
        burst = dataclasses.replace(first, stamp_ns=stamp)
        client_bus.put(KEYS.camera_rgbd, encode_frame(burst, seq=2 + i).to_msgpack())
    wait_until(lambda: bool(received) and received[-1].stamp_ns == stamps[-1], 30,
               what="landmarks of the last frame of the burst")
    got = [m.stamp_ns for m in received]
    assert got == sorted(got) and set(got) <= {first.stamp_ns, second.stamp_ns, *stamps}
    assert [m.seq for m in received] == list(range(len(received)))

    stats = json.loads(client_bus.get(KEYS.stats("detector") + "?format=json")[0][1])
    assert stats["received"] == 23
    assert stats["rejected"] == {"bad_msgpack": 1}
    assert stats["published"] == len(received)
    assert stats["published"] + stats["dropped"] + 1 == stats["received"]
    assert set(stats["latency_ms"]) >= {"decode", "preprocess", "palm", "landmarks",
                                        "backproject", "total"}
    assert detector.poll() is None


def _write_folder(path: Path, opencv_images: dict[str, np.ndarray]) -> list[int]:
    fs = frames(opencv_images)
    with FolderWriter(path, fs[0].intrinsics, 0.001) as writer:
        for f in fs:
            writer.write(f)
    return [f.stamp_ns for f in fs]


def test_camera_from_a_folder_to_the_detector(procs: Processes, router: str, client_bus: Bus,
                                              models_dir: Path, tmp_path: Path,
                                              opencv_images: dict[str, np.ndarray]) -> None:
    stamps = _write_folder(tmp_path / "frames", opencv_images)
    received: list[HandLandmarks] = []
    client_bus.subscribe(KEYS.hand_landmarks,
                         lambda k, p: received.append(HandLandmarks.from_msgpack(p)))
    wait_routed(client_bus)  # before the detector connects, so it learns the subscription
    start_detector(procs, router, client_bus, models_dir)
    camera = start_module(procs, "services.detector.camera", "--rig", KEYS.rig,
                          *zenoh_args(router), "--folder", str(tmp_path / "frames"),
                          "--wait-for", "detector", name="camera")
    wait_until(lambda: camera.poll() is not None, 60, what=f"camera end; {output_of(camera)}")
    assert camera.returncode == 0, output_of(camera)
    assert "camera published 2 frames" in output_of(camera)
    wait_until(lambda: bool(received) and received[-1].stamp_ns == stamps[-1], 30,
               what="landmarks of the last folder frame")
    assert {m.stamp_ns for m in received} <= set(stamps)
    assert all(len(m.hands) == 1 for m in received)


def test_detector_reads_a_source_in_process(procs: Processes, router: str, client_bus: Bus,
                                            models_dir: Path, tmp_path: Path,
                                            opencv_images: dict[str, np.ndarray]) -> None:
    stamps = _write_folder(tmp_path / "frames", opencv_images)
    received: list[HandLandmarks] = []
    client_bus.subscribe(KEYS.hand_landmarks,
                         lambda k, p: received.append(HandLandmarks.from_msgpack(p)))
    detector = start_module(procs, "services.detector", "--rig", KEYS.rig, *zenoh_args(router),
                            "--device", "cpu", "--models-dir", str(models_dir), "--source",
                            f"folder:{tmp_path / 'frames'}", "--rate", "0", name="detector")
    wait_until(lambda: detector.poll() is not None, 60, what=f"detector end; {output_of(detector)}")
    assert detector.returncode == 0, output_of(detector)
    wait_until(lambda: len(received) == len(stamps), 10,
               what=f"landmarks of every frame; log: {output_of(detector)}")
    assert [m.stamp_ns for m in received] == stamps  # rate 0: every frame, in order
    assert in_hand_region(received[0], "basketball1.png")


def test_missing_models_stop_the_detector_with_a_hint(procs: Processes, router: str,
                                                      tmp_path: Path) -> None:
    detector = start_module(procs, "services.detector", "--rig", KEYS.rig, *zenoh_args(router),
                            "--device", "cpu", "--models-dir", str(tmp_path / "empty"),
                            name="detector")
    wait_until(lambda: detector.poll() is not None, 30, what="detector exit")
    assert detector.returncode == 2
    assert "handkse models prepare" in output_of(detector)
