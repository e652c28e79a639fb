"""Shared fixtures: a real Zenoh router process on a unix socket, bus sessions, CLI processes."""

from __future__ import annotations

import subprocess
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from services.common.bus import Bus, ZenohOptions
from services.common.processes import REPO, ProcessGroup, child_env, client_args, handkse_cmd
from services.common.service import BusLike


class Processes(ProcessGroup):
    """CLI subprocesses of a test, killed at teardown; ``name`` labels the log file."""

    def __init__(self, tmp: Path) -> None:
        super().__init__(tmp)
        self.tmp = tmp

    def start(self, *args: str, name: str = "proc") -> subprocess.Popen[bytes]:  # type: ignore[override]
        label = f"{name}-{len(self.procs)}"
        p = super().start(label, *args)
        p.log_path = self.log_path(label)  # type: ignore[attr-defined]
        return p

    def run(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
        return subprocess.run(handkse_cmd(*args), capture_output=True, text=True,
                              env=child_env(), cwd=REPO, timeout=timeout, check=False)


def output_of(p: subprocess.Popen[str]) -> str:
    return Path(p.log_path).read_text(errors="replace")  # type: ignore[attr-defined]


def wait_until(predicate: Callable[[], bool], timeout: float = 10.0, period: float = 0.02,
               what: str = "condition") -> None:
    """Poll ``predicate`` until true; fail the test with ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(period)


def wait_routed(subscriber: BusLike, publisher: BusLike | None = None,
                timeout: float = 10.0) -> None:
    """Wait until what ``publisher`` puts reaches the subscriptions ``subscriber`` has declared.

    Zenoh propagates declarations asynchronously, but in order over each session's link: once a
    probe subscription declared now receives a probe that ``publisher`` puts, the subscriptions
    declared before it are routed as well. Without ``publisher`` a new session with
    ``subscriber``'s options sends the probe: then the router knows the subscriptions, and a
    service process that connects afterwards learns them when it opens its session.
    """
    key = f"handkse-test/probe/{uuid.uuid4().hex}"
    arrived = threading.Event()
    probe = subscriber.subscribe(key, lambda _k, _p: arrived.set())
    try:
        if publisher is None:
            assert isinstance(subscriber, Bus), "a fake bus needs an explicit publisher"
            with Bus(subscriber.options) as other:
                _probe_until(other, key, arrived, timeout)
        else:
            _probe_until(publisher, key, arrived, timeout)
    finally:
        probe.undeclare()


def _probe_until(publisher: BusLike, key: str, arrived: threading.Event, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    publisher.put(key, b"")
    while not arrived.wait(0.02):
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for a subscription to be routed")
        publisher.put(key, b"")


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Processes]:
    p = Processes(tmp_path)
    yield p
    p.stop_all()


@pytest.fixture
def router(procs: Processes, tmp_path: Path) -> str:
    """A ``handkse router`` process listening on a unix socket; returns its endpoint."""
    endpoint = f"unixsock-stream/{tmp_path}/router.sock"
    p = procs.start("router", "-l", endpoint, "--no-multicast-scouting", name="router")
    wait_until(lambda: "router ready" in output_of(p) or p.poll() is not None, 20,
               what="router start")
    assert p.poll() is None, output_of(p)
    return endpoint


def zenoh_args(endpoint: str) -> list[str]:
    """CLI arguments for a client of the router at ``endpoint``."""
    return client_args(endpoint)


@pytest.fixture
def client_bus(router: str) -> Iterator[Bus]:
    """An in-test client session connected to the router."""
    with Bus(ZenohOptions(mode="client", connect=(router,), multicast_scouting=False)) as bus:
        yield bus
