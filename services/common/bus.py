"""The Zenoh bus: session from options, publish/subscribe/query helpers, liveliness.

One module although it is long: it is the only one allowed to import zenoh, so everything that
touches Zenoh's API (options, sessions, queries, liveliness) lives here.

This is the only module that imports zenoh (1.x API). Everything else sees bytes and plain
callbacks, so a service can be driven by an in-memory fake in unit tests.

Pitfalls handled here (docs/deployment.md#zenoh-pitfalls): callbacks swallow exceptions, so every callback is
wrapped and logs what it caught; queries are always finalised (``query.drop()`` in ``finally``);
client mode gets a connect retry so a service may start before its router; sessions are closed
in ``close()``/``with``; a ``get`` that times out or finds no responder raises a clear error.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import Any

import zenoh

from services.common.errors import UserError
from services.common.keys import Keys

log = logging.getLogger(__name__)

MSGPACK = "application/msgpack"
JSON = "application/json"
MODES = ("peer", "client", "router")


class BusError(RuntimeError):
    """A bus operation failed; the message says which key and why."""


class QueryTimeout(BusError):
    """A ``get`` got no complete answer within its timeout."""


class NoResponder(BusError):
    """A ``get`` found no queryable on the key (is the service running and connected?)."""


class QueryRejected(Exception):
    """Raised by a query handler to answer with an error reply carrying this message."""


@dataclass(frozen=True)
class ZenohOptions:
    """How to open a Zenoh session; spelled as in Zenoh's own examples.

    ``config_file`` is a Zenoh JSON5 file; the other fields override it. ``lease_ms`` shortens
    the link lease (outage detection); ``connect_timeout_ms`` bounds how long opening a client
    waits for its router (-1 waits forever).
    """

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = True
    config_file: str | None = None
    lease_ms: int | None = None
    connect_timeout_ms: int = 10000
    shared_memory: bool | None = None
    cfg: tuple[str, ...] = ()  # "KEY:VALUE" JSON5 insertions, applied last (Zenoh's --cfg)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"zenoh mode {self.mode!r} is not one of {list(MODES)}")


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``-m -e -l --no-multicast-scouting -c`` (Zenoh's example spelling) to a parser."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("-m", "--mode", choices=MODES, help="zenoh session mode (default peer)")
    g.add_argument("-e", "--connect", action="append", metavar="ENDPOINT", default=None,
                   help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("-l", "--listen", action="append", metavar="ENDPOINT", default=None,
                   help="endpoint to listen on, e.g. unixsock-stream/tmp/z.sock (repeatable)")
    g.add_argument("--no-multicast-scouting", action="store_true", default=None,
                   help="disable multicast scouting (recommended outside a single laptop)")
    g.add_argument("-c", "--zenoh-config", metavar="FILE",
                   help="zenoh JSON5 config file (the ZENOH_CONFIG environment variable also works)")
    g.add_argument("--cfg", action="append", metavar="KEY:VALUE", default=None,
                   help="set one zenoh config value, e.g. 'transport/auth/usrpwd/user:\"tracker\"'"
                        " (repeatable)")


def options_from_args(args: argparse.Namespace, base: ZenohOptions | None = None) -> ZenohOptions:
    """Resolve options: command line > environment (``ZENOH_*``) > ``base`` (config file)."""
    o = base or ZenohOptions()
    env = os.environ
    if env.get("ZENOH_CONFIG"):
        o = replace(o, config_file=env["ZENOH_CONFIG"])
    if env.get("ZENOH_MODE"):
        o = replace(o, mode=env["ZENOH_MODE"])
    if env.get("ZENOH_CONNECT"):
        o = replace(o, connect=tuple(env["ZENOH_CONNECT"].split(",")))
    if env.get("ZENOH_LISTEN"):
        o = replace(o, listen=tuple(env["ZENOH_LISTEN"].split(",")))
    if getattr(args, "zenoh_config", None):
        o = replace(o, config_file=args.zenoh_config)
    if getattr(args, "mode", None):
        o = replace(o, mode=args.mode)
    if getattr(args, "connect", None):
        o = replace(o, connect=tuple(args.connect))
    if getattr(args, "listen", None):
        o = replace(o, listen=tuple(args.listen))
    if getattr(args, "no_multicast_scouting", None):
        o = replace(o, multicast_scouting=False)
    if getattr(args, "cfg", None):
        o = replace(o, cfg=(*o.cfg, *args.cfg))
    return o


def _zenoh_reason(exc: Exception) -> str:
    """Zenoh's error text without its Rust source location, on one line (``Str("unknown key")
    at .../config.rs:86.`` -> ``unknown key``)."""
    text = re.sub(r"\s+at \S+\.rs:\d+\.?\s*$", "", str(exc))
    inner = re.search(r'msg: "((?:[^"\\]|\\.)*)"', text) or re.fullmatch(r'Str\("(.*)"\)', text)
    if inner:
        text = inner.group(1).replace("\\n", "\n").replace('\\"', '"')
    parse = re.search(r"-->\s*(\d+):(\d+).*=\s*(.+)$", text, re.S)  # a JSON5 syntax error
    if parse:
        text = f"line {parse.group(1)}, column {parse.group(2)}: {parse.group(3)}"
    return " ".join(text.split())


def _config_from_file(path: str) -> zenoh.Config:
    where = "(given with -c, ZENOH_CONFIG or [zenoh] config_file)"
    if not os.path.isfile(path):
        what = "is a folder, not a file" if os.path.isdir(path) else "does not exist"
        raise UserError(f"zenoh config file {path} {what} {where}")
    try:
        return zenoh.Config.from_file(path)
    except Exception as exc:  # zenoh raises ZError for every kind of bad file
        raise UserError(f"zenoh config file {path} is not valid: {_zenoh_reason(exc)}") from exc


def _insert_cfg(conf: zenoh.Config, item: str) -> None:
    """One ``--cfg KEY:VALUE`` insertion; a bad key or value names itself."""
    key, sep, value = item.partition(":")
    if not sep or not key:
        raise UserError(f"--cfg {item!r} must look like KEY:VALUE (VALUE in JSON5), e.g. "
                        "'transport/link/tx/lease:2000'")
    try:
        conf.insert_json5(key, value)
    except Exception as exc:  # zenoh raises ZError for unknown keys and bad values alike
        reason = _zenoh_reason(exc)
        if reason == "unknown key":
            raise UserError(f"--cfg {item!r}: zenoh has no config key {key!r} (keys are paths "
                            "as in Zenoh's DEFAULT_CONFIG.json5, e.g. transport/link/tx/lease)"
                            ) from exc
        raise UserError(f"--cfg {item!r}: bad value for {key}: {reason}") from exc


def zenoh_config(o: ZenohOptions) -> zenoh.Config:
    """Build a ``zenoh.Config``: the JSON5 file (if any), then the explicit options on top.

    A missing or invalid file and a bad ``--cfg`` item raise :class:`UserError` naming them.
    """
    conf = _config_from_file(o.config_file) if o.config_file else zenoh.Config()

    def put(path: str, value: Any) -> None:
        conf.insert_json5(path, json.dumps(value))

    put("mode", o.mode)
    if o.connect:
        put("connect/endpoints", list(o.connect))
    if o.listen:
        put("listen/endpoints", list(o.listen))
    if not o.multicast_scouting:
        put("scouting/multicast/enabled", False)
    if o.connect:
        # Keep retrying the router instead of failing at once (docs/deployment.md#connect-retry).
        put("connect/timeout_ms", {"client": o.connect_timeout_ms, "peer": -1, "router": -1})
        put("connect/retry", {"period_init_ms": 200, "period_max_ms": 1000,
                              "period_increase_factor": 2})
    if o.lease_ms is not None:
        put("transport/link/tx/lease", o.lease_ms)
    if o.shared_memory is not None:
        put("transport/shared_memory/enabled", o.shared_memory)
    for item in o.cfg:
        _insert_cfg(conf, item)
    return conf


Callback = Callable[[str, bytes], None]


class _RateLimitedLog:
    """Logs one line per key per ``period_s`` with the count since the last line; the traceback
    of each failure only at DEBUG (a flood of bad input must not write gigabytes of log)."""

    def __init__(self, period_s: float = 1.0) -> None:
        self.period_s = period_s
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self._count: dict[str, int] = {}

    def exception(self, key: str, message: str) -> None:
        now = time.monotonic()
        with self._lock:
            self._count[key] = self._count.get(key, 0) + 1
            due = now - self._last.get(key, -math.inf) >= self.period_s
            if due:
                self._last[key] = now
                count, self._count[key] = self._count[key], 0
        if due:
            log.error("%s (%d time(s) since the last report): %s", key, count, message)
        log.debug("%s", key, exc_info=True)


_failures = _RateLimitedLog()


def _guarded(name: str, fn: Callable[..., None]) -> Callable[..., None]:
    """Zenoh prints and swallows callback exceptions; log them through ``logging`` instead."""

    def wrapper(*args: Any) -> None:
        try:
            fn(*args)
        except Exception as exc:
            _failures.exception(f"callback for {name} failed", repr(exc))

    return wrapper


@dataclass(frozen=True)
class QueryRequest:
    """What a queryable handler sees: the key, selector parameters and optional payload."""

    key: str
    parameters: dict[str, str]
    payload: bytes | None


@dataclass(frozen=True)
class QueryAnswer:
    payload: bytes
    encoding: str = MSGPACK


# A handler answers at once, or hands back a Future that another thread completes later (a
# deferred answer: the query stays open and the next query is handled meanwhile).
QueryHandler = Callable[[QueryRequest], "QueryAnswer | Future[QueryAnswer]"]


@dataclass(frozen=True)
class Reply:
    """One successful reply to a ``get``: its key, payload and the session id (zid, hex) of
    the session that answered, as Zenoh reports it (None when Zenoh does not say)."""

    key: str
    payload: bytes
    replier: str | None


class LatestSlot:
    """Latest-only queue for camera frames: like ``RingChannel(1)``, but counts what it skips.

    A newer sample replaces an unread one; ``skipped`` counts replaced samples so the consumer
    can report its drops.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: tuple[str, bytes] | None = None
        self.skipped = 0
        self._closed = False

    def push(self, key: str, payload: bytes) -> None:
        with self._cond:
            if self._item is not None:
                self.skipped += 1
            self._item = (key, payload)
            self._cond.notify()

    def take(self, timeout: float | None = None) -> tuple[str, bytes] | None:
        """The newest unread sample, waiting up to ``timeout`` s; None on timeout or close."""
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


