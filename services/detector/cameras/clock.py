"""Camera frame times to host wall-clock nanoseconds, and playback at the recorded pace.

Every source stamps frames on the host's wall clock (``time.time_ns``, ns since the Unix epoch),
the clock the rest of the pipeline compares ages against. Cameras give frame times in one of two
kinds of clock (``domain``):

- ``"host"``: already host wall-clock time. RealSense ``global_time`` (the SDK converts the
  camera's hardware clock to host time with a continuously estimated offset and drift) and
  ``system_time`` (host time when the frame arrived). Used as they are.
- ``"device"``: a free-running clock with its own origin: RealSense ``hardware_clock``, Azure
  Kinect device time, and every recording. Anchored once, at the first frame:
  ``stamp = host_ns(first frame) + (device_ns - device_ns(first frame))``. Anchoring once keeps
  the device's even frame spacing (no host scheduling jitter); the drift of the camera's
  oscillator against the host (tens of ppm, a few ms per minute) is not corrected.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

DOMAINS = ("host", "device")


class DeviceClock:
    """Maps frame times onto the host wall clock; stamps strictly increase.

    ``keep``: use the device times as they are (a recording's own times), only kept increasing.
    A ``"host"`` time more than ``max_host_offset_s`` from the host clock at the first frame is
    not trusted and is anchored like a device time (a warning says so).

    A frame whose stamp would not increase is refused (:meth:`stamp` returns None, counted in
    ``refused``): a frame paired twice by the SDK's frame syncer, a small backward correction of
    global time. A step back by more than ``restart_s`` (a looped recording, a device clock
    reset) re-anchors, so stamps go on one frame period after the last (counted in ``restarts``).
    """

    def __init__(self, *, keep: bool = False, max_host_offset_s: float = 10.0,
                 restart_s: float = 1.0, now_ns: Callable[[], int] = time.time_ns) -> None:
        self.keep = keep
        self.max_host_offset_ns = round(max_host_offset_s * 1e9)
        self.restart_ns = round(restart_s * 1e9)
        self._now_ns = now_ns
        self._offset_ns: int | None = None  # host ns minus device ns
        self._last_ns: int | None = None
        self._period_ns = 33_333_333  # until two frames have been seen
        self.refused = 0
        self.restarts = 0

    def _first_offset(self, device_ns: int, domain: str) -> int:
        if self.keep:
            return 0
        now = self._now_ns()
        if domain == "host":
            if abs(now - device_ns) <= self.max_host_offset_ns:
                return 0
            log.warning("camera frame time is %.1f s off the host clock; anchoring it at the "
                        "first frame instead", (device_ns - now) / 1e9)
        return now - device_ns

    def stamp(self, device_ns: int, domain: str) -> int | None:
        """Host wall-clock ns of a frame taken at ``device_ns`` in ``domain``, or None."""
        if domain not in DOMAINS:
            raise ValueError(f"clock domain must be one of {DOMAINS}, got {domain!r}")
        if self._offset_ns is None:
            self._offset_ns = self._first_offset(int(device_ns), domain)
        stamp = int(device_ns) + self._offset_ns
        last = self._last_ns
        if last is not None and stamp <= last:
            if last - stamp <= self.restart_ns:
                self.refused += 1
                return None
            self._offset_ns += last + self._period_ns - stamp
            stamp = last + self._period_ns
            self.restarts += 1
        elif last is not None:
            self._period_ns = stamp - last
        self._last_ns = stamp
        return stamp


class Pacer:
    """Holds frames back so they leave at ``rate`` times the pace of their stamps.

    ``rate`` 1: the recorded pace, 0.5: half speed, 0: no waiting (every frame as fast as the
    consumer takes it). The first frame leaves at once.
    """

    def __init__(self, rate: float, closed: threading.Event,
                 now_s: Callable[[], float] = time.monotonic) -> None:
        if rate < 0.0:
            raise ValueError(f"rate must be >= 0, got {rate}")
        self.rate = rate
        self._closed = closed
        self._now_s = now_s
        self._origin: tuple[float, int] | None = None  # (monotonic s, stamp ns) of the first

    def wait(self, stamp_ns: int) -> bool:
        """Wait until the frame stamped ``stamp_ns`` is due; False when closed meanwhile."""
        if self.rate > 0.0:
            if self._origin is None:
                self._origin = (self._now_s(), stamp_ns)
            due = self._origin[0] + (stamp_ns - self._origin[1]) / 1e9 / self.rate
            delay = due - self._now_s()
            if delay > 0.0 and self._closed.wait(delay):
                return False
        return not self._closed.is_set()


__all__ = ["DOMAINS", "DeviceClock", "Pacer"]
