"""What ``handkse replay`` publishes, under which rig, with which stamps, and how often.

- **Topics.** A topic is a key below its rig: ``handkse/{rig}/hand/landmarks`` has the topic
  ``hand/landmarks``. By default only the pipeline's inputs are replayed (:data:`SOURCE_TOPICS`):
  a recording of a whole session also holds the tracker's ``hand/body`` and the kinematics'
  ``kinematics/model``, and re-publishing those would mix old results with the live ones.
- **Rigs.** Without a rig, a recording is published under the rig it was recorded on; with one,
  under that rig. A recording of several rigs cannot be put onto one.
- **Stamps.** By default every pass is moved onto the wall clock (:func:`wall_clock_offset`): one
  offset for every message of the pass, added to the envelope ``stamp_ns``, the MCAP log time and
  the publish time, so the relative timing of all topics stays exactly as recorded. At rate 1 the
  first message is stamped with the time it is published; no message is ever stamped later than
  the moment it is published (a faster replay ends on the clock instead), and a pass never
  starts before the previous one ended, so a loop's stamps only grow.
- **Passes.** :func:`play` runs one pass, or passes until stopped (``loop``), optionally
  resetting services before each pass (a new demonstration each time) and standing by while a
  live source (a camera) is on the bus.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from services.common.bus import BusError
from services.common.errors import UserError
from services.common.keys import PREFIX, Keys, check_rig
from services.common.protocol import Ack, ProtocolError, restamp
from services.common.recording import RecordedMessage, replay

log = logging.getLogger(__name__)

SOURCE_TOPICS: tuple[str, ...] = ("camera/rgbd", "hand/landmarks")


def topic_of(key: str) -> str:
    """The part of ``handkse/{rig}/...`` below the rig; any other key is its own topic."""
    parts = key.split("/", 2)
    return parts[2] if len(parts) == 3 and parts[0] == PREFIX else key


def rig_of(key: str) -> str | None:
    """The rig chunk of a ``handkse/{rig}/...`` key, None for other keys."""
    parts = key.split("/", 2)
    return parts[1] if len(parts) == 3 and parts[0] == PREFIX else None


def _unique(items: Iterable[str]) -> list[str]:
    return list(dict.fromkeys(items))


def select_topics(messages: Sequence[RecordedMessage], topics: Sequence[str] | None,
                  source: str) -> list[RecordedMessage]:
    """The messages on ``topics``, or on the :data:`SOURCE_TOPICS` for None; ``source`` names
    the recording in errors.

    An explicit topic that ``messages`` do not have is refused, as is a selection that leaves
    nothing.
    """
    have = _unique(topic_of(m.key) for m in messages)
    listing = ", ".join(have) or "no messages"
    if topics is not None:
        missing = [t for t in topics if t not in have]
        if missing:
            raise UserError(f"--topics: {', '.join(missing)} not in {source}; it has: {listing}")
        return [m for m in messages if topic_of(m.key) in topics]
    chosen = [m for m in messages if topic_of(m.key) in SOURCE_TOPICS]
    if not chosen:
        raise UserError(f"{source} has none of the source topics {', '.join(SOURCE_TOPICS)}; it "
                        f"has: {listing}; choose with --topics or replay everything with "
                        "--all-topics")
    if set(SOURCE_TOPICS) <= set(have):
        log.warning("%s holds both camera/rgbd and hand/landmarks: with a detector running, the "
                    "frames are detected a second time; pick one with --topics", source)
    return chosen


def target_rig(messages: Sequence[RecordedMessage], rig: str | None, source: str
               ) -> tuple[str, str | None]:
    """``(rig the replay runs on, rig to remap to or None)`` for a recording and ``--rig``.

    Without ``rig`` the recording keeps its keys (and runs on its rig, or ``default`` when it
    has none or several); with it every key moves to ``rig``. Several recorded rigs and a ``rig``
    would be merged into one: refused.
    """
    rigs = _unique(r for r in (rig_of(m.key) for m in messages) if r is not None)
    if rig is None:
        return (rigs[0] if len(rigs) == 1 else "default"), None
    check_rig(rig)
    if len(rigs) > 1:
        raise UserError(f"{source} holds the rigs {', '.join(rigs)}: --rig {rig} would merge "
                        "them onto one; replay it without --rig to keep each on its own")
    return rig, (rig if rigs and rigs[0] != rig else None)


def wall_clock_offset(messages: Sequence[RecordedMessage], rate: float, now_ns: int,
                      not_before_ns: int = 0) -> int:
    """The offset [ns] that moves a pass of ``messages`` starting at ``now_ns`` onto the wall
    clock.

    The pass is published at ``now_ns + (log_time - first log_time) / rate`` (all at ``now_ns``
    for ``rate`` 0). The offset puts every stamp at or before that moment, the closest one
    exactly on it; at rate 1 with stamps equal to log times that is ``now_ns - first stamp``.
    ``not_before_ns``: the earliest stamp allowed (the previous pass's last stamp + 1).
    Messages without a stamp (publish time 0) do not count; none stamped gives 0.
    """
    stamped = [m for m in messages if m.publish_time_ns > 0]
    if not stamped:
        return 0
    slowness = 1.0 / rate if rate > 0 else 0.0
    t0 = messages[0].log_time_ns
    lead = max(m.publish_time_ns - round((m.log_time_ns - t0) * slowness) for m in stamped)
    first = min(m.publish_time_ns for m in stamped)
    return max(now_ns - lead, not_before_ns - first)


def restamped(messages: Iterable[RecordedMessage], offset_ns: int) -> Iterator[RecordedMessage]:
    """``messages`` with ``offset_ns`` added to each envelope stamp, log time and publish time
    (lazily: a frame is re-encoded just before it is published)."""
    for m in messages:
        yield dataclasses.replace(
            m, payload=restamp(m.payload, offset_ns), log_time_ns=m.log_time_ns + offset_ns,
            publish_time_ns=m.publish_time_ns + offset_ns if m.publish_time_ns > 0 else 0)


def last_stamp(messages: Sequence[RecordedMessage], offset_ns: int = 0) -> int:
    """The latest publish time of ``messages`` after ``offset_ns`` (0 when none is stamped)."""
    stamps = [m.publish_time_ns for m in messages if m.publish_time_ns > 0]
    return max(stamps) + offset_ns if stamps else 0


class PlaybackBus(Protocol):
    """What a replay needs from the bus (``services.common.bus.Bus``)."""

    def put(self, key: str, payload: bytes, *, frame: bool = False) -> None: ...

    def get(self, selector: str, payload: bytes | None = None, timeout: float = 2.0
            ) -> list[tuple[str, bytes]]: ...

    def watch_liveliness(self, key_expr: str, callback: Callable[[str, bool], None],
                         history: bool = True) -> Any: ...


@dataclass(frozen=True)
class PlaybackOptions:
    """How :func:`play` replays.

    ``rate``: speed factor (0 = as fast as possible); ``loop``: pass after pass until stopped,
    ``loop_pause_s`` apart; ``keep_stamps``: publish the recorded stamps; ``remap_rig``: publish
    under this rig; ``reset``: services reset before every pass; ``standby_while``: services
    whose liveliness token pauses the replay (a pass they interrupt starts over once they are
    gone, after the resets).
    """

    rate: float = 1.0
    loop: bool = False
    loop_pause_s: float = 0.0
    keep_stamps: bool = False
    remap_rig: str | None = None
    reset: tuple[str, ...] = ()
    standby_while: tuple[str, ...] = ()


class _Standby:
    """Tracks the liveliness tokens of the services a replay stands by for."""

    def __init__(self, bus: PlaybackBus, keys: Keys, services: Sequence[str]) -> None:
        self._alive: set[str] = set()
        self._lock = threading.Lock()
        self.present = threading.Event()
        for service in services:
            bus.watch_liveliness(keys.alive(service), self._on_token)

    def _on_token(self, key: str, alive: bool) -> None:
        with self._lock:
            (self._alive.add if alive else self._alive.discard)(key)
            (self.present.set if self._alive else self.present.clear)()

    def names(self) -> str:
        with self._lock:
            return ", ".join(sorted(k.rsplit("/", 1)[-1] for k in self._alive))


@dataclass(frozen=True)
class _Either:
    """Set when any of its events is."""

    events: tuple[threading.Event, ...]

    def is_set(self) -> bool:
        return any(e.is_set() for e in self.events)


def _reset(bus: PlaybackBus, keys: Keys, services: Sequence[str]) -> None:
    for service in services:
        try:
            ack = Ack.from_msgpack(bus.get(keys.reset(service), timeout=5.0)[0][1])
        except (BusError, ProtocolError) as exc:
            log.warning("reset %s failed: %s", service, exc)
            continue
        if not ack.ok:
            log.warning("reset %s refused: %s", service, ack.message)


def play(bus: PlaybackBus, keys: Keys, messages: Sequence[RecordedMessage],
         options: PlaybackOptions, stop: threading.Event) -> int:
    """Replay ``messages`` onto ``bus`` as ``options`` say, until done or ``stop``; returns the
    number of messages published."""
    standby = _Standby(bus, keys, options.standby_while)

    def publish(key: str, payload: bytes) -> None:
        bus.put(key, payload, frame=key.endswith("/camera/rgbd"))

    total = 0
    not_before = 0
    while not stop.is_set():
        if standby.present.is_set():
            log.warning("standing by: %s is on the bus, the replay publishes nothing until it "
                        "is gone", standby.names())
            while standby.present.is_set() and not stop.wait(0.1):
                pass
            continue
        _reset(bus, keys, options.reset)
        offset = 0 if options.keep_stamps else wall_clock_offset(
            messages, options.rate, time.time_ns(), not_before)
        stream = messages if options.keep_stamps else restamped(messages, offset)
        count = replay(stream, publish, rate=options.rate, rig=options.remap_rig,
                       stop=_Either((stop, standby.present)))
        total += count
        not_before = max(not_before, last_stamp(messages, offset) + 1)
        if standby.present.is_set() and not stop.is_set():
            log.warning("%s came up: replay pass stopped after %d messages", standby.names(),
                        count)
            _reset(bus, keys, options.reset)  # the live demonstration starts from nothing
            continue
        if not options.loop:
            break
        stop.wait(options.loop_pause_s)
    return total