@dataclass
class _Declarations:
    items: list[Any] = field(default_factory=list)


class Bus:
    """One Zenoh session and everything declared on it; close it (or use ``with``)."""

    def __init__(self, options: ZenohOptions | None = None) -> None:
        self.options = options or ZenohOptions()
        conf = zenoh_config(self.options)  # a UserError here names the file or --cfg item
        try:
            self.session = zenoh.open(conf)
        except Exception as exc:
            raise BusError(f"cannot open zenoh session ({self.options.mode}, connect="
                           f"{list(self.options.connect)}, listen={list(self.options.listen)}): "
                           f"{exc}") from exc
        self._decl = _Declarations()
        self._lock = threading.Lock()
        self._publishers: dict[tuple[str, bool], Any] = {}

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare everything, then close the session (idempotent)."""
        with self._lock:
            items, self._decl.items = self._decl.items, []
            self._publishers.clear()
        for item in reversed(items):
            try:
                item.undeclare()
            except Exception:  # already gone with a closed session
                log.debug("undeclare failed", exc_info=True)
        if not self.session.is_closed():
            self.session.close()

    def _keep(self, item: Any) -> Any:
        with self._lock:
            self._decl.items.append(item)
        return item

    @property
    def zid(self) -> str:
        return str(self.session.zid())

    # --- publish ---

    def put(self, key: str, payload: bytes, *, frame: bool = False,
            encoding: str = MSGPACK) -> None:
        """Publish ``payload`` on ``key``.

        State messages (``frame=False``) use congestion control BLOCK so none is lost; camera
        frames use DROP, since only the newest frame matters (docs/deployment.md#congestion-control).
        """
        pub_key = (key, frame)
        pub = self._publishers.get(pub_key)
        if pub is None:
            cc = zenoh.CongestionControl.DROP if frame else zenoh.CongestionControl.BLOCK
            pub = self._keep(self.session.declare_publisher(
                key, encoding=zenoh.Encoding(encoding), congestion_control=cc, express=not frame))
            self._publishers[pub_key] = pub
        pub.put(payload)

    # --- subscribe ---

    def subscribe(self, key: str, callback: Callback) -> Any:
        """Call ``callback(key, payload)`` for every sample, in arrival order (FIFO).

        Zenoh invokes callbacks of one subscriber sequentially; a slow callback applies
        back-pressure rather than dropping state messages.
        """

        def on_sample(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                callback(str(sample.key_expr), sample.payload.to_bytes())

        return self._keep(self.session.declare_subscriber(key, _guarded(key, on_sample)))

    def subscribe_latest(self, key: str) -> LatestSlot:
        """Latest-only subscription (camera frames): read with ``slot.take(timeout)``."""
        slot = LatestSlot()
        self.subscribe(key, slot.push)
        return slot

    # --- query ---

    def declare_queryable(self, key: str, handler: QueryHandler) -> Any:
        """Answer queries on ``key`` with ``handler``; every query is finalised.

        Zenoh hands one queryable's queries to its callback one after the other, so a handler
        that waits holds up every later query. A handler that needs long (an articulation)
        returns a ``concurrent.futures.Future`` instead: the query stays open and is answered
        and finalised when another thread completes the future (with a ``QueryAnswer``, or an
        exception), while later queries are handled at once.

        ``QueryRejected`` becomes an error reply with its message; any other exception is logged
        and answered as ``internal error``.
        """

        def on_query(query: zenoh.Query) -> None:
            deferred = False
            try:
                params = {k: v for k, v in _parameters(query.parameters).items()}
                payload = query.payload.to_bytes() if query.payload is not None else None
                request = QueryRequest(key=str(query.key_expr), parameters=params,
                                       payload=payload)
                try:
                    answer = handler(request)
                except Exception as exc:
                    _reply_failure(query, key, exc)
                    return
                if isinstance(answer, Future):
                    deferred = True
                    answer.add_done_callback(lambda done: _reply_later(query, key, done))
                    return
                query.reply(key, answer.payload, encoding=zenoh.Encoding(answer.encoding))
            finally:
                if not deferred:
                    query.drop()

        return self._keep(self.session.declare_queryable(key, _guarded(key, on_query)))

    def get(self, selector: str, payload: bytes | None = None, timeout: float = 2.0
            ) -> list[tuple[str, bytes]]:
        """Query ``selector`` and return ``[(key, payload), ...]`` of the successful replies.

        Raises :class:`NoResponder` when nothing answers, :class:`QueryTimeout` when the timeout
        passes, and :class:`BusError` with the remote message for an error reply.
        """
        replies = self.session.get(selector, payload=payload, timeout=timeout)
        return [(r.key, r.payload) for r in _successful(selector, replies, timeout)]

    def get_replies(self, selector: str, payload: bytes | None = None, timeout: float = 2.0
                    ) -> list[Reply]:
        """Every successful reply to ``selector``, each with the session id of its replier.

        Unlike :meth:`get`, the query goes to every matching queryable and nothing is
        consolidated: two sessions answering on the same key give two replies, so the caller
        can tell them apart (Zenoh's default keeps one of them, whichever). Errors as in
        :meth:`get`.
        """
        replies = self.session.get(selector, payload=payload, timeout=timeout,
                                   target=zenoh.QueryTarget.ALL,
                                   consolidation=zenoh.ConsolidationMode.NONE)
        return _successful(selector, replies, timeout)
    # --- liveliness ---

    def declare_token(self, key: str) -> Any:
        """A liveliness token that exists while this session lives (or until undeclared)."""
        return self._keep(self.session.liveliness().declare_token(key))

    def alive(self, key_expr: str, timeout: float = 1.0) -> list[str]:
        """Keys of the liveliness tokens currently matching ``key_expr``."""
        replies = self.session.liveliness().get(key_expr, timeout=timeout)
        return sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)

    def watch_liveliness(self, key_expr: str, callback: Callable[[str, bool], None],
                         history: bool = True) -> Any:
        """Call ``callback(key, alive)`` when a token matching ``key_expr`` appears or vanishes."""

        def on_sample(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        return self._keep(self.session.liveliness().declare_subscriber(
            key_expr, _guarded(key_expr, on_sample), history=history))


def _successful(selector: str, replies: Any, timeout: float) -> list[Reply]:
    """The successful replies of a ``get``; if there are none, the error that says why."""
    ok: list[Reply] = []
    errors: list[str] = []
    for reply in replies:
        if reply.ok is not None:
            replier = reply.replier_id
            ok.append(Reply(str(reply.ok.key_expr), reply.ok.payload.to_bytes(),
                            None if replier is None else str(replier.zid)))
        else:
            errors.append(reply.err.payload.to_string())
    if ok:
        return ok
    if any(e.strip().lower() == "timeout" for e in errors):
        raise QueryTimeout(f"get {selector!r}: no answer within {timeout:.1f} s")
    if errors:
        raise BusError(f"get {selector!r} failed: {'; '.join(errors)}")
    raise NoResponder(f"get {selector!r}: nothing answers on this key (is the service "
                      "running and connected to the same zenoh network?)")
def _reply_failure(query: zenoh.Query, key: str, exc: BaseException) -> None:
    """The error reply for a handler's exception (``QueryRejected``: its message)."""
    if isinstance(exc, QueryRejected):
        query.reply_err(str(exc).encode())
        return
    _failures.exception(f"queryable {key} failed", repr(exc))
    query.reply_err(f"internal error: {type(exc).__name__}".encode())


def _reply_later(query: zenoh.Query, key: str, done: Future[QueryAnswer]) -> None:
    """Answer and finalise a deferred query (runs in the thread that completed ``done``)."""
    try:
        exc = done.exception() if not done.cancelled() else QueryRejected("query cancelled")
        if exc is not None:
            _reply_failure(query, key, exc)
        else:
            answer = done.result()
            query.reply(key, answer.payload, encoding=zenoh.Encoding(answer.encoding))
    except Exception as exc:  # the session closed meanwhile: nobody to answer
        _failures.exception(f"deferred reply on {key} failed", repr(exc))
    finally:
        query.drop()


def _parameters(params: Any) -> dict[str, str]:
    """Selector parameters as a plain dict (``zenoh.Parameters`` iterates as pairs)."""
    try:
        return {str(k): str(v) for k, v in params}
    except TypeError:
        text = str(params)
        out: dict[str, str] = {}
        for part in filter(None, text.split(";")):
            k, _, v = part.partition("=")
            out[k] = v
        return out


def wait_for_services(bus: Bus, keys: Keys, services: Sequence[str], timeout: float) -> None:
    """Block until every named service's liveliness token is visible on ``bus``.

    ``services``: service names as in :meth:`Keys.alive`; ``timeout`` in seconds. Raises
    :class:`BusError` naming the services still missing when the timeout passes.
    """
    deadline = time.monotonic() + timeout
    wanted = {keys.alive(s) for s in services}
    while True:
        missing = wanted - set(bus.alive(keys.alive_all, timeout=0.5))
        if not missing:
            return
        if time.monotonic() > deadline:
            raise BusError(f"services not alive after {timeout:.0f} s: {sorted(missing)}")
        time.sleep(0.05)
