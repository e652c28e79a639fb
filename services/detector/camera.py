"""Camera service: an RGB-D source published as ``RgbdFrame`` (``handkse camera``).

One source: ``--realsense [--serial S]`` (Intel RealSense through pyrealsense2), ``--kinect``
(Azure Kinect, or Orbbec Femto through its K4A wrapper, through pyk4a), a recording (``--bag
FILE`` from a RealSense, ``--kinect-recording FILE.mkv`` from an Azure Kinect or Femto) or
``--folder DIR`` (see :mod:`services.detector.sources` for the layout); every camera publishes
colour-registered depth and the colour camera's intrinsics (docs/cameras.md). Frames go to
``handkse/{rig}/camera/rgbd`` with JPEG colour and 16-bit depth (raw by default: 1.8 MB per
frame, but no PNG work on either side, which costs ~25-50 ms to encode and ~15 ms to decode per
1280x720 ToF frame; ``--depth-encoding png16`` for slow links), congestion control DROP
(only the newest frame matters). ``--save DIR`` also writes what is captured as a frame folder,
so a Kinect session can be replayed with ``--folder``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time

from services.common.keys import Keys
from services.common.service import BusLike, Service, stop_on_signals
from services.detector.source_factory import open_source
from services.detector.sources import (
    FolderWriter,
    FrameSource,
    SourceUnavailable,
    encode_frame,
)

log = logging.getLogger(__name__)


def publish_frames(service: Service, source: FrameSource, stop: threading.Event, *,
                   jpeg_quality: int = 90, depth_encoding: str = "u16",
                   max_frames: int | None = None, save: FolderWriter | None = None) -> int:
    """Publish every frame of ``source`` until it ends, ``stop`` or ``max_frames``; returns
    the number published."""
    key = service.keys.camera_rgbd
    n = 0
    for frame in source:
        if stop.is_set():
            break
        with service.latency.measure("encode"):
            message = encode_frame(frame, service.next_seq(key), jpeg_quality=jpeg_quality,
                                   depth_encoding=depth_encoding)
        service.publish(key, message, frame=True)
        if save is not None:
            save.write(frame)
        n += 1
        if max_frames is not None and n >= max_frames:
            break
    return n


def run(bus: BusLike, keys: Keys, source: FrameSource, stop: threading.Event, *,
        jpeg_quality: int = 90, depth_encoding: str = "u16", max_frames: int | None = None,
        save: FolderWriter | None = None) -> int:
    """Camera service until the source ends or ``stop``; returns the frames published."""
    service = Service("camera", bus, keys)
    published = [0]

    def capture() -> None:
        try:
            published[0] = publish_frames(service, source, stop, jpeg_quality=jpeg_quality,
                                          depth_encoding=depth_encoding, max_frames=max_frames,
                                          save=save)
        except SourceUnavailable as exc:  # a camera that stopped delivering: say what
            log.error("camera source failed: %s", exc)
        except Exception:
            log.exception("camera source failed")
        finally:
            time.sleep(0.2)  # let the last frames leave before the session closes
            stop.set()

    thread = threading.Thread(target=capture, name="camera-capture", daemon=True)
    thread.start()
    try:
        service.run(stop)
    finally:
        stop.set()
        source.close()
        thread.join(5.0)
    return published[0]


def frame_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> (width, height) in pixels, both positive."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 1280x720, got {text!r}"
                                         ) from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"width and height must be positive, got {text!r}")
    return w, h


def rate_value(text: str) -> float:
    """A playback rate: 1 = recorded pace, 0 = as fast as the consumer takes frames."""
    try:
        rate = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not rate >= 0.0:
        raise argparse.ArgumentTypeError(f"must be >= 0 (0 = as fast as possible), got {text}")
    return rate


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``handkse camera`` (besides --rig, --config, --set and the zenoh ones)."""
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--realsense", action="store_true",
                       help="Intel RealSense D400 camera (needs the realsense extra: pyrealsense2)")
    which.add_argument("--bag", metavar="FILE",
                       help="RealSense recording, .bag or .db3 (realsense extra)")
    which.add_argument("--kinect", action="store_true",
                       help="Azure Kinect or Orbbec Femto (needs the kinect extra: pyk4a + libk4a)")
    which.add_argument("--kinect-recording", metavar="FILE.mkv",
                       help="Azure Kinect / Femto recording from k4arecorder (kinect extra)")
    which.add_argument("--folder", metavar="DIR", help="frame folder (color/, depth/, "
                                                       "intrinsics.json, timestamps.txt)")
    parser.add_argument("--serial", metavar="S",
                        help="RealSense: the camera's serial number (default: the first found)")
    parser.add_argument("--color-size", type=frame_size, default=(1280, 720), metavar="WxH",
                        help="RealSense colour resolution (default 1280x720)")
    parser.add_argument("--depth-size", type=frame_size, default=(848, 480), metavar="WxH",
                        help="RealSense depth resolution before alignment (default 848x480)")
    parser.add_argument("--rate", type=rate_value, default=1.0,
                        help="recordings and folder: playback speed (1 = recorded pace, 0 = "
                             "every frame as fast as it is taken)")
    parser.add_argument("--loop", action="store_true",
                        help="recordings and folder: play forever (stamps keep increasing)")
    parser.add_argument("--keep-stamps", action="store_true",
                        help="recordings: keep the recorded frame times (default: the first "
                             "frame is stamped with the host time at start)")
    parser.add_argument("--fps", type=int, default=30, choices=(5, 6, 15, 30, 60, 90),
                        help="camera frame rate (Kinect: 5, 15, 30); folder pace without "
                             "timestamps.txt")
    parser.add_argument("--kinect-device", type=int, default=0, help="Azure Kinect index")
    parser.add_argument("--depth-mode", default="wfov_binned",
                        choices=("wfov_binned", "nfov_unbinned", "nfov_binned", "wfov_unbinned"),
                        help="Kinect depth mode (default wfov_binned: 0.25-2.88 m)")
    parser.add_argument("--no-undistort", action="store_true",
                        help="publish the images with the lens distortion the camera has")
    parser.add_argument("--jpeg-quality", type=int, default=90)
    parser.add_argument("--depth-encoding", choices=("u16", "png16"), default="u16",
                        help="raw 16-bit depth (default) or PNG16 (smaller, slower)")
    parser.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames")
    parser.add_argument("--save", metavar="DIR", help="also write the frames to a folder")
    parser.add_argument("--wait-for", action="append", metavar="SERVICE",
                        help="wait for this service's liveliness token before publishing")
    parser.add_argument("--wait-timeout", type=float, default=30.0)


