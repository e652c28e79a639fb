"""The small runner every handkse service uses.

A service is one event loop: samples from its subscriptions and control calls (``reset``) are
queued by the bus threads in an :class:`~services.common.inbox.Inbox` (bounded, never blocking a
bus thread, the oldest sample dropped and counted when full) and handled one at a time by
:meth:`Service.run`, so service logic needs no locks. A payload larger than its limit
(:class:`ServiceLimits`) is refused on the bus thread, before it is queued.

The runner declares the liveliness tokens ``handkse/{rig}/alive/{service}`` and
``handkse/{rig}/alive/{service}/{zid}`` (the id of the session that runs it), the ``stats``
queryable and the ``reset`` queryable (exact key only), counts what it receives, publishes and
rejects, and stops gracefully on SIGINT/SIGTERM. A bad message is counted in
``rejected[reason]`` and logged at most once per reason per second; it never stops the service.
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np

from services.common.bus import JSON, QueryAnswer, QueryRejected, QueryRequest
from services.common.inbox import Inbox
from services.common.keys import Keys
from services.common.protocol import Ack, Message, ProtocolError, ServiceStats

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)


class BusLike(Protocol):
    """What a service needs from the bus (``services.common.bus.Bus`` or a test fake)."""

    def put(self, key: str, payload: bytes, *, frame: bool = False,
            encoding: str = ...) -> None: ...

    def subscribe(self, key: str, callback: Callable[[str, bytes], None]) -> Any: ...

    def declare_queryable(self, key: str, handler: Callable[[Any], Any]) -> Any: ...

    def declare_token(self, key: str) -> Any: ...


class LatencyLog:
    """Recent latencies of named stages (bounded), summarised as p50/p99 in milliseconds.

    Thread-safe: the service loop adds while the ``stats`` queryable summarises on a bus thread.
    """

    def __init__(self, size: int = 2000) -> None:
        self._samples: dict[str, deque[float]] = {}
        self._size = size
        self._lock = threading.Lock()

    def add(self, stage: str, seconds: float) -> None:
        with self._lock:
            self._samples.setdefault(stage, deque(maxlen=self._size)).append(seconds * 1e3)

    @contextlib.contextmanager
    def measure(self, stage: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(stage, time.perf_counter() - t0)

    def summary(self) -> dict[str, dict[str, float]]:
        with self._lock:  # a copy, so that a stage added meanwhile cannot break the iteration
            snapshot = {stage: np.array(samples, float) for stage, samples in self._samples.items()}
        out = {}
        for stage, samples in snapshot.items():
            if samples.size:
                p50, p99 = np.percentile(samples, [50, 99])
                out[stage] = {"p50": float(p50), "p99": float(p99)}
        return out


@dataclass(frozen=True)
class ServiceLimits:
    """Input limits of every service (config section ``[limits]``).

    ``queue_size``: samples waiting for the loop before the oldest is dropped (256 is about 8 s
    of a 30 Hz stream; a service further behind than that is better off with recent data).
    ``max_payload_bytes``: the largest accepted payload of a state message (landmarks, bodies,
    models, requests; the largest legitimate one is a few kB). ``max_frame_payload_bytes``: the
    largest camera frame (a 4K BGR image with 16-bit depth is about 41 MB).
    """

    queue_size: int = 256
    max_payload_bytes: int = 1 << 20
    max_frame_payload_bytes: int = 64 << 20

    def __post_init__(self) -> None:
        for name in ("queue_size", "max_payload_bytes", "max_frame_payload_bytes"):
            if getattr(self, name) < 1:
                raise ValueError(f"limits.{name} must be at least 1, got {getattr(self, name)}")


class Service:
    """Counters, control queryables and the event loop of one service process."""

    def __init__(self, name: str, bus: BusLike, keys: Keys,
                 limits: ServiceLimits | None = None) -> None:
        self.name = name
        self.limits = ServiceLimits() if limits is None else limits
        self.bus = bus
        self.keys = keys
        self.started = time.monotonic()
        self.received = 0
        self.published = 0
        self.dropped = 0
        self.rejected: dict[str, int] = {}
        self.skipped: dict[str, int] = {}  # valid inputs without output, by reason (optional)
        self.latency = LatencyLog()
        self._seq: dict[str, int] = {}
        self._inbox = Inbox(self.limits.queue_size)
        self._reject_lock = threading.Lock()  # rejections are counted on bus threads too
        self._dropped_logged = 0
        self._last_log: dict[str, float] = {}
        self._reset_handlers: list[Callable[[], None]] = []
        bus.declare_queryable(keys.stats(name), self._answer_stats)
        bus.declare_queryable(keys.reset(name), self.exact_key_only(keys.reset(name),
                                                                    self._answer_reset))

    # --- counting ---

    def reject(self, reason: str, detail: str) -> None:
        """Count a rejected input under ``reason``; log it at most once per second per reason."""
        with self._reject_lock:
            count = self.rejected[reason] = self.rejected.get(reason, 0) + 1
            now = time.monotonic()
            due = now - self._last_log.get(reason, -1e9) >= 1.0
            if due:
                self._last_log[reason] = now
        if due:
            log.warning("%s rejected input (%s, %d so far): %s", self.name, reason, count, detail)

    def next_seq(self, key: str) -> int:
        seq = self._seq.get(key, 0)
        self._seq[key] = seq + 1
        return seq

    def stats(self) -> ServiceStats:
        with self._reject_lock:
            rejected = dict(self.rejected)
        return ServiceStats(service=self.name, uptime_s=time.monotonic() - self.started,
                            received=self.received, published=self.published,
                            dropped=self.dropped + self.inbox_dropped(), rejected=rejected,
                            latency_ms=self.latency.summary(), skipped=self._skipped())

    # --- wiring ---

    def publish(self, key: str, message: Message, *, frame: bool = False) -> None:
        self.bus.put(key, message.to_msgpack(), frame=frame)
        self.published += 1

    def _skipped(self) -> dict[str, int]:
        skipped = dict(self.skipped)
        superseded = sum(self._inbox.superseded().values())
        if superseded:
            skipped["superseded"] = skipped.get("superseded", 0) + superseded
        return skipped

    def inbox_dropped(self) -> int:
        """Input samples dropped because the loop fell behind (all keys)."""
        return sum(self._inbox.dropped().values())

    def subscribe(self, key: str, message_type: type[M], handler: Callable[[M], None], *,
                  latest: bool = False, frame: bool = False) -> None:
        """Decode every sample on ``key`` as ``message_type`` and hand it to ``handler`` in the loop.

        ``latest``: only the newest unread sample matters (a prior), so a newer valid one replaces
        it. ``frame``: camera frames, with the frame payload limit. ``received`` counts a sample
        when it is decoded (or refused), so once ``received`` reaches N the first N samples'
        rejections are counted too; a sample dropped unhandled is counted in ``dropped`` instead.
        """
        limit = self.limits.max_frame_payload_bytes if frame else self.limits.max_payload_bytes

        def decode(payload: bytes) -> M | None:
            try:
                return message_type.from_msgpack(payload)
            except ProtocolError as exc:
                self.reject(exc.reason, str(exc))
                return None

        def count() -> None:
            with self._reject_lock:
                self.received += 1

        def handle(payload: bytes) -> None:
            count()
            message = decode(payload)
            if message is not None:
                handler(message)

        def on_sample(k: str, payload: bytes) -> None:  # on a bus thread: never blocks
            if len(payload) > limit:
                count()
                self.reject("too_large", f"{len(payload)} bytes on {k} (limit {limit}, "
                                         f"limits.max_{'frame_' if frame else ''}payload_bytes)")
                return
            if latest:
                # Decoded here, so that garbage cannot evict a valid sample from the slot.
                count()
                message = decode(payload)
                if message is not None:
                    self._inbox.put_latest(k, (handler, (message,)))
            else:
                self._inbox.put(k, (handle, (payload,)))

        self.bus.subscribe(key, on_sample)

    def on_reset(self, handler: Callable[[], None]) -> None:
        """Run ``handler`` in the loop when the ``reset`` queryable is called."""
        self._reset_handlers.append(handler)

    def call_soon(self, fn: Callable[..., None], *args: Any) -> None:
        """Run ``fn(*args)`` in the service loop (before waiting samples; never dropped)."""
        self._inbox.call_soon((fn, args))

    def exact_key_only(self, key: str, handler: Callable[[QueryRequest], QueryAnswer]
                       ) -> Callable[[QueryRequest], QueryAnswer]:
        """``handler`` for queries on exactly ``key``; a wildcard query is refused.

        For queryables that change state (reset, articulate): a ``get`` on ``handkse/{rig}/**``
        or ``handkse/{rig}/*/reset`` reaches every queryable it intersects, and exploring the
        keys must not reset a service or move the robot. The refusal is an error reply naming
        the exact key, counted as ``wildcard_query``.
        """

        def answer(request: QueryRequest) -> QueryAnswer:
            if request.key != key:
                self.reject("wildcard_query", f"query on {request.key!r} refused: {key} "
                            "acts only on a query for exactly its key")
                raise QueryRejected(f"{self.name}: {key} acts only on a query for exactly "
                                    f"this key, not {request.key!r}")
            return handler(request)

        return answer

    # --- queryables (run on bus threads; touch only thread-safe state) ---

    def _answer_stats(self, request: QueryRequest) -> QueryAnswer:
        stats = self.stats()
        if request.parameters.get("format") == "json":
            return QueryAnswer(json.dumps(stats.to_json_obj()).encode(), JSON)
        return QueryAnswer(stats.to_msgpack())

    def _answer_reset(self, request: QueryRequest) -> QueryAnswer:
        done = threading.Event()
        errors: list[str] = []

        def do_reset() -> None:
            try:
                for handler in self._reset_handlers:
                    handler()
            except Exception as exc:  # reported to the caller, the service keeps running
                log.exception("%s reset failed", self.name)
                errors.append(str(exc))
            finally:
                done.set()

        self.call_soon(do_reset)
        if not done.wait(5.0):
            ack = Ack(ok=False, message=f"{self.name}: reset did not complete within 5 s")
        elif errors:
            ack = Ack(ok=False, message=f"{self.name}: reset failed: {errors[0]}")
        else:
            ack = Ack(ok=True, message=f"{self.name} reset")
        return QueryAnswer(ack.to_msgpack())

    # --- loop ---

    def run(self, stop: threading.Event, idle: Callable[[], None] | None = None,
            idle_period_s: float = 0.1) -> None:
        """Handle queued events until ``stop`` is set; ``idle`` runs about every ``idle_period_s``."""
        # The liveliness token means "ready": declared only once every subscription and
        # queryable of the service exists.
        self.bus.declare_token(self.keys.alive(self.name))
        # Which session runs the service, for peers that check who answers their queries
        # (the robot bridge trusts model replies only from the kinematics session). A bus
        # without a session id (a minimal test double) declares none.
        zid = getattr(self.bus, "zid", None)
        if isinstance(zid, str):
            self.bus.declare_token(self.keys.session(self.name, zid))
        next_idle = time.monotonic() + idle_period_s
        while not stop.is_set():
            event = self._inbox.take(idle_period_s)
            if event is not None:
                self._handle(event)
            if time.monotonic() >= next_idle:
                next_idle = time.monotonic() + idle_period_s
                self._log_drops()
                if idle is not None:
                    idle()

    def handle_pending(self) -> int:
        """Handle every event queued now, in this thread, then return how many (tests, tools)."""
        handled = 0
        while (event := self._inbox.take(0.0)) is not None:
            self._handle(event)
            handled += 1
        return handled

    def _handle(self, event: tuple[Callable[..., None], tuple[Any, ...]]) -> None:
        fn, args = event
        try:
            fn(*args)
        except Exception as exc:  # a bug for one input must not end the service
            # Counted and logged like any rejection (once per second, with the count); the
            # traceback only at DEBUG, so a flood of one bad input cannot fill a disk.
            self.reject("internal_error", repr(exc))
            log.debug("%s: handler failed", self.name, exc_info=True)

    def _log_drops(self) -> None:
        dropped = self.inbox_dropped()
        if dropped > self._dropped_logged:
            log.warning("%s fell behind: dropped %d oldest input samples (%d so far; "
                        "limits.queue_size=%d)", self.name, dropped - self._dropped_logged,
                        dropped, self.limits.queue_size)
            self._dropped_logged = dropped


def stop_on_signals(stop: threading.Event) -> None:
    """Set ``stop`` on SIGINT/SIGTERM (call from the main thread)."""

    def handler(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
