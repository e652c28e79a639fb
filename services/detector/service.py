"""Detector service: RgbdFrame in, HandLandmarks out (``handkse detector``).

Subscribes ``handkse/{rig}/camera/rgbd`` **latest-only**: while a frame is being processed, newer
ones replace each other and the replaced ones are counted in ``dropped`` (``handkse stats
detector``); the detector never works through a backlog. With ``--source kinect|folder:DIR`` it
reads the frames in-process instead (single-host setup; ``--publish-frames`` also puts them on
the bus). Publishes ``handkse/{rig}/hand/landmarks`` for every processed frame (also with no
hand, so the tracker sees the hand vanish), with the frame's ``stamp_ns``; points are in the
camera frame, or in the world frame when the frame carries ``T_world_camera``.

Frames are handled in the service loop (one at a time, with ``stats`` and ``reset``); a feeder
thread hands over the next frame only when the previous one is done. Latency stages:
``decode`` (JPEG/PNG), ``preprocess``, ``palm``, ``landmarks``, ``backproject`` (see
:mod:`services.detector.pipeline`) and ``total``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, Protocol, TypeVar

import numpy as np

from services.common.keys import Keys
from services.common.protocol import Hand, HandLandmarks, ProtocolError, RgbdFrame
from services.common.service import BusLike, Service, ServiceLimits, stop_on_signals
from services.detector.backproject import to_world
from services.detector.config import DEVICES, VARIANTS, DetectorConfig
from services.detector.pipeline import FrameResult, HandPipeline
from services.detector.source_factory import open_source
from services.detector.sources import (
    CapturedFrame,
    FrameSource,
    SourceUnavailable,
    decode_frame,
    encode_frame,
)

log = logging.getLogger(__name__)

T = TypeVar("T")


class FrameBus(BusLike, Protocol):
    """What the detector needs from the bus: a service bus plus latest-only subscriptions."""

    def subscribe_latest(self, key: str) -> Any: ...


class Latest(Generic[T]):
    """Latest-only hand-over between a producer thread and the service loop; counts skips."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self.skipped = 0

    def push(self, item: T) -> None:
        with self._cond:
            if self._item is not None:
                self.skipped += 1
            self._item = item
            self._cond.notify()

    def take(self, timeout: float) -> T | None:
        with self._cond:
            if self._item is None:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            self._cond.notify_all()
            return item

    def wait_empty(self, stop: threading.Event) -> None:
        """Block until the pending item was taken (or ``stop``)."""
        with self._cond:
            while self._item is not None and not stop.is_set():
                self._cond.wait(0.1)


def landmarks_message(result: FrameResult, frame: CapturedFrame, seq: int) -> HandLandmarks:
    """The wire message of one processed frame (world frame when the camera pose is known)."""
    T_wc = frame.T_world_camera
    hands = []
    for h in result.hands:
        points = h.points if T_wc is None else to_world(h.points, T_wc)
        hands.append(Hand(handedness=h.handedness, score=float(np.clip(h.score, 0.0, 1.0)),
                          points=np.asarray(points, "<f4"),
                          visibility=np.clip(np.asarray(h.visibility, "<f4"), 0.0, 1.0),
                          pixels=np.asarray(h.pixels, "<f4")))
    return HandLandmarks(seq=seq, stamp_ns=int(frame.stamp_ns),
                         frame_id="camera" if T_wc is None else "world", hands=tuple(hands),
                         T_world_camera=None if T_wc is None else np.asarray(T_wc, "<f8"))


class DetectorNode:
    """Binds a :class:`HandPipeline` to a :class:`Service`; every method runs in its loop."""

    def __init__(self, service: Service, pipeline: HandPipeline) -> None:
        self.service = service
        self.pipeline = pipeline
        self.frames = 0
        service.on_reset(pipeline.reset)

    def on_payload(self, payload: bytes) -> None:
        """A received ``RgbdFrame`` payload (bad ones are counted under their reason)."""
        latency = self.service.latency
        try:
            with latency.measure("decode"):
                t0 = time.perf_counter()
                message = RgbdFrame.from_msgpack(payload)
                frame = decode_frame(message)
        except ProtocolError as exc:
            self.service.reject(exc.reason, str(exc))
            return
        self.on_frame(frame, t0)

    def on_frame(self, frame: CapturedFrame, t0: float | None = None) -> HandLandmarks:
        t0 = time.perf_counter() if t0 is None else t0
        result = self.pipeline.process(frame.color_bgr, frame.depth, frame.depth_scale_m,
                                       frame.intrinsics)
        for stage, seconds in result.timings_s.items():
            self.service.latency.add(stage, seconds)
        keys = self.service.keys
        message = landmarks_message(result, frame, self.service.next_seq(keys.hand_landmarks))
        self.service.publish(keys.hand_landmarks, message)
        self.service.latency.add("total", time.perf_counter() - t0)
        self.frames += 1
        return message


