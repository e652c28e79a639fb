"""Azure Kinect (and Orbbec Femto) recordings through ``pyk4a`` (optional extra ``kinect``).

``handkse camera --kinect-recording FILE.mkv`` plays a Matroska file written by ``k4arecorder``
(or the Orbbec K4A wrapper's recorder, or ``pyk4a.PyK4ARecord``) with colour and depth tracks:

- colour: MJPG (``k4arecorder``'s default; decoded with OpenCV), BGRA32, NV12 or YUY2, at the
  recorded resolution;
- depth: transformed into the colour camera by the SDK (``capture.transformed_depth``, from the
  calibration stored in the file), millimetres (``depth_scale_m`` 0.001), 0 = no reading;
- intrinsics: the stored factory calibration of the colour camera at the recorded resolution;
  its distortion (OpenCV's rational model) is removed from colour and depth alike by default.

Every capture is read (none dropped; captures with only one of the two images are skipped),
paced by ``rate`` and re-stamped like every recording (``services.detector.cameras.clock``):
the colour image's device time, anchored to the host clock at the first frame.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from services.detector.cameras.clock import DeviceClock, Pacer
from services.detector.cameras.convert import (
    bgr_from_color,
    captured_frame,
    intrinsics_from_matrix,
)
from services.detector.cameras.handle import HandleOwner, ReleaseOnce
from services.detector.cameras.lens import LensDistortion, Undistorter
from services.detector.sources import CapturedFrame, SourceUnavailable

log = logging.getLogger(__name__)

INSTALL = ("pip install 'handkse[kinect]', with Microsoft's libk4a 1.4 or Orbbec's K4A wrapper "
           "installed (docs/cameras.md)")

# k4a colour resolutions -> (width, height)
COLOR_SIZES = {"RES_720P": (1280, 720), "RES_1080P": (1920, 1080), "RES_1440P": (2560, 1440),
               "RES_1536P": (2048, 1536), "RES_2160P": (3840, 2160), "RES_3072P": (4096, 3072)}
COLOR_FORMATS = {"COLOR_MJPG": "mjpeg", "COLOR_BGRA32": "bgra8", "COLOR_NV12": "nv12",
                 "COLOR_YUY2": "yuyv"}


def import_pyk4a(option: str) -> Any:
    """The ``pyk4a`` module; :class:`SourceUnavailable` naming ``option`` and what to install."""
    try:
        import pyk4a
    except ModuleNotFoundError:
        raise SourceUnavailable(f"{option} needs pyk4a: {INSTALL}") from None
    except (ImportError, OSError) as exc:  # pyk4a present, libk4a.so missing
        raise SourceUnavailable(f"{option} needs pyk4a, which is installed but does not load "
                                f"({exc}): {INSTALL}") from exc
    return pyk4a


class KinectRecordingSource(HandleOwner):
    """Frames of an Azure Kinect / Orbbec Femto ``.mkv`` recording (module docstring)."""

    def __init__(self, path: str | Path, *, rate: float = 1.0, loop: bool = False,
                 undistort: bool = True, keep_stamps: bool = False,
                 option: str = "--kinect-recording") -> None:
        if rate < 0.0:
            raise ValueError(f"rate must be >= 0, got {rate}")
        pyk4a = import_pyk4a(option)
        self.path = Path(path)
        if not self.path.is_file():
            raise SourceUnavailable(f"{option} {self.path}: no such file")
        self._playback = pyk4a.PyK4APlayback(self.path)
        try:
            self._playback.open()
        except Exception as exc:  # pyk4a raises K4AException
            raise SourceUnavailable(f"{option} {self.path}: not a readable Azure "
                                    f"Kinect recording ({exc})") from exc
        self._handle = ReleaseOnce(self._playback.close)
        try:
            config = self._playback.configuration
            if not (config["color_track_enabled"] and config["depth_track_enabled"]):
                raise SourceUnavailable(f"{option} {self.path}: needs a colour and a "
                                        "depth track (recorded with colour and depth on)")
            resolution = config["color_resolution"].name
            color_format = config["color_format"].name
            if resolution not in COLOR_SIZES or color_format not in COLOR_FORMATS:
                raise SourceUnavailable(f"{option} {self.path}: colour "
                                        f"{resolution} {color_format} is not supported")
            # read before any capture: captures transform depth with the playback's calibration
            calibration = self._playback.calibration
            width, height = COLOR_SIZES[resolution]
            color_camera = pyk4a.CalibrationType.COLOR
            self.intrinsics = intrinsics_from_matrix(calibration.get_camera_matrix(color_camera),
                                                     width, height)
            self.distortion = LensDistortion("opencv", tuple(
                float(c) for c in calibration.get_distortion_coefficients(color_camera)))
        except SourceUnavailable:
            self._handle.close()
            raise
        except Exception as exc:  # K4AException from a damaged file
            self._handle.close()
            raise SourceUnavailable(f"{option} {self.path}: cannot read its "
                                    f"configuration and calibration ({exc})") from exc
        self._color_format = COLOR_FORMATS[color_format]
        self.depth_scale_m = 0.001
        self.loop = loop
        self.realtime = rate > 0.0
        self.dropped: Counter[str] = Counter()
        self._undistorter = Undistorter(self.intrinsics, self.distortion, enabled=undistort)
        self._clock = DeviceClock(keep=keep_stamps, restart_s=0.0)
        self._pacer = Pacer(rate, self._handle.closed)
        log.info("%s: colour %dx%d %s, lens distortion %s", self.path, width, height,
                 self._color_format, "removed" if self._undistorter.active else "none or kept")

    def __iter__(self) -> Iterator[CapturedFrame]:
        closed = self._handle.closed
        with self._handle.reading():
            frames_this_pass = 0
            while not closed.is_set():
                try:
                    capture = self._playback.get_next_capture()
                except EOFError:
                    if not self.loop or frames_this_pass == 0:
                        return
                    self._playback.seek(0)
                    frames_this_pass = 0
                    continue
                frame = self._frame(capture)
                if frame is None:
                    continue
                frames_this_pass += 1
                if not self._pacer.wait(frame.stamp_ns):
                    return
                yield frame

    def _frame(self, capture: Any) -> CapturedFrame | None:
        """The frame of a capture, or None (counted in ``dropped``)."""
        color, depth = capture.color, capture.transformed_depth
        if color is None or depth is None:
            self.dropped["incomplete"] += 1
            return None
        stamp = self._clock.stamp(int(capture.color_timestamp_usec) * 1000, "device")
        if stamp is None:
            self.dropped["stamp_not_increasing"] += 1
            return None
        try:
            bgr = bgr_from_color(color, self._color_format, self.intrinsics.width,
                                 self.intrinsics.height)
            return captured_frame(stamp_ns=stamp, color_bgr=bgr,
                                  depth=np.array(depth, np.uint16),
                                  depth_scale_m=self.depth_scale_m, intrinsics=self.intrinsics,
                                  undistorter=self._undistorter)
        except ValueError as exc:
            self.dropped["bad_frame"] += 1
            log.warning("%s: frame dropped: %s", self.path, exc)
            return None


__all__ = ["COLOR_FORMATS", "COLOR_SIZES", "INSTALL", "KinectRecordingSource", "import_pyk4a"]
