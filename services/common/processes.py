"""Running handkse services as child processes: the one scaffolding the demo, the tests and the
benchmarks share.

A :class:`ProcessGroup` starts ``python -m services <command> ...`` children with logs in a
work directory and tears every one of them down on exit (``terminate``, then ``kill`` after 5 s).
:meth:`ProcessGroup.start_pipeline` brings up the usual layout: a router listening on one endpoint
and the filter services as its clients.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
ZENOH_ENV = ("ZENOH_CONFIG", "ZENOH_MODE", "ZENOH_CONNECT", "ZENOH_LISTEN")


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/host:port`` endpoint on a port that was free a moment ago."""
    with socket.socket() as s:
        s.bind((host, 0))
        return f"tcp/{host}:{s.getsockname()[1]}"


def client_args(endpoint: str, rig: str | None = None) -> list[str]:
    """CLI arguments for a client of the router at ``endpoint`` (multicast scouting off)."""
    args = ["-m", "client", "-e", endpoint, "--no-multicast-scouting"]
    return [*args, "--rig", rig] if rig else args


def child_env(extra: Mapping[str, str] | None = None) -> dict[str, str]:
    """This environment with the repository importable, unbuffered output and no Zenoh
    environment overrides (a stray ``ZENOH_CONFIG`` must not change what a child connects to)."""
    env = {k: v for k, v in os.environ.items() if k not in ZENOH_ENV}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


def handkse_cmd(*args: str) -> list[str]:
    """Command line running the ``handkse`` CLI with this interpreter."""
    return [sys.executable, "-m", "services", *args]


class ProcessGroup:
    """Child processes of this one, each logging to ``workdir/<name>.log``; all stopped on exit.

    ``prefix`` is prepended to every command line (for example ``ip netns exec ns1``).
    """

    def __init__(self, workdir: Path, prefix: Sequence[str] = ()) -> None:
        self.workdir = Path(workdir)
        self.prefix = list(prefix)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def start(self, name: str, *args: str, prefix: Sequence[str] | None = None
              ) -> subprocess.Popen[bytes]:
        """Start ``handkse <args>`` as ``name``; a name already running is an error."""
        return self.spawn(name, handkse_cmd(*args), prefix)

    def spawn(self, name: str, argv: Sequence[str], prefix: Sequence[str] | None = None
              ) -> subprocess.Popen[bytes]:
        """Start any command line as ``name`` (logs, environment and teardown as ``start``)."""
        old = self.procs.get(name)
        if old is not None and old.poll() is None:
            raise RuntimeError(f"process {name!r} is already running (pid {old.pid})")
        log = open(self.log_path(name), "ab")  # noqa: SIM115 - owned by the child
        cmd = [*(self.prefix if prefix is None else prefix), *argv]
        p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=child_env(),
                             cwd=REPO)
        log.close()
        self.procs[name] = p
        return p

    def log_path(self, name: str) -> Path:
        return self.workdir / f"{name}.log"

    def log(self, name: str) -> str:
        path = self.log_path(name)
        return path.read_text(errors="replace") if path.exists() else ""

    def running(self, name: str) -> bool:
        p = self.procs.get(name)
        return p is not None and p.poll() is None

    def wait_log(self, name: str, text: str, timeout: float = 30.0) -> None:
        """Wait until ``text`` appears in the log of ``name``; raise if it exits or times out."""
        deadline = time.monotonic() + timeout
        while text not in self.log(name):
            if not self.running(name):
                raise RuntimeError(f"{name} exited before {text!r}:\n{self.log(name)}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"{name}: no {text!r} within {timeout} s:\n{self.log(name)}")
            time.sleep(0.02)

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` (default SIGKILL, a crash) to ``name`` and reap it."""
        p = self.procs[name]
        if p.poll() is None:
            p.send_signal(sig)
        p.wait(10)

    def start_router(self, listen: str, *extra: str, name: str = "router") -> None:
        self.start(name, "router", "-l", listen, "--no-multicast-scouting", *extra)
        self.wait_log(name, "router ready")

    def start_pipeline(self, endpoint: str, rig: str, services: Sequence[str] = ("tracker",
                       "kinematics"), state_dir: Path | None = None) -> None:
        """Router on ``endpoint`` plus ``services`` as its clients; kinematics and tracker keep
        state files in ``state_dir`` (default: the work directory)."""
        self.start_router(endpoint)
        for service in services:
            self.start_service(service, endpoint, rig, state_dir)

    def start_service(self, service: str, endpoint: str, rig: str,
                      state_dir: Path | None = None, extra: Sequence[str] = ()
                      ) -> subprocess.Popen[bytes]:
        """``handkse <service>`` as a client of ``endpoint``; ``extra`` CLI arguments are
        appended (e.g. ``--set zenoh.lease_ms=2000``)."""
        state: list[str] = []
        if service in STATEFUL:
            state = ["--state-file", str((state_dir or self.workdir) / f"{service}.state")]
        return self.start(service, service, *client_args(endpoint, rig), *state, *extra)

    def stop_all(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.terminate()
        for p in self.procs.values():
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)

    def __enter__(self) -> ProcessGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()


STATEFUL = ("tracker", "kinematics")


def wait_for(predicate: Callable[[], bool], timeout: float, what: str,
             period: float = 0.02) -> None:
    """Poll ``predicate`` until true; raise :class:`TimeoutError` naming ``what``."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(period)