def _hand_over(service: Service, take: Callable[[float], T | None], handle: Callable[[T], None],
               stop: threading.Event, after: Callable[[], None] | None = None) -> None:
    """Feeder loop: take the next item, run ``handle`` in the service loop, wait until done."""
    done = threading.Event()

    def run(item: T) -> None:
        try:
            handle(item)
        finally:
            if after is not None:
                after()
            done.set()

    while not stop.is_set():
        item = take(0.1)
        if item is None:
            continue
        done.clear()
        service.call_soon(run, item)
        while not done.wait(0.1):
            if stop.is_set():
                return


def run(bus: FrameBus, keys: Keys, config: DetectorConfig, stop: threading.Event,
        source: FrameSource | None = None, publish_frames: bool = False,
        max_frames: int | None = None, ready: Callable[[], None] | None = None,
        limits: ServiceLimits | None = None) -> DetectorNode:
    """Run the detector until ``stop`` (or the end of ``source``, or ``max_frames``)."""
    pipeline = HandPipeline.from_config(config)
    log.info("detector models loaded; providers %s", pipeline.providers)
    service = Service("detector", bus, keys, limits)
    node = DetectorNode(service, pipeline)

    def count_and_stop() -> None:
        if max_frames is not None and node.frames >= max_frames:
            stop.set()

    threads = []
    if source is None:
        slot = bus.subscribe_latest(keys.camera_rgbd)

        def take_payload(timeout: float) -> bytes | None:
            item = slot.take(timeout)
            return None if item is None else item[1]

        taken = 0

        def on_payload(payload: bytes) -> None:
            nonlocal taken
            taken += 1
            service.received = taken + slot.skipped  # every frame that arrived
            service.dropped = slot.skipped
            limit = service.limits.max_frame_payload_bytes
            if len(payload) > limit:
                service.reject("too_large", f"{len(payload)} bytes on {keys.camera_rgbd} (limit "
                                            f"{limit}, limits.max_frame_payload_bytes)")
                return
            node.on_payload(payload)

        threads.append(threading.Thread(
            target=_hand_over, args=(service, take_payload, on_payload, stop, count_and_stop),
            name="detector-feed", daemon=True))
    else:
        threads += _source_threads(service, node, source, stop, publish_frames, count_and_stop)
    for t in threads:
        t.start()
    if ready is not None:
        ready()
    try:
        service.run(stop)
    finally:
        stop.set()
        if source is not None:
            source.close()
        for t in threads:
            t.join(5.0)
    return node


def _source_threads(service: Service, node: DetectorNode, source: FrameSource,
                    stop: threading.Event, publish_frames: bool,
                    after: Callable[[], None]) -> list[threading.Thread]:
    """Threads that read ``source`` in-process and feed the service loop."""
    keys = service.keys
    latest: Latest[CapturedFrame] = Latest()
    finished = threading.Event()

    handled = 0

    def handle(frame: CapturedFrame) -> None:
        nonlocal handled
        handled += 1
        service.received = handled + latest.skipped
        service.dropped = latest.skipped
        if publish_frames:
            message = encode_frame(frame, service.next_seq(keys.camera_rgbd))
            service.publish(keys.camera_rgbd, message, frame=True)
        node.on_frame(frame)

    def capture() -> None:
        try:
            for frame in source:
                if stop.is_set():
                    break
                if not source.realtime:  # every frame: wait until the last one is taken
                    latest.wait_empty(stop)
                latest.push(frame)  # realtime: a slow detector skips to the newest frame
        except Exception:
            log.exception("frame source failed")
        finally:
            finished.set()

    def take(timeout: float) -> CapturedFrame | None:
        ended = finished.is_set()  # read first: every frame was pushed before it was set
        item = latest.take(timeout)
        if item is None and ended:
            stop.set()  # the source ended and its last frame was handled
        return item

    return [threading.Thread(target=capture, name="detector-source", daemon=True),
            threading.Thread(target=_hand_over, args=(service, take, handle, stop, after),
                             name="detector-feed", daemon=True)]


