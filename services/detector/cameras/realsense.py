"""Intel RealSense cameras through ``pyrealsense2`` (optional extra ``realsense``).

:class:`RealSenseSource` streams a live camera (``handkse camera --realsense [--serial S]``;
D400 series: D415, D435(i), D455, D405, ...): colour as ``bgr8`` and depth as ``z16`` at one
frame rate, through the SDK's pipeline. Recordings are in
:mod:`services.detector.cameras.realsense_recording`; both share :class:`AlignedFrames`.

The SDK aligns depth to the colour camera (``rs.align``), so every depth pixel sits on the
colour pixel that sees the same point; the published intrinsics are the colour stream's
(``fx, fy, ppx, ppy``), its distortion is removed when the SDK reports the OpenCV-compatible
Brown-Conrady model with non-zero coefficients (D455, D405), and the depth scale (metres per
unit: 0.001 on most models, 0.0001 on the D405) comes from the device.

Frame times: the source turns the SDK's global time on, so colour frame times are host
wall-clock time (domain ``global_time``; ``system_time`` when the kernel gives no frame
metadata); a camera that reports ``hardware_clock`` is anchored to the host clock at its first
frame (:mod:`services.detector.cameras.clock`).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from typing import Any

import numpy as np

from services.common.protocol import CameraIntrinsics
from services.detector.cameras.clock import DeviceClock
from services.detector.cameras.convert import bgr_from_color, captured_frame, float32_value
from services.detector.cameras.handle import HandleOwner, ReleaseOnce
from services.detector.cameras.lens import LensDistortion, Undistorter
from services.detector.sources import CapturedFrame, SourceUnavailable

log = logging.getLogger(__name__)

INSTALL = "pip install 'handkse[realsense]'"


def import_pyrealsense2(option: str) -> Any:
    """The ``pyrealsense2`` module; :class:`SourceUnavailable` naming ``option`` and the extra."""
    try:
        import pyrealsense2
    except ModuleNotFoundError:
        raise SourceUnavailable(f"{option} needs pyrealsense2: {INSTALL}") from None
    except (ImportError, OSError) as exc:  # installed, but a shared library is missing
        hint = " (Debian/Ubuntu: apt install libusb-1.0-0)" if "libusb" in str(exc) else ""
        raise SourceUnavailable(f"{option} needs pyrealsense2, which is installed but does not "
                                f"load: {exc}{hint}") from exc
    return pyrealsense2


def lens_from_realsense(model: str, coeffs: Any) -> LensDistortion:
    """A RealSense distortion model name (``rs.distortion.X.name``) and its five coefficients."""
    values = tuple(float(c) for c in coeffs)
    if model == "brown_conrady":  # the unmodified model: OpenCV's, same coefficient order
        return LensDistortion("opencv", values)
    return LensDistortion(model, values)


def intrinsics_from_realsense(intr: Any) -> tuple[CameraIntrinsics, LensDistortion]:
    """Pinhole intrinsics and lens distortion of an ``rs.intrinsics`` (fields ``width, height,
    fx, fy, ppx, ppy, model, coeffs``; pixels, same convention as OpenCV)."""
    intrinsics = CameraIntrinsics(fx=float(intr.fx), fy=float(intr.fy), cx=float(intr.ppx),
                                  cy=float(intr.ppy), width=int(intr.width),
                                  height=int(intr.height))
    return intrinsics, lens_from_realsense(intr.model.name, intr.coeffs)


def clock_domain(timestamp_domain: str) -> str:
    """The :class:`DeviceClock` domain of a RealSense timestamp domain name."""
    return "host" if timestamp_domain in ("global_time", "system_time") else "device"


class AlignedFrames:
    """SDK framesets (colour + depth) to :class:`CapturedFrame`: depth aligned to colour by the
    SDK, colour to BGR, the lens distortion removed, the colour frame's time on the host clock.

    ``recorded``: times of a recording, always anchored (or kept) as device times; else the
    frame's own timestamp domain decides. Frames that cannot be used are counted in
    ``dropped`` by reason.
    """

    def __init__(self, rs: Any, name: str, color_profile: Any, depth_scale_m: float, *,
                 undistort: bool, clock: DeviceClock, recorded: bool) -> None:
        self.name = name
        self.intrinsics, self.distortion = intrinsics_from_realsense(
            color_profile.as_video_stream_profile().get_intrinsics())
        self.depth_scale_m = float32_value(depth_scale_m)
        self.dropped: Counter[str] = Counter()
        self._align = rs.align(rs.stream.color)
        self._undistorter = Undistorter(self.intrinsics, self.distortion, enabled=undistort)
        self._clock = clock
        self._recorded = recorded
        lens = ("none" if self.distortion.is_identity else
                f"{self.distortion.model} {'removed' if self._undistorter.active else 'kept'}")
        log.info("%s: colour %dx%d %s, depth scale %g m, lens distortion %s", name,
                 self.intrinsics.width, self.intrinsics.height, color_profile.format().name,
                 self.depth_scale_m, lens)

    def frame(self, frameset: Any) -> CapturedFrame | None:
        """The frame of an SDK frameset, or None (counted in ``dropped``)."""
        aligned = self._align.process(frameset)
        color, depth = aligned.get_color_frame(), aligned.get_depth_frame()
        if not color or not depth:
            self.dropped["incomplete"] += 1
            return None
        domain = ("device" if self._recorded
                  else clock_domain(color.get_frame_timestamp_domain().name))
        stamp = self._clock.stamp(round(color.get_timestamp() * 1e6), domain)
        if stamp is None:
            self.dropped["stamp_not_increasing"] += 1
            return None
        try:
            bgr = bgr_from_color(np.asanyarray(color.get_data()),
                                 color.get_profile().format().name, color.get_width(),
                                 color.get_height())
            return captured_frame(stamp_ns=stamp, color_bgr=bgr,
                                  depth=np.array(np.asanyarray(depth.get_data()), np.uint16),
                                  depth_scale_m=self.depth_scale_m, intrinsics=self.intrinsics,
                                  undistorter=self._undistorter)
        except ValueError as exc:
            self.dropped["bad_frame"] += 1
            log.warning("%s: frame dropped: %s", self.name, exc)
            return None


def _size(size: tuple[int, int]) -> str:
    return f"{size[0]}x{size[1]}"


class RealSenseSource(HandleOwner):
    """A live RealSense camera (module docstring); the first one found without ``serial``."""

    realtime = True

    def __init__(self, *, serial: str | None = None, color_size: tuple[int, int] = (1280, 720),
                 depth_size: tuple[int, int] = (848, 480), fps: int = 30, undistort: bool = True,
                 timeout_s: float = 5.0, option: str = "--realsense") -> None:
        rs = import_pyrealsense2(option)
        self.name = f"RealSense {self._serial(rs, serial, option)}"
        config = rs.config()
        if serial:
            config.enable_device(serial)
        config.enable_stream(rs.stream.color, color_size[0], color_size[1], rs.format.bgr8, fps)
        config.enable_stream(rs.stream.depth, depth_size[0], depth_size[1], rs.format.z16, fps)
        self._pipeline = rs.pipeline()
        try:
            profile = self._pipeline.start(config)
        except RuntimeError as exc:
            raise SourceUnavailable(
                f"{self.name}: cannot stream colour {_size(color_size)} and depth "
                f"{_size(depth_size)} at {fps} fps ({exc}; a USB 2 port carries less: try "
                "--fps 15 or smaller sizes)") from exc
        self._handle = ReleaseOnce(self._pipeline.stop)
        try:
            device = profile.get_device()
            for sensor in device.query_sensors():
                if sensor.supports(rs.option.global_time_enabled):
                    sensor.set_option(rs.option.global_time_enabled, 1.0)
            self._frames = AlignedFrames(rs, self.name, profile.get_stream(rs.stream.color),
                                         device.first_depth_sensor().get_depth_scale(),
                                         undistort=undistort, clock=DeviceClock(),
                                         recorded=False)
        except RuntimeError as exc:
            self._handle.close()
            raise SourceUnavailable(f"{self.name}: cannot read the stream setup: {exc}") from exc
        self.intrinsics = self._frames.intrinsics
        self.depth_scale_m = self._frames.depth_scale_m
        self.dropped = self._frames.dropped
        self._timeout_ms = round(timeout_s * 1000)

    @staticmethod
    def _serial(rs: Any, serial: str | None, option: str) -> str:
        serials = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
        if not serials:
            raise SourceUnavailable(f"{option}: no RealSense camera found (connected to a USB 3 "
                                    "port? used by another process? udev rules installed? "
                                    "see docs/cameras.md)")
        if serial and serial not in serials:
            raise SourceUnavailable(f"--serial {serial}: no RealSense with that serial number "
                                    f"(connected: {', '.join(serials)})")
        return serial or str(serials[0])

    def __iter__(self) -> Iterator[CapturedFrame]:
        closed = self._handle.closed
        waited_ms = 0
        with self._handle.reading():
            while not closed.is_set():
                ok, frames = self._pipeline.try_wait_for_frames(200)  # short: close() is seen
                if not ok:
                    waited_ms += 200
                    if waited_ms >= self._timeout_ms:
                        raise SourceUnavailable(f"{self.name}: no frames for "
                                                f"{waited_ms / 1000:g} s")
                    continue
                waited_ms = 0
                frame = self._frames.frame(frames)
                if frame is not None:
                    yield frame


__all__ = ["INSTALL", "AlignedFrames", "RealSenseSource", "clock_domain", "import_pyrealsense2",
           "intrinsics_from_realsense", "lens_from_realsense"]