def open_camera(args: argparse.Namespace) -> FrameSource:
    """The source the arguments name, opened; :class:`SourceUnavailable` or ``ValueError`` say
    why not. Each SDK is imported here, only for its own source."""
    if args.serial is not None and not args.realsense:
        raise SourceUnavailable("--serial selects a RealSense camera: use it with --realsense")
    if args.realsense:
        from services.detector.cameras.realsense import RealSenseSource

        return RealSenseSource(serial=args.serial, color_size=args.color_size,
                               depth_size=args.depth_size, fps=args.fps,
                               undistort=not args.no_undistort)
    if args.bag:
        from services.detector.cameras.realsense_recording import RealSenseRecording

        return RealSenseRecording(args.bag, rate=args.rate, loop=args.loop,
                                  undistort=not args.no_undistort, keep_stamps=args.keep_stamps)
    if args.kinect_recording:
        from services.detector.cameras.kinect_recording import KinectRecordingSource

        return KinectRecordingSource(args.kinect_recording, rate=args.rate, loop=args.loop,
                                     undistort=not args.no_undistort,
                                     keep_stamps=args.keep_stamps)
    return open_source("kinect" if args.kinect else f"folder:{args.folder}",
                       rate=args.rate, loop=args.loop, device_id=args.kinect_device,
                       depth_mode=args.depth_mode, fps=args.fps,
                       undistort=not args.no_undistort)


def main(args: argparse.Namespace) -> int:
    """``handkse camera``: 0 when the source ended or was stopped, 2 when it cannot open."""
    from services.common.bus import Bus, options_from_args, wait_for_services
    from services.common.config import section_from_args

    keys = Keys(args.rig)
    try:
        source = open_camera(args)
    except (SourceUnavailable, ValueError) as exc:
        print(f"handkse camera: {exc}", file=sys.stderr, flush=True)
        return 2
    stop = threading.Event()
    stop_on_signals(stop)
    save = None
    try:
        with Bus(options_from_args(args, section_from_args(args, "zenoh"))) as bus:
            if args.wait_for:
                wait_for_services(bus, keys, args.wait_for, args.wait_timeout)
            if args.save:
                first = getattr(source, "intrinsics", None)
                assert first is not None
                save = FolderWriter(args.save, first,
                                    getattr(source, "depth_scale_m", 0.001),
                                    getattr(source, "T_world_camera", None))
            print("camera ready", flush=True)
            n = run(bus, keys, source, stop, jpeg_quality=args.jpeg_quality,
                    depth_encoding=args.depth_encoding, max_frames=args.max_frames, save=save)
    finally:
        source.close()
        if save is not None:
            save.close()
    print(f"camera published {n} frames", flush=True)
    dropped = getattr(source, "dropped", None)
    if dropped:  # e.g. frames the SDK's syncer paired twice, captures with one image only
        log.info("camera skipped %s", ", ".join(f"{count} {why}" for why, count in dropped.items()))
    return 0


if __name__ == "__main__":
    from services.common.entry import run_service

    sys.exit(run_service("services.detector.camera", __doc__ or "", main, add_arguments))
