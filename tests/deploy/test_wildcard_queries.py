"""Queries that do what they say (issue 13, finding 7): a wildcard ``get`` explores the keys
but resets nothing. Real tracker and kinematics processes on a router without access control
(the single-host layout), so only the services' own check stands in the way."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.common.bus import Bus, BusError
from services.common.keys import Keys
from services.common.protocol import Ack, KinematicModel, ServiceStats
from tests.conftest import Processes, output_of, wait_until, zenoh_args
from tests.kinematics.test_service import revolute_bodies

KEYS = Keys("wild")


def _start(procs: Processes, router: str, service: str, state: Path) -> None:
    p = procs.start(service, "--rig", KEYS.rig, "--state-file", str(state), *zenoh_args(router),
                    name=service)
    wait_until(lambda: f"{service} ready" in output_of(p) or p.poll() is not None, 30,
               what=f"{service} start")
    assert p.poll() is None, output_of(p)


def _updates(bus: Bus) -> int:
    return KinematicModel.from_msgpack(bus.get(KEYS.kinematics_model)[0][1]).updates


def _refused(bus: Bus, service: str) -> int:
    stats = ServiceStats.from_msgpack(bus.get(KEYS.stats(service))[0][1])
    return stats.rejected.get("wildcard_query", 0)


def test_a_wildcard_get_resets_neither_tracker_nor_kinematics(
        procs: Processes, router: str, client_bus: Bus, tmp_path: Path) -> None:
    tracker_state = tmp_path / "tracker.state"
    _start(procs, router, "tracker", tracker_state)
    _start(procs, router, "kinematics", tmp_path / "kinematics.state")
    wait_until(lambda: {KEYS.alive("tracker"), KEYS.alive("kinematics")}
               <= set(client_bus.alive(KEYS.alive_all)), 20, what="both services")
    for body in revolute_bodies(30):
        client_bus.put(KEYS.hand_body, body.to_msgpack())
    wait_until(lambda: _updates(client_bus) == 30, 20, what="30 updates")
    assert not tracker_state.exists()  # the tracker writes it on a reset (no landmarks yet)

    # exploring every key answers the data queryables (model, stats) ...
    explored = {key for key, _ in client_bus.get(KEYS.all, timeout=5.0)}
    assert {KEYS.kinematics_model, KEYS.stats("tracker"), KEYS.stats("kinematics")} <= explored
    # ... and the reset queryables refuse, each saying why
    with pytest.raises(BusError) as refused:
        client_bus.get(KEYS.reset("*"), timeout=5.0)
    for service in ("tracker", "kinematics"):
        assert f"{service}: {KEYS.reset(service)} acts only on a query for exactly this key" \
            in str(refused.value)
        assert _refused(client_bus, service) == 2  # the `**` and the `*/reset` query
    assert _updates(client_bus) == 30
    assert not tracker_state.exists()

    # the exact key still resets
    for service in ("tracker", "kinematics"):
        assert Ack.from_msgpack(client_bus.get(KEYS.reset(service))[0][1]).ok
    assert _updates(client_bus) == 0
    assert tracker_state.exists()
