"""Stamps that stay with their stream: one message stamped far ahead cannot become "the latest".

A service that orders its input by ``stamp_ns`` (sensor time, ns) refuses a sample that arrives out
of order. Without a bound on how far *ahead* a stamp may be, one message stamped 2^63 - 1 would
make every later real sample out of order. :class:`StampWindow` is that bound; it compares each
stamp with the **receive clock**, this host's wall clock (``time.time_ns()``) when the service
handles the sample, through the sample's offset ``stamp_ns - received_ns``:

- **lead**: a stamp more than ``max_lead_s`` ahead of the receive clock is refused. A capture time
  lies in the past of its reception, so only clocks that disagree (or a forgery) put a stamp in
  the future; a clock *behind* (a recording replayed with its original stamps, a synthetic epoch
  near 0) is never refused by this rule.
- **jump**: a stamp whose offset exceeds the offset of the last accepted sample by more than
  ``max_jump_s`` is refused: between two accepted samples the stream may not run ahead of the
  receive clock by more than that. A gap of any length is fine (the clock moved on with the
  stamps), and so is a replay faster than real time, a step at a time.
- **resync**: samples refused by the jump rule alone that agree with one another (stamps
  increasing, each offset within ``max_jump_s`` of the previous one's) for ``resync_s`` of receive
  time, with no accepted sample among them, are a stream that really moved ahead (a sensor clock
  stepped forward, a long gap in a replay faster than real time); the sample that completes
  ``resync_s`` is accepted. A lone message never is, nor anything refused by the lead rule.

The window remembers only the last accepted sample (its *anchor*) and the current run of refused
ones; :meth:`StampWindow.forget` drops both (a new demonstration may bring a new stream). It is
plain Python (no numpy) so every service can use it, and it keeps no clock of its own: the caller
passes ``received_ns``. docs/protocol.md#stamps states the rules for senders.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

INT64_MAX = (1 << 63) - 1


@dataclass(frozen=True)
class StampLimits:
    """How far a stamp may run ahead (config section ``[stamps]``); ``max_lead_s`` or
    ``max_jump_s`` 0 turns that rule off."""

    # A stamp may be at most this far ahead of the receive clock [s] (clock disagreement allowed).
    max_lead_s: float = 5.0
    # Between two accepted samples the stamps may run ahead of the receive clock by this much [s].
    max_jump_s: float = 5.0
    # Receive time over which a consistent run of jumped samples is adopted as the stream [s].
    resync_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("max_lead_s", "max_jump_s", "resync_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"stamps.{name} must be finite and >= 0, got {value!r}")


def _seconds(ns: int) -> str:
    return f"{ns * 1e-9:.3g} s"


def _stamp(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= INT64_MAX:
        raise ValueError(f"{where}: expected an integer in [0, 2^63), got {value!r}")
    return value


class StampWindow:
    """The lead, jump and resync rules of the module docstring for one input stream.

    Use: ``why = window.check(stamp, received)``; refuse the sample if ``why`` is not None (it
    says how far ahead it was); otherwise, once the sample was used, ``window.accept(stamp,
    received)``. ``received`` is the wall clock in ns when the sample was handled.
    """

    def __init__(self, limits: StampLimits | None = None) -> None:
        self.limits = StampLimits() if limits is None else limits
        self._lead_ns = round(self.limits.max_lead_s * 1e9)
        self._jump_ns = round(self.limits.max_jump_s * 1e9)
        self._resync_ns = round(self.limits.resync_s * 1e9)
        self._anchor: tuple[int, int] | None = None  # (stamp, received) of the last accepted
        # the run of jumped samples: (received of its first, stamp and received of its last)
        self._run: tuple[int, int, int] | None = None

    @property
    def anchor(self) -> tuple[int, int] | None:
        """``(stamp_ns, received_ns)`` of the last accepted sample, None before one."""
        return self._anchor

    def lead_problem(self, stamp_ns: int, received_ns: int) -> str | None:
        """Why ``stamp_ns`` breaks the lead rule at ``received_ns``, or None."""
        lead = stamp_ns - received_ns
        if self._lead_ns and lead > self._lead_ns:
            return (f"stamp {stamp_ns} is {_seconds(lead)} ahead of the receive clock "
                    f"(limit stamps.max_lead_s = {self.limits.max_lead_s:g})")
        return None

    def check(self, stamp_ns: int, received_ns: int) -> str | None:
        """None if ``stamp_ns`` may be used now; else why not. A refused sample is remembered as
        part of a possible resync run (module docstring)."""
        lead = self.lead_problem(stamp_ns, received_ns)
        if lead is not None:
            return lead
        if self._anchor is None or not self._jump_ns:
            return None
        offset = stamp_ns - received_ns
        jump = offset - (self._anchor[0] - self._anchor[1])
        if jump <= self._jump_ns:
            return None
        run = self._run
        if (run is not None and stamp_ns > run[1]
                and abs(offset - (run[1] - run[2])) <= self._jump_ns):
            if received_ns - run[0] >= self._resync_ns:
                return None  # a stream that moved ahead, consistently, for resync_s
            self._run = (run[0], stamp_ns, received_ns)
        else:
            self._run = (received_ns, stamp_ns, received_ns)
        return (f"stamp {stamp_ns} jumps {_seconds(jump)} ahead of the stream (limit "
                f"stamps.max_jump_s = {self.limits.max_jump_s:g}; a stream that stays this far "
                f"ahead is adopted after stamps.resync_s = {self.limits.resync_s:g})")

    def accept(self, stamp_ns: int, received_ns: int) -> None:
        """The sample at ``stamp_ns`` (received at ``received_ns``) was used: it is the anchor."""
        self._anchor = (int(stamp_ns), int(received_ns))
        self._run = None

    def forget(self) -> None:
        """Drop the anchor and any run: the next sample is judged by the lead rule only."""
        self._anchor = None
        self._run = None

    # --- state files ---

    def to_state(self) -> dict[str, Any]:
        """The anchor, for a state file (the run of refused samples is not kept)."""
        return {"anchor": None if self._anchor is None else list(self._anchor)}

    @classmethod
    def from_state(cls, state: Any, limits: StampLimits | None = None,
                   now_ns: int | None = None) -> StampWindow:
        """Rebuild from :meth:`to_state`; ValueError naming the field if it is not valid, or if its
        anchor breaks the lead rule at ``now_ns`` (a poisoned stamp must not come back)."""
        window = cls(limits)
        if not isinstance(state, dict) or "anchor" not in state:
            raise ValueError(f"stamps: expected a map with 'anchor', got {state!r:.80}")
        anchor = state["anchor"]
        if anchor is not None:
            if not isinstance(anchor, list) or len(anchor) != 2:
                raise ValueError(f"stamps.anchor: expected [stamp_ns, received_ns], got "
                                 f"{anchor!r:.80}")
            stamp = _stamp(anchor[0], "stamps.anchor[0]")
            received = _stamp(anchor[1], "stamps.anchor[1]")
            problem = window.lead_problem(stamp, received)
            if problem is None and now_ns is not None:
                problem = window.lead_problem(stamp, now_ns)
            if problem is not None:
                raise ValueError(f"stamps.anchor: {problem}")
            window._anchor = (stamp, received)
        return window


__all__ = ["INT64_MAX", "StampLimits", "StampWindow"]
