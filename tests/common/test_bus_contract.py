"""One contract for the bus, run against the in-memory fake and a real Zenoh router.

Every test here runs twice: with two :class:`FakeBus` sessions on one network, and with two
real client sessions of a router on a unix socket. A behaviour the node unit tests rely on is
pinned down here, so the fake cannot drift from the real bus. Tests wait on conditions (which
hold at once on the fake), never for a fixed time.
"""

from __future__ import annotations

import inspect
import threading
import uuid
from collections.abc import Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import pytest

from services.common.bus import (
    JSON,
    Bus,
    BusError,
    NoResponder,
    QueryAnswer,
    QueryRejected,
    QueryRequest,
    QueryTimeout,
    ZenohOptions,
)
from tests.common.fake_bus import FakeBus, FakeNetwork, intersects
from tests.conftest import Processes, output_of, wait_routed, wait_until

Sample = tuple[str, bytes]


@pytest.fixture(scope="module")
def router_endpoint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """One real router for this module's tests (each test uses keys of its own)."""
    tmp: Path = tmp_path_factory.mktemp("contract")
    procs = Processes(tmp)
    endpoint = f"unixsock-stream/{tmp}/router.sock"
    p = procs.start("router", "-l", endpoint, "--no-multicast-scouting", name="router")
    try:
        wait_until(lambda: "router ready" in output_of(p) or p.poll() is not None, 20,
                   what="router start")
        assert p.poll() is None, output_of(p)
        yield endpoint
    finally:
        procs.stop_all()


@pytest.fixture(params=["fake", "zenoh"])
def pair(request: pytest.FixtureRequest) -> Iterator[tuple[Any, Any]]:
    """Two sessions on one network: ``(a, b)``."""
    if request.param == "fake":
        network = FakeNetwork()
        with FakeBus(network) as a, FakeBus(network) as b:
            yield a, b
    else:
        endpoint = request.getfixturevalue("router_endpoint")
        options = ZenohOptions(mode="client", connect=(endpoint,), multicast_scouting=False)
        with Bus(options) as a, Bus(options) as b:
            yield a, b


@pytest.fixture
def root() -> str:
    """A key prefix no other test uses."""
    return f"contract/{uuid.uuid4().hex[:12]}"


def _collect(into: list[Sample]) -> Any:
    return lambda key, payload: into.append((key, payload))


def _answers(bus: Any, selector: str) -> bool:
    try:
        bus.get(selector, timeout=1.0)
    except NoResponder:
        return False
    return True


def test_put_reaches_matching_subscribers_in_order(pair: tuple[Any, Any], root: str) -> None:
    a, b = pair
    exact: list[Sample] = []
    one_chunk: list[Sample] = []
    any_chunks: list[Sample] = []
    unrelated: list[Sample] = []
    own: list[Sample] = []
    key = f"{root}/data/x"
    b.subscribe(key, _collect(exact))
    b.subscribe(f"{root}/data/*", _collect(one_chunk))
    b.subscribe(f"{root}/**", _collect(any_chunks))
    b.subscribe(f"{root}/other", _collect(unrelated))
    a.subscribe(key, _collect(own))  # a session also receives its own samples
    wait_routed(b, a)
    wait_routed(a, a)

    for i in range(20):
        a.put(key, bytes([i]))
    a.put(f"{root}/data/x/deeper", b"deeper")
    wait_until(lambda: (len(exact), len(one_chunk), len(any_chunks), len(own)) == (20, 20, 21, 20),
               what="every sample at every matching subscriber")

    expected = [(key, bytes([i])) for i in range(20)]
    assert exact == expected and one_chunk == expected and own == expected  # FIFO, keys as put
    assert [s for s in any_chunks if s[0] == key] == expected
    assert (f"{root}/data/x/deeper", b"deeper") in any_chunks
    assert unrelated == []


