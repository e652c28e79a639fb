"""Device frame times to host wall-clock ns, and the playback pacer."""

from __future__ import annotations

import itertools
import logging
import threading

import numpy as np
import pytest

from services.detector.cameras.clock import DeviceClock, Pacer

HOST_NOW = 1_754_000_000_000_000_000  # the fake host clock, ns since the epoch


def fixed_clock(**kwargs: object) -> DeviceClock:
    return DeviceClock(now_ns=lambda: HOST_NOW, **kwargs)  # type: ignore[arg-type]


def test_host_domain_times_are_used_as_they_are() -> None:
    clock = fixed_clock()
    first = HOST_NOW - 40_000_000  # a global-time stamp 40 ms old when it arrives
    assert clock.stamp(first, "host") == first
    assert clock.stamp(first + 33_333_333, "host") == first + 33_333_333


def test_device_times_are_anchored_at_the_first_frame() -> None:
    clock = fixed_clock()
    device = [5_000_000, 38_333_000, 71_667_000]  # a camera clock from power-on
    assert [clock.stamp(t, "device") for t in device] == [
        HOST_NOW, HOST_NOW + 33_333_000, HOST_NOW + 66_667_000]


def test_host_times_far_off_the_host_clock_are_anchored(
        caplog: pytest.LogCaptureFixture) -> None:
    clock = fixed_clock()
    recorded = HOST_NOW - 86_400 * 10**9  # a day old
    with caplog.at_level(logging.WARNING):
        assert clock.stamp(recorded, "host") == HOST_NOW
    assert "off the host clock" in caplog.text
    assert clock.stamp(recorded + 10**6, "host") == HOST_NOW + 10**6


def test_kept_stamps_stay_as_recorded() -> None:
    clock = fixed_clock(keep=True)
    assert [clock.stamp(t, "device") for t in (1_000_000_000, 1_033_300_000)] == [
        1_000_000_000, 1_033_300_000]


def test_repeats_and_small_steps_back_are_refused() -> None:
    clock = fixed_clock()
    assert clock.stamp(HOST_NOW, "host") == HOST_NOW
    assert clock.stamp(HOST_NOW, "host") is None  # the same frame paired twice
    assert clock.stamp(HOST_NOW - 200_000, "host") is None  # a global-time correction
    assert clock.stamp(HOST_NOW + 33_000_000, "host") == HOST_NOW + 33_000_000
    assert (clock.refused, clock.restarts) == (2, 0)


def test_a_restart_continues_one_period_after_the_last_frame() -> None:
    clock = fixed_clock()
    for t in (10_000_000_000, 10_033_000_000, 10_066_000_000):
        clock.stamp(t, "device")
    after = clock.stamp(50_000_000, "device")  # the recording starts again
    assert after == HOST_NOW + 66_000_000 + 33_000_000
    assert clock.stamp(83_000_000, "device") == after + 33_000_000
    assert clock.restarts == 1


def test_recordings_restart_on_any_step_back() -> None:
    clock = fixed_clock(restart_s=0.0)  # a short looped recording: 3 frames, 66 ms
    stamps = [clock.stamp(t, "device") for t in [0, 33, 66] * 3]
    assert stamps == [HOST_NOW + i * 33 for i in range(9)]


def test_stamps_strictly_increase_whatever_the_device_does() -> None:
    rng = np.random.default_rng(7)
    steps = rng.choice([33_333_333, 0, -150_000, -5_000_000_000, 2_000_000_000], 500,
                       p=[0.8, 0.08, 0.06, 0.03, 0.03])
    for domain in ("host", "device"):
        clock = fixed_clock()
        device = HOST_NOW + np.cumsum(steps)
        stamps = [s for t in device if (s := clock.stamp(int(t), domain)) is not None]
        assert len(stamps) > 400
        assert all(b > a for a, b in itertools.pairwise(stamps))


def test_unknown_domains_are_refused() -> None:
    with pytest.raises(ValueError, match="clock domain"):
        fixed_clock().stamp(0, "hardware_clock")


class RecordingEvent(threading.Event):
    """An event whose waits return at once and are recorded (no real sleeping in tests)."""

    def __init__(self) -> None:
        super().__init__()
        self.waits: list[float] = []

    def wait(self, timeout: float | None = None) -> bool:
        self.waits.append(float(timeout or 0.0))
        return self.is_set()


def test_pacer_holds_frames_to_rate_times_their_spacing() -> None:
    closed = RecordingEvent()
    pacer = Pacer(2.0, closed, now_s=lambda: 100.0)  # the host clock stands still
    assert all(pacer.wait(t) for t in (0, 1_000_000_000, 2_000_000_000))
    assert closed.waits == [0.5, 1.0]  # the first frame leaves at once


def test_pacer_rate_zero_never_waits_and_closing_stops_it() -> None:
    closed = RecordingEvent()
    fast = Pacer(0.0, closed)
    assert fast.wait(0) and fast.wait(10**12) and closed.waits == []
    closed.set()
    assert not fast.wait(2 * 10**12)
    paced = Pacer(1.0, closed, now_s=lambda: 0.0)
    assert not paced.wait(0) and not paced.wait(10**9)
    with pytest.raises(ValueError, match=">= 0"):
        Pacer(-1.0, closed)