# --------------------------------------------------------------------------------------------
# Command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``handkse detector`` (besides --rig, --config, --set and the zenoh ones)."""
    parser.add_argument("--source", metavar="SPEC",
                        help="read frames in this process instead of subscribing to "
                             "handkse/{rig}/camera/rgbd: 'kinect', 'realsense[:SERIAL]', "
                             "'bag:FILE', 'kinect-recording:FILE' or 'folder:DIR'")
    parser.add_argument("--rate", type=float, default=1.0,
                        help="folder source: replay speed (1 = recorded pace, 0 = every frame "
                             "as fast as possible)")
    parser.add_argument("--loop", action="store_true", help="folder source: replay forever")
    parser.add_argument("--publish-frames", action="store_true",
                        help="with --source: also publish the frames on camera/rgbd")
    parser.add_argument("--max-frames", type=int, metavar="N",
                        help="stop after processing N frames")
    parser.add_argument("--device", choices=DEVICES,
                        help="ONNX Runtime device (default [detector] device = auto: TensorRT > "
                             "CUDA > CPU)")
    parser.add_argument("--threads", type=int, help="intra-op threads per model (default 2)")
    parser.add_argument("--models-dir", metavar="DIR", help="prepared model cache")
    parser.add_argument("--palm-model", choices=VARIANTS, help="palm detector variant")
    parser.add_argument("--landmark-model", choices=VARIANTS, help="hand-landmark variant")
    parser.add_argument("--max-hands", type=int, choices=(1, 2))
    parser.add_argument("--keypoint-model", metavar="PATH",
                        help="RTMPose-hand SimCC ONNX file (rtmlib's end2end.onnx from "
                             "https://download.openmmlab.com/mmpose/v1/projects/rtmposev1/"
                             "onnx_sdk/rtmpose-m_simcc-hand5_pt-aic-coco_210e-256x256-74fb594_"
                             "20230320.zip) for per-landmark confidences")
    parser.add_argument("--kinect-device", type=int, default=0, help="Azure Kinect index")


_CLI_FIELDS = {"device": "device", "threads": "threads", "models_dir": "models_dir",
               "palm_model": "palm_model", "landmark_model": "landmark_model",
               "max_hands": "max_hands", "keypoint_model": "keypoint_model"}


def config_from_args(args: argparse.Namespace) -> DetectorConfig:
    """``[detector]`` of ``--config``/``--set``, then the explicit command-line options."""
    from services.common import config as config_module

    config = config_module.section_from_args(args, "detector")
    assert isinstance(config, DetectorConfig)
    changes = {name: getattr(args, attr) for attr, name in _CLI_FIELDS.items()
               if getattr(args, attr, None) is not None}
    return dataclasses.replace(config, **changes) if changes else config


def main(args: argparse.Namespace) -> int:
    """``handkse detector``: 0 on a clean stop, 2 when models, device or source are missing."""
    from services.common.bus import Bus, options_from_args
    from services.common.config import section_from_args
    from services.detector.models import ModelsMissing
    from services.detector.runtime import DeviceUnavailable

    config = config_from_args(args)
    stop = threading.Event()
    stop_on_signals(stop)
    source = None
    try:
        if args.source:
            source = open_source(args.source, rate=args.rate, loop=args.loop,
                                 device_id=args.kinect_device)
        with Bus(options_from_args(args, section_from_args(args, "zenoh"))) as bus:
            node = run(bus, Keys(args.rig), config, stop, source=source,
                       publish_frames=args.publish_frames, max_frames=args.max_frames,
                       ready=lambda: print("detector ready", flush=True),
                       limits=section_from_args(args, "limits"))
            log.info("detector processed %d frames", node.frames)
            time.sleep(0.2)  # let the last landmarks leave before the session closes
    except (ModelsMissing, SourceUnavailable, DeviceUnavailable, FileNotFoundError) as exc:
        print(f"handkse detector: {exc}", file=sys.stderr, flush=True)
        return 2
    finally:
        if source is not None:
            source.close()
    return 0


__all__ = ["DetectorNode", "Latest", "add_arguments", "config_from_args", "landmarks_message",
           "main", "run"]