def test_an_undeclared_subscription_gets_nothing_more(pair: tuple[Any, Any], root: str) -> None:
    a, b = pair
    got: list[Sample] = []
    sentinel: list[Sample] = []
    sub = b.subscribe(f"{root}/k", _collect(got))
    b.subscribe(f"{root}/sentinel", _collect(sentinel))
    wait_routed(b, a)
    a.put(f"{root}/k", b"1")
    wait_until(lambda: len(got) == 1, what="the first sample")
    sub.undeclare()
    a.put(f"{root}/k", b"2")
    a.put(f"{root}/sentinel", b"s")
    wait_until(lambda: len(sentinel) == 1, what="the sentinel")
    assert got == [(f"{root}/k", b"1")]


def test_a_latest_subscription_keeps_the_newest_and_counts_the_rest(pair: tuple[Any, Any],
                                                                    root: str) -> None:
    a, b = pair
    key = f"{root}/frames"
    slot = b.subscribe_latest(key)
    every: list[Sample] = []
    b.subscribe(key, _collect(every))
    wait_routed(b, a)
    for i in range(3):
        a.put(key, bytes([i]), frame=True)
    wait_until(lambda: len(every) == 3 and slot.skipped == 2, what="three frames")
    assert slot.take(timeout=1.0) == (key, b"\x02")
    assert slot.take(timeout=0.0) is None


def test_a_queryable_answers_with_its_key_and_reports_errors(pair: tuple[Any, Any],
                                                              root: str) -> None:
    a, b = pair
    key = f"{root}/q"
    seen: list[QueryRequest] = []

    def handler(request: QueryRequest) -> QueryAnswer:
        seen.append(request)
        if "fail" in request.parameters:
            raise QueryRejected("asked to fail")
        if "crash" in request.parameters:
            raise ValueError("a bug in the handler")
        if "json" in request.parameters:
            return QueryAnswer(b'{"ok": true}', JSON)
        return QueryAnswer(b"answer:" + (request.payload or b""))

    a.declare_queryable(key, handler)
    wait_until(lambda: _answers(b, key), what="the queryable")

    assert b.get(key, payload=b"x") == [(key, b"answer:x")]
    assert seen[-1].key == key and seen[-1].payload == b"x" and seen[-1].parameters == {}
    assert b.get(f"{key}?a=1;b=two") == [(key, b"answer:")]
    assert seen[-1].parameters == {"a": "1", "b": "two"} and seen[-1].payload is None
    assert b.get(f"{key}?json=1") == [(key, b'{"ok": true}')]
    with pytest.raises(BusError, match="asked to fail") as rejected:
        b.get(f"{key}?fail=1")
    assert not isinstance(rejected.value, (NoResponder, QueryTimeout))
    with pytest.raises(BusError, match="internal error: ValueError"):
        b.get(f"{key}?crash=1")


def test_a_deferred_answer_does_not_hold_up_later_queries(pair: tuple[Any, Any],
                                                           root: str) -> None:
    """A handler may return a Future (a long job): that query is answered when another thread
    completes it, and the queries after it are answered meanwhile."""
    a, b = pair
    key = f"{root}/deferred"
    pending: list[Future[QueryAnswer]] = []

    def handler(request: QueryRequest) -> QueryAnswer | Future[QueryAnswer]:
        if request.payload in (b"later", b"fail later"):
            job: Future[QueryAnswer] = Future()
            pending.append(job)
            return job
        return QueryAnswer(b"now")

    a.declare_queryable(key, handler)
    wait_until(lambda: _answers(b, key), what="the queryable")
    replies: list[Any] = []

    def ask(payload: bytes) -> None:
        try:
            replies.append(b.get(key, payload=payload, timeout=20.0))
        except BusError as exc:
            replies.append(exc)

    waiting = threading.Thread(target=ask, args=(b"later",))
    waiting.start()
    wait_until(lambda: len(pending) == 1, what="the deferred query")
    assert b.get(key, payload=b"quick") == [(key, b"now")]  # while the first is open
    assert not replies
    pending[0].set_result(QueryAnswer(b"done"))
    waiting.join(20.0)
    assert replies == [[(key, b"done")]]
    failing = threading.Thread(target=ask, args=(b"fail later",))
    failing.start()
    wait_until(lambda: len(pending) == 2, what="the second deferred query")
    pending[1].set_exception(QueryRejected("refused later"))
    failing.join(20.0)
    assert isinstance(replies[-1], BusError) and "refused later" in str(replies[-1])


