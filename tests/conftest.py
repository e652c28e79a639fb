"""Shared fixtures: a real Zenoh router process on a unix socket, bus sessions, CLI processes."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from services.common.bus import Bus, ZenohOptions

REPO = Path(__file__).resolve().parent.parent


def handkse_cmd(*args: str) -> list[str]:
    """Command line running the ``handkse`` CLI with this interpreter."""
    return [sys.executable, "-m", "services", *args]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env["PYTHONUNBUFFERED"] = "1"
    for k in ("ZENOH_CONFIG", "ZENOH_MODE", "ZENOH_CONNECT", "ZENOH_LISTEN"):
        env.pop(k, None)
    return env


class Processes:
    """Starts CLI subprocesses and kills whatever is left at teardown."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.procs: list[subprocess.Popen[str]] = []

    def start(self, *args: str, name: str = "proc") -> subprocess.Popen[str]:
        log = open(self.tmp / f"{name}-{len(self.procs)}.log", "w")  # noqa: SIM115
        p = subprocess.Popen(handkse_cmd(*args), stdout=log, stderr=subprocess.STDOUT,
                             text=True, env=_env(), cwd=REPO)
        p.log_path = log.name  # type: ignore[attr-defined]
        self.procs.append(p)
        return p

    def run(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
        return subprocess.run(handkse_cmd(*args), capture_output=True, text=True, env=_env(),
                              cwd=REPO, timeout=timeout, check=False)

    def stop_all(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)


def output_of(p: subprocess.Popen[str]) -> str:
    return Path(p.log_path).read_text()  # type: ignore[attr-defined]


def wait_until(predicate: Callable[[], bool], timeout: float = 10.0, period: float = 0.02,
               what: str = "condition") -> None:
    """Poll ``predicate`` until true; fail the test with ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(period)


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
    return ["-m", "client", "-e", endpoint, "--no-multicast-scouting"]


@pytest.fixture
def client_bus(router: str) -> Iterator[Bus]:
    """An in-test client session connected to the router."""
    with Bus(ZenohOptions(mode="client", connect=(router,), multicast_scouting=False)) as bus:
        yield bus
