"""A service's input queue: bounded, never blocking the bus, every drop counted.

Zenoh calls subscriber callbacks on its own threads; a callback that blocks stalls that
session's receive path, and with state messages published in congestion-control BLOCK mode the
stall spreads back to the publisher. Two services that feed each other (tracker -> kinematics ->
tracker) then stop each other, and ``stats`` queries go unanswered. So a callback only appends
here and returns.

Policy (``docs/protocol.md``, "Backpressure"):

- **FIFO inputs** (landmarks, bodies): one queue of ``capacity`` samples across them, in arrival
  order; when it is full the *oldest* sample is dropped and counted under its key, so a service
  that falls behind catches up on recent data instead of lagging ever further.
- **Latest inputs** (a model used only as a prior): one slot per key; a newer sample replaces an
  unread one, which is counted as *superseded* (not lost: its newer version is used).
- **Control calls** (``reset``, work scheduled with ``call_soon``): never dropped, and handled
  before waiting samples.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any

Event = tuple[Callable[..., None], tuple[Any, ...]]


class Inbox:
    """Thread-safe: bus threads ``put``, the service loop ``take``s."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"inbox capacity must be at least 1, got {capacity}")
        self.capacity = capacity
        self._cond = threading.Condition()
        self._control: deque[Event] = deque()
        self._fifo: deque[tuple[str, Event]] = deque()
        self._latest: dict[str, Event] = {}
        self._dropped: dict[str, int] = {}
        self._superseded: dict[str, int] = {}

    def put(self, key: str, event: Event) -> None:
        """Queue a FIFO sample; drops (and counts) the oldest sample when full."""
        with self._cond:
            if len(self._fifo) >= self.capacity:
                old_key, _ = self._fifo.popleft()
                self._dropped[old_key] = self._dropped.get(old_key, 0) + 1
            self._fifo.append((key, event))
            self._cond.notify()

    def put_latest(self, key: str, event: Event) -> None:
        """Keep only the newest unread sample of ``key``; a replaced one is counted superseded."""
        with self._cond:
            if key in self._latest:
                self._superseded[key] = self._superseded.get(key, 0) + 1
            self._latest[key] = event
            self._cond.notify()

    def call_soon(self, event: Event) -> None:
        """Queue a control call: never dropped, taken before samples."""
        with self._cond:
            self._control.append(event)
            self._cond.notify()

    def take(self, timeout: float) -> Event | None:
        """The next event (control, then latest slots, then FIFO), waiting up to ``timeout`` s."""
        with self._cond:
            if not (self._control or self._latest or self._fifo):
                self._cond.wait(timeout)
            if self._control:
                return self._control.popleft()
            if self._latest:
                key = next(iter(self._latest))
                return self._latest.pop(key)
            if self._fifo:
                return self._fifo.popleft()[1]
            return None

    def dropped(self) -> dict[str, int]:
        """Dropped samples by key since start (a copy)."""
        with self._cond:
            return dict(self._dropped)

    def superseded(self) -> dict[str, int]:
        """Latest-only samples replaced unread by a newer one, by key (a copy)."""
        with self._cond:
            return dict(self._superseded)

    def __len__(self) -> int:
        with self._cond:
            return len(self._control) + len(self._latest) + len(self._fifo)
