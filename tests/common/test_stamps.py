"""The stamp window: a stamp far ahead of its stream or of the receive clock is refused, a stream
that really moved ahead is adopted after ``resync_s``, one message never is."""

from __future__ import annotations

import pytest

from services.common.config import ConfigError, load_section
from services.common.stamps import INT64_MAX, StampLimits, StampWindow

S = 1_000_000_000  # 1 s in ns
NOW = 1_750_000_000 * S  # a wall clock in 2025
FRAME = 33_333_333  # 30 Hz


def stream(window: StampWindow, stamps: list[int], received: list[int]) -> list[str | None]:
    """Offer each sample; accept those that pass (as a service does); the refusals."""
    out = []
    for stamp, at in zip(stamps, received, strict=True):
        why = window.check(stamp, at)
        if why is None:
            window.accept(stamp, at)
        out.append(why)
    return out


def test_a_stamp_far_ahead_of_the_clock_is_refused_and_never_becomes_the_anchor() -> None:
    window = StampWindow()
    why = window.check(INT64_MAX, NOW)
    assert why is not None and "ahead of the receive clock" in why and "max_lead_s" in why
    assert window.anchor is None  # nothing adopted
    assert window.check(NOW + 4 * S, NOW) is None  # within the 5 s lead
    assert window.check(NOW + 6 * S, NOW) is not None


@pytest.mark.parametrize("epoch", [0, 10**9, 5 * 10**11, NOW - 400 * 24 * 3600 * S, NOW])
def test_streams_of_any_past_epoch_pass_at_any_rate(epoch: int) -> None:
    """A replay of an old recording, a synthetic epoch near 0, a live camera; in real time, as
    fast as possible (the clock hardly moves), or after a 60 s gap in real time."""
    stamps = [epoch + k * FRAME for k in range(100)]
    real_time = [NOW + k * FRAME for k in range(100)]
    flat_out = [NOW + k * 1000 for k in range(100)]
    for received in (real_time, flat_out):
        assert stream(StampWindow(), stamps, received) == [None] * 100
    gap = [*stamps[:50], *(s + 60 * S for s in stamps[50:])]
    gap_received = [*real_time[:50], *(r + 60 * S for r in real_time[50:])]
    assert stream(StampWindow(), gap, gap_received) == [None] * 100


def test_one_message_ahead_of_the_stream_is_refused_the_stream_continues() -> None:
    window = StampWindow()
    stamps = [10**9 + k * FRAME for k in range(60)]
    received = [NOW + k * FRAME for k in range(60)]
    assert stream(window, stamps[:30], received[:30]) == [None] * 30
    why = window.check(stamps[30] + 3600 * S, received[30])  # an hour ahead, in the past of now
    assert why is not None and "ahead of the stream" in why and "max_jump_s" in why
    assert window.anchor == (stamps[29], received[29])
    assert stream(window, stamps[31:], received[31:]) == [None] * 29
    assert window.anchor == (stamps[-1], received[-1])


def test_a_stream_that_moved_ahead_is_adopted_after_resync_s() -> None:
    """A clock stepped forward by a minute: refused for resync_s (1 s) of receive time, then the
    new stream is the stream."""
    window = StampWindow()
    received = [NOW + k * FRAME for k in range(120)]
    stamps = [10**9 + k * FRAME + (60 * S if k >= 30 else 0) for k in range(120)]
    refused = stream(window, stamps, received)
    assert refused[:30] == [None] * 30
    first = 30 + next(i for i, why in enumerate(refused[30:]) if why is None)
    assert all(why is not None for why in refused[30:first])
    assert received[first] - received[30] >= S > received[first - 1] - received[30]
    assert refused[first:] == [None] * (120 - first)


def test_a_lone_message_or_a_burst_never_resyncs() -> None:
    """Jumped samples that do not agree with each other, or a burst that spans less than
    resync_s of receive time, are refused whatever their number."""
    window = StampWindow()
    stream(window, [10**9], [NOW])
    scattered = [10**9 + (100 + 10 * (k % 2) * 3600) * S + k for k in range(200)]
    assert all(window.check(s, NOW + k * FRAME) is not None for k, s in enumerate(scattered))
    window = StampWindow()
    stream(window, [10**9], [NOW])
    burst = [10**9 + 3600 * S + k * FRAME for k in range(1000)]
    assert all(window.check(s, NOW + k * 10**5) is not None for k, s in enumerate(burst))


def test_real_samples_between_jumped_ones_keep_the_stream() -> None:
    window = StampWindow()
    stream(window, [10**9 - FRAME], [NOW - FRAME])
    for k in range(200):
        at = NOW + k * FRAME
        assert window.check(10**9 + k * FRAME + 3600 * S, at) is not None  # an attacker
        assert window.check(10**9 + k * FRAME, at) is None  # the real stream
        window.accept(10**9 + k * FRAME, at)


def test_forget_drops_the_anchor_for_a_new_stream() -> None:
    window = StampWindow()
    stream(window, [10**9], [NOW])
    assert window.check(5 * 10**11, NOW + FRAME) is not None  # another recording
    window.forget()
    assert window.anchor is None and window.check(5 * 10**11, NOW + FRAME) is None


def test_rules_can_be_turned_off() -> None:
    window = StampWindow(StampLimits(max_lead_s=0.0, max_jump_s=0.0))
    assert stream(window, [10**9, INT64_MAX], [NOW, NOW + FRAME]) == [None, None]


def test_state_round_trip_and_invalid_states() -> None:
    window = StampWindow()
    assert StampWindow.from_state(window.to_state()).anchor is None
    window.accept(10**9, NOW)
    restored = StampWindow.from_state(window.to_state(), now_ns=NOW + S)
    assert restored.anchor == (10**9, NOW)
    for bad, message in [(None, "expected a map"), ({}, "expected a map"),
                         ({"anchor": "x"}, r"\[stamp_ns, received_ns\]"),
                         ({"anchor": [1.5, NOW]}, "integer"), ({"anchor": [True, NOW]}, "integer"),
                         ({"anchor": [-1, NOW]}, "integer"),
                         ({"anchor": [INT64_MAX + 1, NOW]}, "integer"),
                         ({"anchor": [INT64_MAX, NOW]}, "ahead of the receive clock")]:
        with pytest.raises(ValueError, match=message):
            StampWindow.from_state(bad)
    # an anchor stamped ahead of the clock of the host that restores it
    with pytest.raises(ValueError, match="ahead of the receive clock"):
        StampWindow.from_state({"anchor": [NOW + 60 * S, NOW + 60 * S]}, now_ns=NOW)


def test_limits_are_a_config_section() -> None:
    assert load_section("stamps") == StampLimits()
    assert load_section("stamps", None, ["stamps.max_jump_s=2"]).max_jump_s == 2.0
    for bad in ("stamps.max_lead_s=-1", "stamps.resync_s=nan"):
        with pytest.raises(ConfigError, match="stamps"):
            load_section("stamps", None, [bad])
