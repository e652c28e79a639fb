"""The deployment's Zenoh access control, enforced by a Python router loaded from
``docker/zenoh/router.json5`` (listen endpoint and credentials file replaced for the test)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from services.common.bus import Bus, BusError, QueryAnswer, ZenohOptions
from services.common.keys import Keys

ROUTER_CONFIG = Path(__file__).resolve().parents[2] / "docker" / "zenoh" / "router.json5"
PASSWORDS = {"operator": "op-secret", "tracker": "tr-secret", "robot": "rb-secret",
             "kinematics": "kin-secret"}
KEYS = Keys("acl")


@pytest.fixture
def endpoint(tmp_path: Path) -> Iterator[str]:
    creds = tmp_path / "credentials.txt"
    creds.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))
    ep = f"unixsock-stream/{tmp_path}/router.sock"
    options = ZenohOptions(config_file=str(ROUTER_CONFIG), mode="router", listen=(ep,),
                           cfg=(f'transport/auth/usrpwd/dictionary_file:"{creds}"',))
    with Bus(options):
        yield ep


def client(endpoint: str, user: str, password: str) -> Bus:
    return Bus(ZenohOptions(mode="client", connect=(endpoint,), multicast_scouting=False,
                            connect_timeout_ms=2000,
                            cfg=(f'transport/auth/usrpwd/user:"{user}"',
                                 f'transport/auth/usrpwd/password:"{password}"')))


def test_only_the_operator_may_articulate_and_reset(endpoint: str) -> None:
    with (client(endpoint, "robot", PASSWORDS["robot"]) as robot,
          client(endpoint, "kinematics", PASSWORDS["kinematics"]) as kinematics,
          client(endpoint, "operator", PASSWORDS["operator"]) as operator,
          client(endpoint, "tracker", PASSWORDS["tracker"]) as tracker):
        robot.declare_queryable(KEYS.robot_articulate, lambda r: QueryAnswer(b"moved"))
        kinematics.declare_queryable(KEYS.reset("kinematics"), lambda r: QueryAnswer(b"reset"))
        kinematics.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(b"model"))

        assert operator.get(KEYS.robot_articulate, timeout=2.0)[0][1] == b"moved"
        assert operator.get(KEYS.reset("kinematics"), timeout=2.0)[0][1] == b"reset"
        # a service identity asks only for what it needs (the robot bridge: the model) and may
        # not move the robot or reset anything (tests/deploy/test_least_privilege.py: the rest)
        assert robot.get(KEYS.kinematics_model, timeout=2.0)[0][1] == b"model"
        with pytest.raises(BusError):
            tracker.get(KEYS.kinematics_model, timeout=1.0)
        with pytest.raises(BusError):
            tracker.get(KEYS.robot_articulate, timeout=1.0)
        with pytest.raises(BusError):
            tracker.get(KEYS.reset("kinematics"), timeout=1.0)


def test_a_peer_without_credentials_is_refused(endpoint: str) -> None:
    with pytest.raises(BusError, match="cannot open zenoh session"):
        client(endpoint, "tracker", "wrong-password")
    with pytest.raises(BusError, match="cannot open zenoh session"):
        Bus(ZenohOptions(mode="client", connect=(endpoint,), multicast_scouting=False,
                         connect_timeout_ms=2000))
