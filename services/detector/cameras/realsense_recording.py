"""RealSense recordings through ``pyrealsense2`` (optional extra ``realsense``).

``handkse camera --bag FILE`` plays ``.bag`` (ROS 1: the RealSense Viewer and SDKs before 2.59)
and ``.db3`` (rosbag2: SDK 2.59 and later) recordings with a colour and a depth stream, as
recorded (any colour format); frames come out exactly as from a live camera
(:class:`~services.detector.cameras.realsense.AlignedFrames`), with the recorded intrinsics,
depth units and distortion.

Every recorded frame is read and none dropped, whatever the reading pace: the playback runs not
in real time and each frame waits in the SDK until it is taken (a queue of a few frames). The
SDK's pipeline is not used for this: its frame syncer pairs colour with depth by waiting in real
time, which drops frames, and now and then stalls, when a recording is read at another pace than
it was recorded. Here the two streams are paired by their timestamps (within half a frame
period) and each pair goes through the SDK's depth-to-colour alignment like a live frameset.
The playback stays paused until both streams are started, so no first frame is lost.

Frames are re-stamped (:mod:`services.detector.cameras.clock`): the first gets the host time
when playback starts, later ones keep the recorded spacing (``keep_stamps``: the recorded
times); ``loop`` plays the file again and again with stamps going on; ``rate`` paces playback.
"""

from __future__ import annotations

import logging
import queue
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

from services.detector.cameras.clock import DeviceClock, Pacer
from services.detector.cameras.handle import HandleOwner, ReleaseOnce
from services.detector.cameras.realsense import AlignedFrames, import_pyrealsense2
from services.detector.sources import CapturedFrame, SourceUnavailable

log = logging.getLogger(__name__)

SUFFIXES = (".bag", ".db3")
T = TypeVar("T")


class FramePairer(Generic[T]):
    """Pairs a colour and a depth stream, each in time order, by their timestamps (ms).

    A colour and a depth frame pair up when their times differ by at most ``tolerance_ms``;
    a frame older than the other stream's oldest beyond that has no partner and is dropped
    (counted in ``unpaired``).
    """

    def __init__(self, tolerance_ms: float) -> None:
        self.tolerance_ms = tolerance_ms
        self._color: deque[tuple[float, T]] = deque()
        self._depth: deque[tuple[float, T]] = deque()
        self.unpaired = 0

    def add(self, is_color: bool, t_ms: float, item: T) -> None:
        (self._color if is_color else self._depth).append((t_ms, item))

    def take(self) -> list[tuple[T, T]]:
        """The (colour, depth) pairs complete so far, in time order."""
        pairs = []
        while self._color and self._depth:
            dt = self._color[0][0] - self._depth[0][0]
            if abs(dt) <= self.tolerance_ms:
                pairs.append((self._color.popleft()[1], self._depth.popleft()[1]))
            else:
                (self._depth if dt > 0 else self._color).popleft()
                self.unpaired += 1
        return pairs

    def clear(self) -> None:
        self._color.clear()
        self._depth.clear()


@dataclass
class _Pass:
    """One playback of the file: the SDK objects that must live while it plays."""

    context: Any
    playback: Any
    sensors: list[Any]
    color_profile: Any
    depth_scale_m: float


