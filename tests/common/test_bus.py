"""The bus across real processes: bad input to a service, liveliness after a kill.

What one session sees of another (pub/sub, queries, errors, tokens) is the contract in
``test_bus_contract.py``, which the in-memory fake passes too.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import time

import pytest

from services.common.bus import (
    Bus,
    BusError,
    ZenohOptions,
    wait_for_services,
)
from services.common.keys import Keys
from services.common.processes import child_env
from services.common.protocol import HandLandmarks, ServiceStats
from tests.common import samples
from tests.conftest import REPO, wait_routed, wait_until

KEYS = Keys("t1")


def _start_echo(router: str, tmp_path) -> subprocess.Popen[str]:  # type: ignore[no-untyped-def]
    log = open(tmp_path / "echo.log", "w")  # noqa: SIM115
    return subprocess.Popen([sys.executable, "-m", "tests.common.echo_service", router, KEYS.rig],
                            stdout=log, stderr=subprocess.STDOUT, env=child_env(), cwd=REPO, text=True)


def test_service_counts_bad_input_and_keeps_serving(client_bus: Bus, router: str,
                                                     tmp_path) -> None:  # type: ignore[no-untyped-def]
    echoed: list[bytes] = []
    client_bus.subscribe(f"{KEYS.root}/test/echo", lambda k, p: echoed.append(p))
    wait_routed(client_bus)  # before the service connects, so it learns the subscription
    echo = _start_echo(router, tmp_path)
    try:
        wait_until(lambda: KEYS.alive("echo") in client_bus.alive(KEYS.alive_all), 20,
                   what="echo service liveliness")
        good = samples.hand_landmarks()
        bad = [b"", b"\xc1", b"\x93\x01\x02", samples.hand_body().to_msgpack(),
               good.to_msgpack()[:-5]]
        for payload in bad:
            client_bus.put(KEYS.hand_landmarks, payload)
        client_bus.put(KEYS.hand_landmarks, good.to_msgpack())
        wait_until(lambda: len(echoed) == 1, 10, what="echo of the valid message")
        assert HandLandmarks.from_msgpack(echoed[0]) == good
        stats = ServiceStats.from_msgpack(client_bus.get(KEYS.stats("echo"))[0][1])
        assert stats.received == 6 and stats.published == 1
        assert sum(stats.rejected.values()) == 5
        assert stats.rejected.get("wrong_schema") == 1
        assert echo.poll() is None
    finally:
        echo.terminate()
        echo.wait(10)
    assert echo.returncode == 0  # SIGTERM -> graceful stop


def test_liveliness_token_vanishes_within_1s_after_kill(client_bus: Bus, router: str,
                                                         tmp_path) -> None:  # type: ignore[no-untyped-def]
    events: list[tuple[float, str, bool]] = []
    client_bus.watch_liveliness(KEYS.alive_all,
                                lambda k, alive: events.append((time.monotonic(), k, alive)))
    echo = _start_echo(router, tmp_path)
    wait_until(lambda: any(a for _, _, a in events), 20, what="token appears")
    t_kill = time.monotonic()
    echo.kill()
    echo.wait(5)
    wait_until(lambda: any(not a for _, _, a in events), 5, what="token disappears")
    t_gone = next(t for t, _, a in events if not a)
    assert t_gone - t_kill < 1.0


def test_a_failing_queryable_is_answered_and_logged_once_a_second(
        client_bus: Bus, caplog: pytest.LogCaptureFixture) -> None:
    def broken(_req):  # type: ignore[no-untyped-def]
        raise ZeroDivisionError("a bug for this input")

    client_bus.declare_queryable("t1/broken", broken)
    t0 = time.monotonic()
    with caplog.at_level(logging.ERROR, logger="services.common.bus"):
        for _ in range(30):
            with pytest.raises(BusError, match="internal error: ZeroDivisionError"):
                client_bus.get("t1/broken")
    lines = [r for r in caplog.records if "t1/broken" in r.getMessage()]
    # 30 failures within a few seconds: one line per second at most, each with its count.
    assert 1 <= len(lines) <= 1 + int(time.monotonic() - t0)
    assert all(r.exc_info is None for r in lines)


def test_wait_for_services_sees_tokens_and_names_the_missing(client_bus: Bus, router: str) -> None:
    options = ZenohOptions(mode="client", connect=(router,), multicast_scouting=False)
    with Bus(options) as other:
        other.declare_token(KEYS.alive("tracker"))
        wait_for_services(client_bus, KEYS, ["tracker"], timeout=20.0)  # returns: token seen
        with pytest.raises(BusError, match="not alive after") as err:
            wait_for_services(client_bus, KEYS, ("tracker", "kinematics"), timeout=0.3)
    assert KEYS.alive("kinematics") in str(err.value)
    assert KEYS.alive("tracker") not in str(err.value)  # only what is missing is named