def test_a_wildcard_get_collects_a_reply_from_every_queryable(pair: tuple[Any, Any],
                                                               root: str) -> None:
    a, b = pair
    a.declare_queryable(f"{root}/q/one", lambda _r: QueryAnswer(b"1"))
    b.declare_queryable(f"{root}/q/two", lambda _r: QueryAnswer(b"2"))
    b.declare_queryable(f"{root}/elsewhere", lambda _r: QueryAnswer(b"no"))

    def replies() -> list[Sample]:
        try:
            return sorted(b.get(f"{root}/q/*"))
        except NoResponder:
            return []

    wait_until(lambda: len(replies()) == 2, what="both queryables")
    assert replies() == [(f"{root}/q/one", b"1"), (f"{root}/q/two", b"2")]


def test_get_replies_keeps_every_reply_and_names_its_session(pair: tuple[Any, Any],
                                                               root: str) -> None:
    a, b = pair
    key = f"{root}/two"
    a.declare_queryable(key, lambda _r: QueryAnswer(b"a"))
    b.declare_queryable(key, lambda _r: QueryAnswer(b"b"))

    def heard() -> list[tuple[bytes, str | None]]:
        try:
            return sorted((r.payload, r.replier) for r in b.get_replies(key, timeout=1.0))
        except NoResponder:
            return []

    wait_until(lambda: len(heard()) == 2, what="both queryables")
    for _ in range(5):  # nothing consolidated away, whichever answers first
        assert heard() == [(b"a", a.zid), (b"b", b.zid)]
    assert {r.key for r in b.get_replies(key)} == {key}
    assert len(b.get(key)) == 1  # while `get` keeps one reply per key
    with pytest.raises(NoResponder):
        b.get_replies(f"{root}/nobody", timeout=0.5)


def test_get_without_responder_is_a_clear_error(pair: tuple[Any, Any], root: str) -> None:
    _, b = pair
    with pytest.raises(NoResponder, match="nothing answers"):
        b.get(f"{root}/nobody", timeout=0.5)


def test_get_gives_up_at_its_timeout(pair: tuple[Any, Any], root: str) -> None:
    a, b = pair
    release = threading.Event()
    finished = threading.Event()

    def slow(request: QueryRequest) -> QueryAnswer:
        if "probe" not in request.parameters:
            release.wait(30)
            finished.set()
        return QueryAnswer(b"late")

    a.declare_queryable(f"{root}/slow", slow)
    wait_until(lambda: _answers(b, f"{root}/slow?probe=1"), what="the queryable")
    try:
        with pytest.raises(QueryTimeout, match="within"):
            b.get(f"{root}/slow", timeout=0.5)
        assert not finished.is_set()  # get returned at its timeout, not when the handler did
    finally:
        release.set()
    wait_until(finished.is_set, what="the slow handler")


