"""Detector benchmark: per-stage latency on a 1280x720 RGB-D frame, and frames per second
through the service.

Frame: opencv-doc ``basketball1.png`` (fetched like the tests), a 16:9 crop around the man
catching the ball upscaled to 1280x720 (his hand ~120 px, ~9 % of the width: about the smallest
the 192-px palm detector finds on a whole frame), with a synthetic 16-bit depth image (0.7 m
hand plane, 1 mm noise, 2 % holes), JPEG colour and raw 16-bit depth as ``handkse camera`` sends
it by default (the cost of PNG16 depth is measured separately).

1. Library, CPU, ``threads`` intra-op threads (default 2), full models: ``decode`` (JPEG + PNG16
   of the wire message) and the pipeline stages ``preprocess``, ``palm``, ``landmarks``,
   ``backproject``, p50/p99 over ``frames`` frames, in **detection mode** (``tracking =
   false``: palm detection on every frame), **tracking mode** (default config: the ROI comes from
   the previous landmarks; with ``max_hands = 2`` and one hand in view, palm detection still
   looks for a second hand every 10th frame) and **tracking, one hand** (``max_hands = 1``:
   palm detection never runs once the hand is found). Stages that did not run in a frame are
   not sampled; ``frame`` is the sum per frame including decoding, and ``fps`` its inverse mean.
   ``p5`` is given as well: on a shared machine it approximates the uncontended cost. The
   modes take turns frame by frame, so that other load affects them alike.
   ``library_cpu_time_1_thread``: the same stages with one ORT thread, timed with
   ``time.thread_time`` (CPU time of the thread that does all the work): what one dedicated
   core would take, much less sensitive to other processes than wall time.
2. Service: a router and ``python -m services.detector`` as separate processes on a unix
   socket; this process publishes the frame (new stamp each time) at ``rate_hz`` for
   ``seconds`` and counts the HandLandmarks that come back (fps) and their latency from publish
   to receipt. At 120 Hz the detector is saturated (skips to the newest frame): its fps is the
   throughput; at 30 Hz (the Azure Kinect's rate) it shows whether it keeps up.

``python -m bench.detector [--frames N] [--seconds S] [--device auto|cpu|cuda|tensorrt]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench.common import percentiles_ms, write_result
from services.common.bus import Bus, ZenohOptions
from services.common.keys import Keys
from services.common.processes import ProcessGroup, client_args
from services.common.protocol import CameraIntrinsics, HandLandmarks, RgbdFrame
from services.detector.config import DetectorConfig
from services.detector.models import default_models_dir, prepare
from services.detector.pipeline import STAGES, HandPipeline
from services.detector.samples import opencv_doc_images
from services.detector.sources import CapturedFrame, decode_depth, decode_frame, encode_frame

CROP = (40, 60, 213)  # x0, y0, width of the 16:9 crop of basketball1.png


def bench_frame(seed: int = 0) -> CapturedFrame:
    image = cv2.imread(str(opencv_doc_images() / "basketball1.png"), cv2.IMREAD_COLOR)
    assert image is not None
    x0, y0, w = CROP
    h = w * 9.0 / 16.0
    M = np.array([[1280.0 / w, 0.0, -x0 * 1280.0 / w], [0.0, 720.0 / h, -y0 * 720.0 / h]])
    color = cv2.warpAffine(image, M, (1280, 720), flags=cv2.INTER_CUBIC)
    rng = np.random.default_rng(seed)
    depth = (700 + rng.normal(0.0, 1.0, (720, 1280))).astype(np.uint16)
    depth[rng.random((720, 1280)) < 0.02] = 0
    K = CameraIntrinsics(fx=608.0, fy=608.0, cx=639.5, cy=359.5, width=1280, height=720)
    return CapturedFrame(stamp_ns=time.time_ns(), color_bgr=np.asarray(color, np.uint8),
                         depth=depth, depth_scale_m=0.001, intrinsics=K)


def library(configs: dict[str, DetectorConfig], message: RgbdFrame, frames: int,
            clock: Callable[[], float] = time.perf_counter) -> dict[str, dict[str, Any]]:
    """Per-stage latency of each configuration; the modes take turns frame by frame, so that
    load from other processes affects them alike. ``clock=time.thread_time`` with one ORT
    thread (which then runs in the calling thread) measures CPU time instead of wall time."""
    pipelines = {mode: HandPipeline.from_config(c, clock) for mode, c in configs.items()}
    payload = message.to_msgpack()
    samples: dict[str, dict[str, list[float]]] = {
        m: {s: [] for s in ("decode", *STAGES, "frame")} for m in configs}
    palm_runs = dict.fromkeys(configs, 0)
    hands = dict.fromkeys(configs, 0)
    for i in range(frames + 10):
        for mode, pipeline in pipelines.items():
            t0 = clock()
            frame = decode_frame(RgbdFrame.from_msgpack(payload))
            decode_s = clock() - t0
            result = pipeline.process(frame.color_bgr, frame.depth, frame.depth_scale_m,
                                      frame.intrinsics)
            if i < 10:  # warm-up (first runs allocate, TensorRT builds engines)
                continue
            samples[mode]["decode"].append(decode_s)
            for stage, seconds in result.timings_s.items():
                samples[mode][stage].append(seconds)
            samples[mode]["frame"].append(decode_s + sum(result.timings_s.values()))
            palm_runs[mode] += result.palm_ran
            hands[mode] += len(result.hands)
    out: dict[str, dict[str, Any]] = {}
    for mode, pipeline in pipelines.items():
        stages = {k: {**percentiles_ms(v), "p5": float(np.percentile(v, 5) * 1e3)}
                  for k, v in samples[mode].items() if v}
        out[mode] = {"stages_ms": stages, "fps": 1e3 / stages["frame"]["mean"],
                     "fps_p50": 1e3 / stages["frame"]["p50"],
                     "palm_ran_fraction": palm_runs[mode] / frames,
                     "hands_per_frame": hands[mode] / frames, "providers": pipeline.providers}
    return out


def service(config_args: list[str], message: RgbdFrame, rate_hz: float, seconds: float,
            device: str, threads: int) -> dict[str, Any]:
    keys = Keys("benchdet")
    group = ProcessGroup(Path(tempfile.mkdtemp(prefix="handkse-bench-")))
    endpoint = f"unixsock-stream/{group.workdir}/router.sock"
    group.start_router(endpoint)
    detector = group.start("detector", "detector", *client_args(endpoint, keys.rig), "--device",
                           device, "--threads", str(threads), *config_args)
    sent_at: dict[int, float] = {}
    latencies: list[float] = []
    received: list[int] = []
    lock = threading.Lock()
    try:
        with Bus(ZenohOptions(mode="client", connect=(endpoint,),
                              multicast_scouting=False)) as bus:
            deadline = time.monotonic() + 60.0
            while keys.alive("detector") not in bus.alive(keys.alive_all):
                if time.monotonic() > deadline or detector.poll() is not None:
                    raise RuntimeError("detector did not start")
                time.sleep(0.1)

            def on_landmarks(_k: str, payload: bytes) -> None:
                stamp = HandLandmarks.from_msgpack(payload).stamp_ns
                now = time.perf_counter()
                with lock:
                    received.append(stamp)
                    if stamp in sent_at:
                        latencies.append(now - sent_at[stamp])

            bus.subscribe(keys.hand_landmarks, on_landmarks)
            time.sleep(0.3)
            # warm up (palm detection finds the hand, sessions allocate)
            for _ in range(10):
                bus.put(keys.camera_rgbd, dataclasses.replace(
                    message, stamp_ns=time.time_ns()).to_msgpack(), frame=True)
                time.sleep(0.1)
            time.sleep(0.5)
            with lock:
                received.clear()
                latencies.clear()
            period = 1.0 / rate_hz
            n = int(rate_hz * seconds)
            t_next = t_start = time.perf_counter()
            for i in range(n):
                stamp = time.time_ns()
                payload = dataclasses.replace(message, seq=i, stamp_ns=stamp).to_msgpack()
                with lock:
                    sent_at[stamp] = time.perf_counter()
                bus.put(keys.camera_rgbd, payload, frame=True)
                t_next += period
                delay = t_next - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            elapsed = time.perf_counter() - t_start
            time.sleep(0.5)
            with lock:
                got = [s for s in received if s in sent_at]
                lat = list(latencies)
    finally:
        group.stop_all()
    return {"input_hz": rate_hz, "sent": n, "processed": len(got),
            "fps": len(got) / elapsed, "latency_ms": percentiles_ms(lat) if lat else None}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu", choices=("auto", "cpu", "cuda", "tensorrt"))
    parser.add_argument("--skip-service", action="store_true")
    args = parser.parse_args(argv if argv is not None else [])
    prepare(default_models_dir())
    frame = bench_frame()
    message = encode_frame(frame)
    base = DetectorConfig(device=args.device, threads=args.threads)
    load_before = os.getloadavg()
    lib = library({
        "detection": dataclasses.replace(base, tracking=False),
        "tracking": base,
        "tracking_one_hand": dataclasses.replace(base, max_hands=1),
        "detection_lite": dataclasses.replace(base, tracking=False, palm_model="lite",
                                              landmark_model="lite"),
    }, message, args.frames)
    cpu = None
    if args.device == "cpu":
        one = dataclasses.replace(base, threads=1)
        cpu = library({"detection": dataclasses.replace(one, tracking=False),
                       "tracking_one_hand": dataclasses.replace(one, max_hands=1)},
                      message, args.frames // 2, clock=time.thread_time)
    for mode, r in lib.items():
        if r["hands_per_frame"] < 0.99:
            print(f"warning: {mode}: a hand in only {r['hands_per_frame']:.0%} of the frames")
    png = encode_frame(frame, depth_encoding="png16").depth
    png_decode = []
    for _ in range(30):
        t0 = time.perf_counter()
        decode_depth(png)
        png_decode.append(time.perf_counter() - t0)
    result: dict[str, Any] = {
        "frame": {"size": [1280, 720], "jpeg_bytes": len(message.color.data),
                  "depth_bytes": len(message.depth.data), "depth_encoding": "u16",
                  "png16_depth_bytes": len(png.data),
                  "png16_depth_decode_ms": percentiles_ms(png_decode),
                  "source": "opencv-doc basketball1.png, 16:9 crop upscaled"},
        "load_average_before": load_before,
        "threads": args.threads, "device": args.device, "library": lib,
        "library_cpu_time_1_thread": cpu,
        "goal": "CPU: tracking >= 60 fps, detection >= 30 fps (paper: 22 fps on a GPU)",
    }
    if not args.skip_service:
        svc = {}
        for mode, extra in (("detection", ["--set", "detector.tracking=false"]),
                            ("tracking", []), ("tracking_one_hand", ["--max-hands", "1"])):
            for rate in (120.0, 30.0):
                svc[f"{mode}_{int(rate)}hz"] = service(extra, message, rate, args.seconds,
                                                       args.device, args.threads)
        result["service"] = svc
    result["load_average_after"] = os.getloadavg()
    write_result("detector" if args.device in ("cpu", "auto") else f"detector_{args.device}",
                 result)


if __name__ == "__main__":
    main(sys.argv[1:])
