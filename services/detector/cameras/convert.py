"""Camera buffers to :class:`~services.detector.sources.CapturedFrame`, with no camera SDK.

What every SDK source shares: colour buffers in the camera's pixel format to BGR, the lens
distortion of the colour camera removed (:mod:`.lens`; ``RgbdFrame`` carries pinhole
intrinsics only), and the checks that colour, registered depth, intrinsics and depth scale
agree.

Depth stays in the camera's raw units (uint16, 0 = no reading) with its scale in metres per
unit: 1000 units at ``depth_scale_m`` 0.001 (RealSense D435/D455, Azure Kinect) is 1.0 m, as is
10000 units at 0.0001 (RealSense D405).
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.common.protocol import CameraIntrinsics
from services.detector.cameras.lens import Undistorter
from services.detector.sources import CapturedFrame

log = logging.getLogger(__name__)

# pixel format -> bytes per pixel of a packed buffer (nv12 and mjpeg are handled apart)
_PACKED = {"bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4, "yuyv": 2, "uyvy": 2}
_TO_BGR = {"rgb8": cv2.COLOR_RGB2BGR, "bgra8": cv2.COLOR_BGRA2BGR, "rgba8": cv2.COLOR_RGBA2BGR,
           "yuyv": cv2.COLOR_YUV2BGR_YUYV, "uyvy": cv2.COLOR_YUV2BGR_UYVY,
           "nv12": cv2.COLOR_YUV2BGR_NV12}
COLOR_FORMATS = (*_PACKED, "nv12", "mjpeg")


def bgr_from_color(data: ArrayLike, color_format: str, width: int, height: int
                   ) -> NDArray[np.uint8]:
    """A new (height, width, 3) uint8 BGR image from a colour buffer.

    ``color_format`` (one of :data:`COLOR_FORMATS`): ``bgr8``/``rgb8``/``bgra8``/``rgba8``
    packed 8-bit channels; ``yuyv`` (YUY2) and ``uyvy`` 4:2:2; ``nv12`` 4:2:0 (a Y plane then
    interleaved UV, ``height * 3 / 2`` rows); ``mjpeg`` one JPEG. ``data`` is any array or
    buffer of those bytes, in any shape. ``ValueError`` names a wrong size or format, or a JPEG
    that does not decode.
    """
    buf = np.ascontiguousarray(data, np.uint8).reshape(-1)
    if color_format == "mjpeg":
        decoded = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        if decoded is None:
            raise ValueError("MJPEG colour frame does not decode")
        out = np.asarray(decoded, np.uint8)
    elif color_format == "nv12" or color_format in _PACKED:
        if color_format == "nv12":
            if width % 2 or height % 2:
                raise ValueError(f"nv12 needs an even width and height, got {width}x{height}")
            shape: tuple[int, ...] = (height * 3 // 2, width)
        else:
            shape = (height, width, _PACKED[color_format])
        need = math.prod(shape)
        if buf.size != need:
            raise ValueError(f"{color_format} colour frame has {buf.size} bytes, "
                             f"{width}x{height} needs {need}")
        image = buf.reshape(shape)
        out = (image.copy() if color_format == "bgr8"
               else np.asarray(cv2.cvtColor(image, _TO_BGR[color_format]), np.uint8))
    else:
        raise ValueError(f"colour format {color_format!r} is not supported "
                         f"(supported: {', '.join(COLOR_FORMATS)})")
    if out.shape != (height, width, 3):
        raise ValueError(f"{color_format} colour frame is {out.shape[1]}x{out.shape[0]}, "
                         f"expected {width}x{height}")
    return out


def intrinsics_from_matrix(K: ArrayLike, width: int, height: int) -> CameraIntrinsics:
    """Pinhole intrinsics from a 3x3 camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``
    (pixels; OpenCV's convention: the centre of the top-left pixel is (0, 0))."""
    M = np.asarray(K, np.float64)
    if M.shape != (3, 3):
        raise ValueError(f"camera matrix must be 3x3, got shape {M.shape}")
    return CameraIntrinsics(fx=float(M[0, 0]), fy=float(M[1, 1]), cx=float(M[0, 2]),
                            cy=float(M[1, 2]), width=int(width), height=int(height))


def captured_frame(*, stamp_ns: int, color_bgr: NDArray[np.uint8], depth: NDArray[np.uint16],
                   depth_scale_m: float, intrinsics: CameraIntrinsics,
                   undistorter: Undistorter | None = None) -> CapturedFrame:
    """One frame from arrays, checked: (H, W, 3) uint8 BGR colour whose size the intrinsics
    give, (H, W) uint16 depth registered to it (raw units, 0 = no reading), a positive depth
    scale in metres per unit, a stamp in host wall-clock ns. ``ValueError`` names what
    disagrees."""
    if color_bgr.dtype != np.uint8 or color_bgr.ndim != 3 or color_bgr.shape[2] != 3:
        raise ValueError(f"colour must be (H, W, 3) uint8, got {color_bgr.shape} "
                         f"{color_bgr.dtype}")
    h, w = color_bgr.shape[:2]
    if (w, h) != (intrinsics.width, intrinsics.height):
        raise ValueError(f"colour image is {w}x{h}, intrinsics say "
                         f"{intrinsics.width}x{intrinsics.height}")
    if depth.dtype != np.uint16 or depth.shape != (h, w):
        raise ValueError(f"depth must be ({h}, {w}) uint16 registered to the colour image, got "
                         f"{depth.shape} {depth.dtype}")
    if not (math.isfinite(depth_scale_m) and depth_scale_m > 0.0):
        raise ValueError(f"depth scale must be a positive number of metres, got {depth_scale_m}")
    if undistorter is not None:
        color_bgr, depth = undistorter.apply(color_bgr, depth)
    return CapturedFrame(stamp_ns=int(stamp_ns), color_bgr=color_bgr, depth=depth,
                         depth_scale_m=float(depth_scale_m), intrinsics=intrinsics)


def float32_value(x: float) -> float:
    """The decimal an SDK meant by a float32 value (0.0010000000474974513 -> 0.001)."""
    return float(str(np.float32(x)))


__all__ = ["COLOR_FORMATS", "bgr_from_color", "captured_frame", "float32_value",
           "intrinsics_from_matrix"]