def test_liveliness_tokens_appear_and_vanish(pair: tuple[Any, Any], root: str) -> None:
    a, b = pair
    pattern = f"{root}/alive/*"
    events: list[tuple[str, bool]] = []
    b.watch_liveliness(pattern, lambda k, alive: events.append((k, alive)))
    wait_routed(b, a)
    one = a.declare_token(f"{root}/alive/one")
    wait_until(lambda: (f"{root}/alive/one", True) in events, what="token one appears")
    assert b.alive(pattern) == [f"{root}/alive/one"]
    assert b.alive(f"{root}/elsewhere/*") == []

    history: list[tuple[str, bool]] = []
    b.watch_liveliness(pattern, lambda k, alive: history.append((k, alive)), history=True)
    wait_until(lambda: history == [(f"{root}/alive/one", True)], what="history of token one")
    live_only: list[tuple[str, bool]] = []
    b.watch_liveliness(pattern, lambda k, alive: live_only.append((k, alive)), history=False)
    wait_routed(b, a)

    one.undeclare()
    wait_until(lambda: (f"{root}/alive/one", False) in events, what="token one vanishes")
    assert b.alive(pattern) == []
    a.declare_token(f"{root}/alive/two")
    wait_until(lambda: (f"{root}/alive/two", True) in live_only, what="token two appears")
    assert live_only == [(f"{root}/alive/one", False), (f"{root}/alive/two", True)]

    a.close()  # a session's tokens end with it
    wait_until(lambda: (f"{root}/alive/two", False) in events, what="token two vanishes")
    assert b.alive(pattern) == []


def test_tokens_of_one_key_count_as_one(pair: tuple[Any, Any], root: str) -> None:
    """A service that declares its token again (a second ``run``) stays alive once."""
    a, b = pair
    key, sentinel = f"{root}/alive/svc", f"{root}/alive/sentinel"
    events: list[tuple[str, bool]] = []
    b.watch_liveliness(f"{root}/alive/*", lambda k, alive: events.append((k, alive)))
    wait_routed(b, a)
    first = a.declare_token(key)
    second = a.declare_token(key)
    wait_until(lambda: (key, True) in events, what="the token")
    assert b.alive(f"{root}/alive/*") == [key]
    first.undeclare()
    a.declare_token(sentinel)
    wait_until(lambda: (sentinel, True) in events, what="the sentinel token")
    assert (key, False) not in events and b.alive(f"{root}/alive/*") == [sentinel, key]
    second.undeclare()
    wait_until(lambda: (key, False) in events, what="the last token of the key vanishes")
    assert events.count((key, True)) == 1


@pytest.mark.parametrize("bad", ["", "a//b", "a/b/"])
def test_invalid_key_expressions_are_refused(pair: tuple[Any, Any], bad: str) -> None:
    a, _ = pair
    with pytest.raises(Exception, match=r"(?i)invalid key expr"):
        a.subscribe(bad, lambda _k, _p: None)
    with pytest.raises(Exception, match=r"(?i)invalid key expr"):
        a.put(bad, b"x")


def test_the_fake_has_the_interface_of_the_bus() -> None:
    """Same public methods with the same parameters (names, kinds, defaults) as ``Bus``."""
    public = {n for n, _ in inspect.getmembers(Bus) if not n.startswith("_")}
    assert public <= set(dir(FakeBus)), public - set(dir(FakeBus))
    for name in sorted(public | {"__enter__", "__exit__"}):
        real, fake = getattr(Bus, name), getattr(FakeBus, name)
        assert isinstance(real, property) == isinstance(fake, property), name
        if callable(real):
            shape = [(p.name, p.kind, p.default) for p in inspect.signature(real).parameters.values()]
            fake_shape = [(p.name, p.kind, p.default)
                          for p in inspect.signature(fake).parameters.values()]
            assert fake_shape == shape, name


def test_key_expression_intersection() -> None:
    """The fake's routing rule: ``*`` is one chunk, ``**`` any number (zero included)."""
    assert intersects("a/b", "a/b") and not intersects("a/b", "a/c")
    assert intersects("a/*", "a/b") and not intersects("a/*", "a/b/c") and not intersects("a/*", "a")
    assert intersects("a/**", "a") and intersects("a/**", "a/b/c") and intersects("**", "x")
    assert intersects("a/**/c", "a/c") and intersects("a/**/c", "a/b/b/c")
    assert not intersects("a/**/c", "a/b/d")
    assert intersects("a/*/c", "a/**") and intersects("*/b", "a/*")
    with pytest.raises(ValueError, match="not supported"):
        intersects("a/b$*", "a/bc")
