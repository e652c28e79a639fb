"""An in-memory stand-in for ``services.common.bus.Bus``, for unit tests of nodes.

:class:`FakeBus` has the public interface of the real bus (put, subscribe, subscribe_latest,
declare_queryable, get, get_replies, declare_token, alive, watch_liveliness, close) and its observable
semantics, which ``tests/common/test_bus_contract.py`` checks against both. Sessions that share
a :class:`FakeNetwork` see each other, as sessions on one Zenoh router do.

What is deliberately different, so tests need no sleeps:

- Delivery is synchronous. ``put`` (and a token appearing or vanishing) returns only after
  every matching callback ran, in the caller's thread. A ``put`` made inside a callback is
  queued and delivered right after that callback returns, so samples stay in FIFO order.
  Callbacks of the whole network run one at a time.
- ``alive`` and ``watch_liveliness(history=True)`` see tokens the moment they are declared.
- Query handlers run on a thread of their own (as on Zenoh's threads), so a handler that waits
  for a service loop behaves as it does on the real bus; ``get`` waits for them up to its
  timeout.

Key expressions support the chunk wildcards ``*`` (one chunk) and ``**`` (any number of
chunks); ``$*`` inside a chunk is refused, since no handkse key uses it.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from services.common.bus import (
    MSGPACK,
    BusError,
    Callback,
    LatestSlot,
    NoResponder,
    QueryAnswer,
    QueryHandler,
    QueryRejected,
    QueryRequest,
    QueryTimeout,
    Reply,
)

log = logging.getLogger(__name__)

_TIMEOUT_REPLY = "Timeout"  # the error reply Zenoh gives a query that ran out of time


def check_key_expr(key_expr: str) -> tuple[str, ...]:
    """The chunks of ``key_expr``; ValueError for one Zenoh would refuse (or this fake cannot
    match)."""
    chunks = tuple(key_expr.split("/"))
    if not key_expr or any(not c for c in chunks):
        raise ValueError(f"invalid key expression {key_expr!r}: empty chunks, leading and "
                         "trailing slashes are forbidden")
    for c in chunks:
        if c not in ("*", "**") and ("*" in c or "$" in c or "?" in c or "#" in c):
            raise ValueError(f"invalid key expression {key_expr!r}: chunk {c!r} is not "
                             "supported by the fake bus")
    return chunks


@lru_cache(maxsize=4096)
def _chunks_intersect(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    if not a or not b:
        return all(c == "**" for c in a + b)
    if a[0] == "**":
        return _chunks_intersect(a[1:], b) or _chunks_intersect(a, b[1:])
    if b[0] == "**":
        return _chunks_intersect(a, b[1:]) or _chunks_intersect(a[1:], b)
    if a[0] == b[0] or "*" in (a[0], b[0]):
        return _chunks_intersect(a[1:], b[1:])
    return False


def intersects(a: str, b: str) -> bool:
    """Whether some key matches both key expressions (Zenoh's rule for routing a sample)."""
    return _chunks_intersect(check_key_expr(a), check_key_expr(b))


def split_selector(selector: str) -> tuple[str, dict[str, str]]:
    """``key?a=1;b=2`` as ``("key", {"a": "1", "b": "2"})``."""
    key, _, text = selector.partition("?")
    params: dict[str, str] = {}
    for part in filter(None, text.split(";")):
        name, _, value = part.partition("=")
        params[name] = value
    return key, params


@dataclass(frozen=True)
class PutRecord:
    """One ``put`` as the fake saw it (``frame`` and ``encoding`` as passed)."""

    key: str
    payload: bytes
    frame: bool
    encoding: str


class Declaration:
    """What ``subscribe``/``declare_queryable``/``declare_token``/``watch_liveliness`` return:
    something with ``undeclare()``, like the Zenoh objects the real bus returns."""

    def __init__(self, bus: FakeBus, kind: str, key_expr: str, target: Any) -> None:
        self.bus = bus
        self.kind = kind
        self.key_expr = key_expr
        self.target = target
        self.declared = True

    def undeclare(self) -> None:
        self.bus.network._undeclare(self)


class FakeNetwork:
    """Everything declared by the sessions of one in-memory Zenoh network."""

    def __init__(self) -> None:
        self._lock = threading.Condition()
        self._declarations: list[Declaration] = []
        self._pending: deque[tuple[Declaration, tuple[Any, ...]]] = deque()
        self._delivering: int | None = None  # thread ident of the thread running callbacks
        self.puts: list[PutRecord] = []
        self.callback_errors: list[BaseException] = []

    # --- declarations ---

    def _declare(self, decl: Declaration) -> Declaration:
        with self._lock:
            self._declarations.append(decl)
        return decl

    def _live(self, kind: str) -> list[Declaration]:
        return [d for d in self._declarations if d.kind == kind and d.declared]

    def _alive_keys(self) -> set[str]:
        return {d.key_expr for d in self._live("token")}

    def _undeclare(self, decl: Declaration) -> None:
        with self._lock:
            if not decl.declared:
                return
            decl.declared = False
            self._declarations.remove(decl)
            vanished = decl.kind == "token" and decl.key_expr not in self._alive_keys()
            if vanished:
                self._queue_liveliness(decl.key_expr, False)
        if vanished:
            self._deliver()

    def _undeclare_all(self, bus: FakeBus) -> None:
        with self._lock:
            mine = [d for d in self._declarations if d.bus is bus]
        for decl in reversed(mine):
            self._undeclare(decl)

    # --- delivery ---

    def _queue_liveliness(self, key: str, alive: bool) -> None:
        for w in self._live("watch"):
            if intersects(w.key_expr, key):
                self._pending.append((w, (key, alive)))

    def _deliver(self) -> None:
        """Run every queued callback, FIFO; a nested call (from a callback) returns at once."""
        me = threading.get_ident()
        with self._lock:
            if self._delivering == me:
                return
            self._lock.wait_for(lambda: self._delivering is None)
            self._delivering = me
        try:
            while True:
                with self._lock:
                    if not self._pending:
                        return
                    decl, args = self._pending.popleft()
                    if not decl.declared:  # undeclared meanwhile: Zenoh calls it no more
                        continue
                try:
                    decl.target(*args)
                except Exception as exc:  # as the real bus: logged, never raised into put
                    log.exception("callback for %s failed", decl.key_expr)
                    self.callback_errors.append(exc)
        finally:
            with self._lock:
                self._delivering = None
                self._lock.notify_all()

    def put(self, key: str, payload: bytes, frame: bool, encoding: str) -> None:
        check_key_expr(key)
        with self._lock:
            self.puts.append(PutRecord(key, bytes(payload), frame, encoding))
            for s in self._live("sub"):
                if intersects(s.key_expr, key):
                    self._pending.append((s, (key, bytes(payload))))
        self._deliver()

    def declare_token(self, bus: FakeBus, key: str) -> Declaration:
        check_key_expr(key)
        with self._lock:
            appeared = key not in self._alive_keys()
            decl = self._declare(Declaration(bus, "token", key, None))
            if appeared:
                self._queue_liveliness(key, True)
        self._deliver()
        return decl

    def watch(self, bus: FakeBus, key_expr: str, callback: Callable[[str, bool], None],
              history: bool) -> Declaration:
        check_key_expr(key_expr)
        with self._lock:
            decl = self._declare(Declaration(bus, "watch", key_expr, callback))
            if history:
                for key in sorted(self._alive_keys()):
                    if intersects(key_expr, key):
                        self._pending.append((decl, (key, True)))
        self._deliver()
        return decl

    def alive(self, key_expr: str) -> list[str]:
        check_key_expr(key_expr)
        with self._lock:
            return sorted(k for k in self._alive_keys() if intersects(key_expr, k))

    def queryables(self, key_expr: str) -> list[Declaration]:
        check_key_expr(key_expr)
        with self._lock:
            return [q for q in self._live("queryable") if intersects(q.key_expr, key_expr)]


class FakeBus:
    """One session on a :class:`FakeNetwork` (a private one by default); see the module doc."""

    _ids = itertools.count(1)

    def __init__(self, network: FakeNetwork | None = None) -> None:
        self.network = network or FakeNetwork()
        self._zid = f"fake{next(self._ids):028x}"
        self._closed = False

    def __enter__(self) -> FakeBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare everything this session declared (idempotent)."""
        self._closed = True
        self.network._undeclare_all(self)

    @property
    def zid(self) -> str:
        return self._zid

    @property
    def puts(self) -> list[PutRecord]:
        """Every ``put`` on the network so far, in order (all sessions)."""
        return self.network.puts

    def _check_open(self) -> None:
        if self._closed:
            raise BusError("the fake bus session is closed")

    # --- publish / subscribe ---

    def put(self, key: str, payload: bytes, *, frame: bool = False,
            encoding: str = MSGPACK) -> None:
        """Deliver ``payload`` to every matching subscriber before returning."""
        self._check_open()
        self.network.put(key, payload, frame, encoding)

    def subscribe(self, key: str, callback: Callback) -> Declaration:
        self._check_open()
        check_key_expr(key)
        return self.network._declare(Declaration(self, "sub", key, callback))

    def subscribe_latest(self, key: str) -> LatestSlot:
        slot = LatestSlot()
        self.subscribe(key, slot.push)
        return slot

    # --- query ---

    def declare_queryable(self, key: str, handler: QueryHandler) -> Declaration:
        self._check_open()
        check_key_expr(key)
        return self.network._declare(Declaration(self, "queryable", key, handler))

    def get(self, selector: str, payload: bytes | None = None, timeout: float = 2.0
            ) -> list[tuple[str, bytes]]:
        """Query ``selector``; the same replies and errors as ``Bus.get``."""
        ok: dict[str, bytes] = {}  # one reply per key: Zenoh's default consolidation
        for reply in self._query(selector, payload, timeout):
            ok[reply.key] = reply.payload
        return list(ok.items())

    def get_replies(self, selector: str, payload: bytes | None = None, timeout: float = 2.0
                    ) -> list[Reply]:
        """Every successful reply, each with its replier's zid, as ``Bus.get_replies``."""
        return self._query(selector, payload, timeout)

    def _query(self, selector: str, payload: bytes | None, timeout: float) -> list[Reply]:
        self._check_open()
        key_expr, params = split_selector(selector)
        targets = self.network.queryables(key_expr)
        request = QueryRequest(key=key_expr, parameters=params, payload=payload)
        replies: list[list[tuple[bool, str, bytes]]] = [[] for _ in targets]
        threads = [threading.Thread(target=_answer, args=(q, request, replies[i]), daemon=True,
                                    name=f"fake-query-{q.key_expr}")
                   for i, q in enumerate(targets)]
        for t in threads:
            t.start()
        deadline = time.monotonic() + timeout
        late = []
        for t in threads:
            t.join(max(0.0, deadline - time.monotonic()))
            late.append(t.is_alive())  # its reply, if any comes, is not part of this answer
        ok: list[Reply] = []
        errors: list[str] = []
        for target, out, too_late in zip(targets, replies, late, strict=True):
            for success, key, data in [] if too_late else out:
                if success:
                    ok.append(Reply(key, data, target.bus.zid))
                else:
                    errors.append(data.decode(errors="replace"))
        if any(late):
            errors.append(_TIMEOUT_REPLY)
        if ok:
            return ok
        if _TIMEOUT_REPLY in errors:
            raise QueryTimeout(f"get {selector!r}: no answer within {timeout:.1f} s")
        if errors:
            raise BusError(f"get {selector!r} failed: {'; '.join(errors)}")
        raise NoResponder(f"get {selector!r}: nothing answers on this key (is the service "
                          "running and connected to the same zenoh network?)")

    # --- liveliness ---

    def declare_token(self, key: str) -> Declaration:
        self._check_open()
        return self.network.declare_token(self, key)

    def alive(self, key_expr: str, timeout: float = 1.0) -> list[str]:
        self._check_open()
        return self.network.alive(key_expr)

    def watch_liveliness(self, key_expr: str, callback: Callable[[str, bool], None],
                         history: bool = True) -> Declaration:
        self._check_open()
        return self.network.watch(self, key_expr, callback, history)


def _answer(queryable: Declaration, request: QueryRequest,
            out: list[tuple[bool, str, bytes]]) -> None:
    """Run one handler as the real bus does: a reply, or an error reply with the reason."""
    try:
        answer = queryable.target(request)
        if isinstance(answer, Future):  # deferred: this query waits for it, later ones do not
            answer = answer.result()
    except QueryRejected as exc:
        out.append((False, queryable.key_expr, str(exc).encode()))
        return
    except Exception as exc:
        log.exception("queryable %s failed", queryable.key_expr)
        out.append((False, queryable.key_expr, f"internal error: {type(exc).__name__}".encode()))
        return
    if not isinstance(answer, QueryAnswer):
        log.error("queryable %s returned %r, not a QueryAnswer", queryable.key_expr, answer)
        return
    out.append((True, queryable.key_expr, bytes(answer.payload)))