class RealSenseRecording(HandleOwner):
    """Frames of a RealSense recording (module docstring)."""

    def __init__(self, path: str | Path, *, rate: float = 1.0, loop: bool = False,
                 undistort: bool = True, keep_stamps: bool = False, timeout_s: float = 5.0,
                 option: str = "--bag") -> None:
        if rate < 0.0:
            raise ValueError(f"rate must be >= 0, got {rate}")
        self._rs = rs = import_pyrealsense2(option)
        self.path = Path(path)
        self._option = option
        if not self.path.is_file():
            raise SourceUnavailable(f"{option} {self.path}: no such file")
        if self.path.suffix.lower() not in SUFFIXES:
            raise SourceUnavailable(f"{option} {self.path}: expected a RealSense recording "
                                    "(.bag or .db3)")
        self.loop = loop
        self.realtime = rate > 0.0
        self._timeout_ms = round(timeout_s * 1000)
        self._incoming: queue.Queue[Any] = queue.Queue(maxsize=4)
        self._handle = ReleaseOnce(self._stop_pass)
        self._pass: _Pass | None = self._open_pass()
        try:
            self._frames = AlignedFrames(rs, str(self.path), self._pass.color_profile,
                                         self._pass.depth_scale_m, undistort=undistort,
                                         clock=DeviceClock(keep=keep_stamps, restart_s=0.0),
                                         recorded=True)
        except RuntimeError as exc:
            self._handle.close()
            raise SourceUnavailable(f"{option} {self.path}: cannot read the stream setup: "
                                    f"{exc}") from exc
        self.intrinsics = self._frames.intrinsics
        self.depth_scale_m = self._frames.depth_scale_m
        self.dropped = self._frames.dropped
        self._pairer: FramePairer[Any] = FramePairer(500.0 / self._pass.color_profile.fps())
        self._pacer = Pacer(rate, self._handle.closed)
        # the SDK aligns framesets only: a processing block makes one of each pair
        self._pair: list[Any] = []
        self._combiner = rs.processing_block(
            lambda _frame, source: source.frame_ready(source.allocate_composite_frame(self._pair)))
        self._combined = rs.frame_queue(2)
        self._combiner.start(self._combined)

    def _open_pass(self) -> _Pass:
        """Load the file paused, not in real time, with its colour and depth streams started."""
        rs = self._rs
        context = rs.context()
        try:
            device = context.load_device(str(self.path))
        except RuntimeError as exc:
            raise SourceUnavailable(f"{self._option} {self.path}: not a readable RealSense "
                                    f"recording ({exc})") from exc
        playback = device.as_playback()
        playback.set_real_time(False)
        playback.pause()
        wanted: dict[Any, list[Any]] = {}  # sensor -> its colour and/or depth profile
        found: dict[Any, Any] = {}  # stream type -> (sensor, profile)
        for sensor in device.query_sensors():
            for profile in sensor.get_stream_profiles():
                kind = profile.stream_type()
                if kind in (rs.stream.color, rs.stream.depth) and kind not in found:
                    found[kind] = (sensor, profile)
                    wanted.setdefault(sensor, []).append(profile)
        if len(found) < 2:
            streams = sorted({p.stream_type().name for s in device.query_sensors()
                              for p in s.get_stream_profiles()})
            raise SourceUnavailable(f"{self._option} {self.path}: needs a colour and a depth "
                                    f"stream, it has {', '.join(streams) or 'none'}")
        depth_sensor = found[rs.stream.depth][0]
        started = []
        try:
            depth_scale = depth_sensor.as_depth_sensor().get_depth_scale()
            for sensor, profiles in wanted.items():
                sensor.open(profiles)
                sensor.start(self._put)
                started.append(sensor)
        except RuntimeError as exc:
            for sensor in started:
                sensor.stop()
                sensor.close()
            raise SourceUnavailable(f"{self._option} {self.path}: cannot play its streams "
                                    f"({exc})") from exc
        return _Pass(context, playback, started, found[rs.stream.color][1], depth_scale)

    def _put(self, frame: Any) -> None:
        """SDK callback: hold the playback until the frame is queued (dropped once closed)."""
        while not self._handle.closed.is_set():
            try:
                self._incoming.put(frame, timeout=0.1)
                return
            except queue.Full:
                continue

    def _stop_pass(self) -> None:
        current, self._pass = self._pass, None
        if current is None:
            return
        for sensor in current.sensors:
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError as exc:  # already stopped by the end of the file
                log.debug("%s: stopping a sensor: %s", self.path, exc)
        while not self._incoming.empty():
            self._incoming.get_nowait()
        self._pairer.clear()

    def _ended(self) -> bool:
        assert self._pass is not None
        return bool(self._pass.playback.current_status() == self._rs.playback_status.stopped)

    def _frameset(self, color: Any, depth: Any) -> Any:
        self._pair[:] = [depth, color]
        try:
            self._combiner.invoke(depth)
            return self._combined.wait_for_frame(1000).as_frameset()
        finally:
            self._pair.clear()

    def __iter__(self) -> Iterator[CapturedFrame]:
        closed = self._handle.closed
        rs = self._rs
        with self._handle.reading():
            if self._pass is None:
                return
            self._pass.playback.resume()
            waited_ms, ended_checks, frames_this_pass = 0, 0, 0
            while not closed.is_set():
                try:
                    sdk_frame = self._incoming.get(timeout=0.2)
                except queue.Empty:
                    # ended: stopped, and nothing more arrived since (frames in flight)
                    ended_checks = ended_checks + 1 if self._ended() else 0
                    if ended_checks >= 2:
                        if not self.loop or frames_this_pass == 0:
                            return
                        self._stop_pass()
                        self._pass = self._open_pass()
                        self._pass.playback.resume()
                        waited_ms, ended_checks, frames_this_pass = 0, 0, 0
                        continue
                    waited_ms += 200
                    if waited_ms >= self._timeout_ms and not ended_checks:
                        raise SourceUnavailable(f"{self.path}: playback stalled, no frames "
                                                f"for {waited_ms / 1000:g} s") from None
                    continue
                waited_ms = ended_checks = 0
                is_color = sdk_frame.get_profile().stream_type() == rs.stream.color
                self._pairer.add(is_color, sdk_frame.get_timestamp(), sdk_frame)
                pairs = self._pairer.take()
                if self._pairer.unpaired:
                    self.dropped["unpaired"] = self._pairer.unpaired
                for color, depth in pairs:
                    try:
                        frame = self._frames.frame(self._frameset(color, depth))
                    except RuntimeError as exc:
                        self.dropped["bad_frame"] += 1
                        log.warning("%s: frame dropped: %s", self.path, exc)
                        continue
                    if frame is None:
                        continue
                    frames_this_pass += 1
                    if not self._pacer.wait(frame.stamp_ns):
                        return
                    yield frame


__all__ = ["SUFFIXES", "FramePairer", "RealSenseRecording"]
