"""A stand-in for the part of ``pyk4a`` that plays recordings (a hardware fake).

``pyk4a`` needs Microsoft's libk4a, which cannot be installed here, so the Kinect recording
source is tested against this module instead: the same names, the same enum members, the same
behaviour where the source relies on it (``EOFError`` at the end, captures that transform depth
only once the playback's calibration has been read, MJPG colour as a 1-D byte buffer). Its
"recordings" are ``.npz`` files written by :func:`write_recording`; a real ``.mkv`` is not
read, so the real playback is untested here.

Put ``fake_sdk/`` on ``sys.path`` (or ``PYTHONPATH`` of a child process) to import it as
``pyk4a``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from enum import IntEnum
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

FAKE = True


class ImageFormat(IntEnum):
    COLOR_MJPG = 0
    COLOR_NV12 = 1
    COLOR_YUY2 = 2
    COLOR_BGRA32 = 3
    DEPTH16 = 4


class ColorResolution(IntEnum):
    OFF = 0
    RES_720P = 1
    RES_1080P = 2


class DepthMode(IntEnum):
    OFF = 0
    NFOV_UNBINNED = 2
    WFOV_2X2BINNED = 3


class CalibrationType(IntEnum):
    DEPTH = 0
    COLOR = 1


class K4AException(Exception):
    pass


class Calibration:
    def __init__(self, K: NDArray[np.float64], dist: NDArray[np.float64]) -> None:
        self._K, self._dist = K, dist

    def get_camera_matrix(self, camera: CalibrationType) -> NDArray[np.float64]:
        if camera != CalibrationType.COLOR:
            raise ValueError("the fake holds the colour camera only")
        return self._K.copy()

    def get_distortion_coefficients(self, camera: CalibrationType) -> NDArray[np.float64]:
        if camera != CalibrationType.COLOR:
            raise ValueError("the fake holds the colour camera only")
        return self._dist.copy()


class PyK4ACapture:
    def __init__(self, calibration: Calibration | None, color: NDArray[np.uint8] | None,
                 depth_in_color: NDArray[np.uint16] | None, color_timestamp_usec: int) -> None:
        self._calibration = calibration
        self.color = color
        self._depth = depth_in_color
        self.color_timestamp_usec = color_timestamp_usec

    @property
    def transformed_depth(self) -> NDArray[np.uint16] | None:
        if self._depth is None:
            return None
        if self._calibration is None:  # as pyk4a: the capture got the playback's None
            raise AttributeError("'NoneType' object has no attribute 'transformation_handle'")
        return self._depth


class PyK4APlayback:
    def __init__(self, path: str | Path, thread_safe: bool = True) -> None:
        self.path = Path(path)
        self._data: Any = None
        self._calibration: Calibration | None = None
        self._next = 0
        self.closed = False

    def open(self) -> None:
        try:
            self._data = dict(np.load(self.path, allow_pickle=False))
        except Exception as exc:
            raise K4AException(f"Cannot open file {self.path}") from exc

    @property
    def configuration(self) -> dict[str, Any]:
        meta = json.loads(str(self._data["meta"]))
        return {"color_format": ImageFormat[meta["color_format"]],
                "color_resolution": ColorResolution[meta["color_resolution"]],
                "depth_mode": DepthMode.WFOV_2X2BINNED, "color_track_enabled": meta["color"],
                "depth_track_enabled": meta["depth"]}

    @property
    def calibration(self) -> Calibration:
        if self._calibration is None:
            self._calibration = Calibration(self._data["K"], self._data["dist"])
        return self._calibration

    def get_next_capture(self) -> PyK4ACapture:
        times = self._data["t_usec"]
        if self._next >= len(times):
            raise EOFError
        i = self._next
        self._next += 1
        color = self._data.get(f"color_{i}")
        depth = self._data.get(f"depth_{i}")
        return PyK4ACapture(self._calibration, color, depth, int(times[i]))

    def seek(self, offset: int) -> None:
        if offset != 0:
            raise K4AException("the fake seeks to the start only")
        self._next = 0

    def close(self) -> None:
        if self.closed:
            raise K4AException("Playback not opened.")
        self.closed = True


def encode_color(bgr: NDArray[np.uint8], color_format: str) -> NDArray[np.uint8]:
    """A colour image as libk4a hands it out: MJPG a 1-D JPEG buffer, BGRA32 (h, w, 4), NV12
    (h * 3 / 2, w, 1), YUY2 (h, w, 2)."""
    from tests.detector.cameras.images import nv12_from_bgr, yuv422_from_bgr

    if color_format == "COLOR_NV12":
        return nv12_from_bgr(bgr)[:, :, None]
    if color_format == "COLOR_YUY2":
        return yuv422_from_bgr(bgr, "yuyv")
    if color_format == "COLOR_MJPG":
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
        assert ok
        return np.asarray(buf, np.uint8).reshape(-1)
    if color_format == "COLOR_BGRA32":
        return np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA), np.uint8)
    raise ValueError(f"the fake cannot write {color_format}")


def write_recording(path: Path, colors: Sequence[NDArray[np.uint8] | None],
                    depths: Sequence[NDArray[np.uint16] | None], times_usec: Sequence[int], *,
                    K: NDArray[np.float64], dist: Sequence[float] = (0.0,) * 8,
                    color_format: str = "COLOR_MJPG", color_resolution: str = "RES_720P",
                    color_track: bool = True, depth_track: bool = True) -> None:
    """A fake recording: per capture the colour buffer as libk4a gives it (or None) and the
    depth already in the colour camera (or None), device times in microseconds."""
    arrays: dict[str, Any] = {
        "meta": np.array(json.dumps({"color_format": color_format,
                                     "color_resolution": color_resolution,
                                     "color": color_track, "depth": depth_track})),
        "K": np.asarray(K, np.float64), "dist": np.asarray(dist, np.float64),
        "t_usec": np.asarray(times_usec, np.int64)}
    for i, (c, d) in enumerate(zip(colors, depths, strict=True)):
        if c is not None:
            arrays[f"color_{i}"] = c
        if d is not None:
            arrays[f"depth_{i}"] = d
    with open(path, "wb") as f:
        np.savez(f, **arrays)
