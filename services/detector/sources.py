"""RGB-D frame sources (Azure Kinect, a folder) and the RgbdFrame image codec.

RealSense cameras and recordings (RealSense ``.bag``/``.db3``, Azure Kinect ``.mkv``) are in
:mod:`services.detector.cameras`; :func:`services.detector.source_factory.open_source` opens
any of them.

A source yields :class:`CapturedFrame` (BGR colour, raw 16-bit depth registered to the colour
image, intrinsics of the colour camera) and is closed after use (``with``). Sources:

- :class:`FolderSource`, a folder written by :class:`FolderWriter` (or by hand)::

      DIR/intrinsics.json   {"fx", "fy", "cx", "cy", "width", "height", "depth_scale_m",
                             optional "T_world_camera": 4x4 nested list}
      DIR/color/NNNNNN.jpg  colour (.jpg/.jpeg/.png; sorted by name)
      DIR/depth/NNNNNN.png  16-bit depth registered to the colour image, same stem; 0 = none
      DIR/timestamps.txt    optional: one capture time in ns per frame, in name order
                            (without it frames are 1/fps apart)

  ``rate`` 1 replays at the recorded pace, 0 as fast as the consumer takes frames; ``loop``
  starts again with stamps shifted past the last one, so they keep increasing.
- :class:`KinectSource`, an Azure Kinect through ``pyk4a`` (optional extra ``kinect``; needs
  Microsoft's Azure Kinect Sensor SDK, ``libk4a``): 1280x720 colour, depth transformed into
  the colour camera (WFOV 2x2-binned by default, 0.25-2.88 m, which covers the paper's 0.4-1.0 m),
  factory intrinsics of the colour camera; the colour and depth images are undistorted with the
  factory distortion model by default, so the pinhole intrinsics hold.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from services.common.protocol import (
    CameraIntrinsics,
    ColorImage,
    DepthImage,
    ProtocolError,
    RgbdFrame,
)
from services.detector.cameras.lens import LensDistortion, Undistorter

log = logging.getLogger(__name__)

COLOR_SUFFIXES = (".jpg", ".jpeg", ".png")


class SourceUnavailable(RuntimeError):
    """A frame source cannot be opened; the message says what to install or fix."""


@dataclass(frozen=True)
class CapturedFrame:
    """One RGB-D frame as arrays."""

    stamp_ns: int
    color_bgr: NDArray[np.uint8]  # (H, W, 3)
    depth: NDArray[np.uint16]  # (H_d, W_d) registered to the colour image, 0 = no reading
    depth_scale_m: float  # metres per depth unit
    intrinsics: CameraIntrinsics  # of the colour image
    T_world_camera: NDArray[np.float64] | None = None


class FrameSource(Protocol):
    """An iterable of frames that is closed after use.

    ``realtime``: frames arrive at the sensor's pace whether or not they are taken (a consumer
    that falls behind should skip to the newest); False: every frame waits for its consumer.
    """

    realtime: bool

    def __iter__(self) -> Iterator[CapturedFrame]: ...

    def close(self) -> None: ...


# --------------------------------------------------------------------------------------------
# RgbdFrame <-> arrays


def encode_frame(frame: CapturedFrame, seq: int = 0, *, color_encoding: str = "jpeg",
                 jpeg_quality: int = 90, depth_encoding: str = "u16",
                 png_compression: int = 1) -> RgbdFrame:
    """The wire message of a frame: JPEG (or PNG / raw) colour, raw 16-bit (or PNG16) depth.

    Raw depth is the default: 1.8 MB per 1280x720 frame (55 MB/s at 30 fps, fine on loopback
    and gigabit), against ~25-50 ms to encode and ~15 ms to decode PNG16 of a noisy ToF depth
    image on one CPU core; choose ``png16`` on a slow link.
    """
    h, w = frame.color_bgr.shape[:2]
    if color_encoding == "bgr8":
        color = np.ascontiguousarray(frame.color_bgr, np.uint8).tobytes()
    elif color_encoding in ("jpeg", "png"):
        params = ([cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if color_encoding == "jpeg"
                  else [cv2.IMWRITE_PNG_COMPRESSION, png_compression])
        ok, buf = cv2.imencode(".jpg" if color_encoding == "jpeg" else ".png", frame.color_bgr,
                               params)
        if not ok:
            raise ValueError(f"{color_encoding} encoding of the colour image failed")
        color = buf.tobytes()
    else:
        raise ValueError(f"unknown colour encoding {color_encoding!r}")
    depth16 = np.ascontiguousarray(frame.depth, np.uint16)
    dh, dw = depth16.shape
    if depth_encoding == "u16":
        depth = depth16.astype("<u2", copy=False).tobytes()
    elif depth_encoding == "png16":
        ok, buf = cv2.imencode(".png", depth16, [cv2.IMWRITE_PNG_COMPRESSION, png_compression])
        if not ok:
            raise ValueError("PNG encoding of the depth image failed")
        depth = buf.tobytes()
    else:
        raise ValueError(f"unknown depth encoding {depth_encoding!r}")
    T = None if frame.T_world_camera is None else np.asarray(frame.T_world_camera, "<f8")
    return RgbdFrame(seq=seq, stamp_ns=int(frame.stamp_ns), frame_id="camera",
                     color=ColorImage(encoding=color_encoding, width=w, height=h, data=color),
                     depth=DepthImage(encoding=depth_encoding, width=dw, height=dh,
                                      scale_m=float(frame.depth_scale_m), data=depth),
                     intrinsics=frame.intrinsics, T_world_camera=T)


def decode_color(image: ColorImage) -> NDArray[np.uint8]:
    """(H, W, 3) BGR; :class:`ProtocolError` (reason ``bad_image``) when it does not decode to
    the announced size."""
    if image.encoding == "bgr8":
        return np.frombuffer(image.data, np.uint8).reshape(image.height, image.width, 3)
    out = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
    if out is None:
        raise ProtocolError(f"RgbdFrame.color: {image.encoding} data does not decode",
                            "bad_image")
    if out.shape[:2] != (image.height, image.width):
        raise ProtocolError(f"RgbdFrame.color: decodes to {out.shape[1]}x{out.shape[0]}, "
                            f"announced {image.width}x{image.height}", "bad_image")
    return np.asarray(out, np.uint8)


def decode_depth(image: DepthImage) -> NDArray[np.uint16]:
    """(H, W) uint16 raw depth; :class:`ProtocolError` (``bad_image``) when malformed."""
    if image.encoding == "u16":
        return np.frombuffer(image.data, "<u2").reshape(image.height, image.width)
    out = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if out is None or out.dtype != np.uint16 or out.ndim != 2:
        raise ProtocolError("RgbdFrame.depth: png16 data is not a 16-bit single-channel PNG",
                            "bad_image")
    if out.shape != (image.height, image.width):
        raise ProtocolError(f"RgbdFrame.depth: decodes to {out.shape[1]}x{out.shape[0]}, "
                            f"announced {image.width}x{image.height}", "bad_image")
    return np.asarray(out, np.uint16)


def decode_frame(message: RgbdFrame) -> CapturedFrame:
    """Arrays of a received frame (raises :class:`ProtocolError` for undecodable images)."""
    color = decode_color(message.color)
    if (message.intrinsics.width, message.intrinsics.height) != (message.color.width,
                                                                 message.color.height):
        raise ProtocolError("RgbdFrame.intrinsics: size differs from the colour image's",
                            "bad_field")
    return CapturedFrame(stamp_ns=message.stamp_ns, color_bgr=color,
                         depth=decode_depth(message.depth), depth_scale_m=message.depth.scale_m,
                         intrinsics=message.intrinsics, T_world_camera=message.T_world_camera)


# --------------------------------------------------------------------------------------------
# Folder


def _intrinsics_from_json(doc: dict[str, Any], where: Path) -> CameraIntrinsics:
    try:
        return CameraIntrinsics(fx=float(doc["fx"]), fy=float(doc["fy"]), cx=float(doc["cx"]),
                                cy=float(doc["cy"]), width=int(doc["width"]),
                                height=int(doc["height"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise SourceUnavailable(f"{where}: needs fx, fy, cx, cy, width, height ({exc})") from exc


class FolderSource:
    """Frames from a folder (layout in the module docstring)."""

    def __init__(self, path: str | Path, rate: float = 1.0, loop: bool = False,
                 fps: float = 30.0) -> None:
        self.path = Path(path)
        meta_path = self.path / "intrinsics.json"
        try:
            meta = json.loads(meta_path.read_text())
        except FileNotFoundError:
            raise SourceUnavailable(f"{meta_path} is missing (frame folder layout: "
                                    "intrinsics.json, color/, depth/, timestamps.txt)") from None
        except json.JSONDecodeError as exc:
            raise SourceUnavailable(f"{meta_path} is not valid JSON: {exc}") from exc
        self.intrinsics = _intrinsics_from_json(meta, meta_path)
        self.depth_scale_m = float(meta.get("depth_scale_m", 0.001))
        T = meta.get("T_world_camera")
        self.T_world_camera = None if T is None else np.asarray(T, np.float64).reshape(4, 4)
        colors = sorted(p for p in (self.path / "color").glob("*")
                        if p.suffix.lower() in COLOR_SUFFIXES)
        if not colors:
            raise SourceUnavailable(f"{self.path / 'color'} has no .jpg/.png images")
        self.frames: list[tuple[Path, Path]] = []
        for c in colors:
            d = self.path / "depth" / f"{c.stem}.png"
            if not d.is_file():
                raise SourceUnavailable(f"{d} is missing (depth for {c.name})")
            self.frames.append((c, d))
        stamps_path = self.path / "timestamps.txt"
        if stamps_path.is_file():
            lines = [ln.split()[0] for ln in stamps_path.read_text().splitlines() if ln.strip()]
            if len(lines) != len(self.frames):
                raise SourceUnavailable(f"{stamps_path} has {len(lines)} stamps for "
                                        f"{len(self.frames)} frames")
            self.stamps_ns = [int(s) for s in lines]
        else:
            self.stamps_ns = [round(i * 1e9 / fps) for i in range(len(self.frames))]
        if any(b <= a for a, b in zip(self.stamps_ns, self.stamps_ns[1:], strict=False)):
            raise SourceUnavailable(f"{stamps_path}: stamps must increase")
        self.rate = rate
        self.loop = loop
        self.realtime = rate > 0.0
        self._closed = threading.Event()

    def __len__(self) -> int:
        return len(self.frames)

    def read(self, i: int, stamp_offset_ns: int = 0) -> CapturedFrame:
        color_path, depth_path = self.frames[i]
        color = cv2.imread(str(color_path), cv2.IMREAD_COLOR)
        depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
        if color is None or depth is None:
            raise SourceUnavailable(f"cannot read {color_path.name} / {depth_path.name}")
        if depth.dtype != np.uint16 or depth.ndim != 2:
            raise SourceUnavailable(f"{depth_path} must be a 16-bit single-channel PNG")
        if color.shape[:2] != (self.intrinsics.height, self.intrinsics.width):
            raise SourceUnavailable(f"{color_path} is {color.shape[1]}x{color.shape[0]}, "
                                    f"intrinsics say {self.intrinsics.width}x"
                                    f"{self.intrinsics.height}")
        return CapturedFrame(stamp_ns=self.stamps_ns[i] + stamp_offset_ns,
                             color_bgr=np.asarray(color, np.uint8),
                             depth=np.asarray(depth, np.uint16), depth_scale_m=self.depth_scale_m,
                             intrinsics=self.intrinsics, T_world_camera=self.T_world_camera)

    def __iter__(self) -> Iterator[CapturedFrame]:
        n = len(self.frames)
        span = self.stamps_ns[-1] - self.stamps_ns[0]
        period = span // max(n - 1, 1) if n > 1 else round(1e9 / 30)
        offset = 0
        start_wall = time.monotonic()
        first = self.stamps_ns[0]
        while not self._closed.is_set():
            for i in range(n):
                if self._closed.is_set():
                    return
                if self.rate > 0.0:
                    due = start_wall + (self.stamps_ns[i] + offset - first) / 1e9 / self.rate
                    delay = due - time.monotonic()
                    if delay > 0 and self._closed.wait(delay):
                        return
                yield self.read(i, offset)
            if not self.loop:
                return
            offset += span + period

    def close(self) -> None:
        self._closed.set()

    def __enter__(self) -> FolderSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FolderWriter:
    """Writes frames in the folder layout :class:`FolderSource` reads."""

    def __init__(self, path: str | Path, intrinsics: CameraIntrinsics, depth_scale_m: float,
                 T_world_camera: NDArray[Any] | None = None, jpeg_quality: int = 95) -> None:
        self.path = Path(path)
        (self.path / "color").mkdir(parents=True, exist_ok=True)
        (self.path / "depth").mkdir(parents=True, exist_ok=True)
        meta: dict[str, Any] = {**intrinsics.to_dict(), "depth_scale_m": depth_scale_m}
        if T_world_camera is not None:
            meta["T_world_camera"] = np.asarray(T_world_camera, float).tolist()
        (self.path / "intrinsics.json").write_text(json.dumps(meta, indent=2) + "\n")
        self.jpeg_quality = jpeg_quality
        self.count = 0
        self._stamps = open(self.path / "timestamps.txt", "w")  # noqa: SIM115 - closed in close()

    def write(self, frame: CapturedFrame) -> None:
        name = f"{self.count:06d}"
        cv2.imwrite(str(self.path / "color" / f"{name}.jpg"), frame.color_bgr,
                    [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        cv2.imwrite(str(self.path / "depth" / f"{name}.png"), np.asarray(frame.depth, np.uint16))
        self._stamps.write(f"{int(frame.stamp_ns)}\n")
        self._stamps.flush()
        self.count += 1

    def close(self) -> None:
        self._stamps.close()

    def __enter__(self) -> FolderWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------------------------
# Azure Kinect

KINECT_HINT = ("the Azure Kinect source needs the optional extra `kinect` (pip install "
               "'handkse[kinect]', i.e. pyk4a) and Microsoft's Azure Kinect Sensor SDK library "
               "libk4a 1.4 (Debian/Ubuntu: libk4a1.4 and libk4a1.4-dev from "
               "packages.microsoft.com; see https://github.com/microsoft/Azure-Kinect-Sensor-SDK)")


def _import_pyk4a() -> Any:
    try:
        import pyk4a
    except (ImportError, OSError) as exc:  # OSError: pyk4a present but libk4a.so missing
        raise SourceUnavailable(f"{KINECT_HINT} ({exc})") from exc
    return pyk4a


class KinectSource:
    """Azure Kinect frames through pyk4a (imported when the source is opened)."""

    realtime = True
    DEPTH_MODES = ("wfov_binned", "nfov_unbinned", "nfov_binned", "wfov_unbinned")

    def __init__(self, device_id: int = 0, depth_mode: str = "wfov_binned", fps: int = 30,
                 undistort: bool = True, timeout_s: float = 2.0) -> None:
        if depth_mode not in self.DEPTH_MODES:
            raise ValueError(f"depth_mode must be one of {self.DEPTH_MODES}, got {depth_mode!r}")
        if fps not in (5, 15, 30):
            raise ValueError(f"Azure Kinect fps must be 5, 15 or 30, got {fps}")
        pyk4a = _import_pyk4a()
        modes = {"wfov_binned": pyk4a.DepthMode.WFOV_2X2BINNED,
                 "wfov_unbinned": pyk4a.DepthMode.WFOV_UNBINNED,
                 "nfov_binned": pyk4a.DepthMode.NFOV_2X2BINNED,
                 "nfov_unbinned": pyk4a.DepthMode.NFOV_UNBINNED}
        config = pyk4a.Config(color_resolution=pyk4a.ColorResolution.RES_720P,
                              color_format=pyk4a.ImageFormat.COLOR_BGRA32,
                              depth_mode=modes[depth_mode],
                              camera_fps={5: pyk4a.FPS.FPS_5, 15: pyk4a.FPS.FPS_15,
                                          30: pyk4a.FPS.FPS_30}[fps],
                              synchronized_images_only=True)
        self._k4a = pyk4a.PyK4A(config=config, device_id=device_id)
        try:
            self._k4a.start()
        except Exception as exc:  # pyk4a raises K4AException subclasses
            raise SourceUnavailable(f"cannot open Azure Kinect {device_id}: {exc} (is it "
                                    "connected, powered and not used by another process?)"
                                    ) from exc
        calibration = self._k4a.calibration
        K = np.asarray(calibration.get_camera_matrix(pyk4a.CalibrationType.COLOR), float)
        dist = np.asarray(calibration.get_distortion_coefficients(pyk4a.CalibrationType.COLOR),
                          float)
        self.intrinsics = CameraIntrinsics(fx=float(K[0, 0]), fy=float(K[1, 1]),
                                           cx=float(K[0, 2]), cy=float(K[1, 2]),
                                           width=1280, height=720)
        # keeps K: the published intrinsics describe the undistorted image
        self._undistorter = Undistorter(self.intrinsics,
                                        LensDistortion("opencv", tuple(float(c) for c in dist)),
                                        enabled=undistort)
        self._timeout_ms = int(timeout_s * 1000)
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._iterating = False
        self._stopped = False

    def __iter__(self) -> Iterator[CapturedFrame]:
        origin: tuple[int, int] | None = None  # (device us, wall ns) of the first frame
        with self._lock:
            self._iterating = True
        try:
            while not self._closed.is_set():
                capture = self._k4a.get_capture(timeout=self._timeout_ms)
                color, depth = capture.color, capture.transformed_depth
                if color is None or depth is None:
                    continue
                device_us = int(capture.color_timestamp_usec)
                if origin is None:
                    origin = (device_us, time.time_ns())
                # the device clock is steady; anchor it to the wall clock once
                stamp = origin[1] + (device_us - origin[0]) * 1000
                bgr, depth = self._undistorter.apply(np.ascontiguousarray(color[:, :, :3]),
                                                     np.asarray(depth, np.uint16))
                yield CapturedFrame(stamp_ns=stamp, color_bgr=bgr, depth=depth,
                                    depth_scale_m=0.001, intrinsics=self.intrinsics)
        finally:
            with self._lock:
                self._iterating = False
            self._stop_device()

    def _stop_device(self) -> None:
        with self._lock:
            if self._stopped or self._iterating:
                return
            self._stopped = True
        self._k4a.stop()

    def close(self) -> None:
        """Stop: at once when idle, else when the running iteration sees the flag (<= timeout)."""
        self._closed.set()
        self._stop_device()

    def __enter__(self) -> KinectSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["KINECT_HINT", "CapturedFrame", "FolderSource", "FolderWriter", "FrameSource",
           "KinectSource", "SourceUnavailable", "decode_color", "decode_depth", "decode_frame",
           "encode_frame"]
