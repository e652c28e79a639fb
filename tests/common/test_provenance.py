"""Keeping a service's reply only from the session that runs it: the choice on its own, then
over a real router with a real service process and impostor sessions."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from services.common.bus import Bus, QueryAnswer, Reply
from services.common.keys import Keys
from services.common.processes import child_env
from services.common.provenance import (
    AmbiguousReply,
    UntrustedReply,
    ask_service,
    choose,
    sessions_of,
)
from tests.conftest import REPO, wait_until

KEYS = Keys("prov")
MODEL = KEYS.kinematics_model
REAL, FORGER, OTHER = "aa" * 16, "bb" * 16, "cc" * 16


def test_the_reply_of_the_service_session_is_kept_and_the_rest_set_aside() -> None:
    forged, real = Reply(MODEL, b"forged", FORGER), Reply(MODEL, b"real", REAL)
    answer = choose([forged, real], {REAL}, "kinematics", MODEL)
    assert answer.reply == real
    assert answer.untrusted == (forged,)
    # in the other order too: the first reply is not taken blindly
    assert choose([real, forged], {REAL}, "kinematics", MODEL).reply == real


def test_replies_only_from_other_sessions_are_refused() -> None:
    forged = Reply(MODEL, b"forged", FORGER)
    with pytest.raises(UntrustedReply, match="none of which holds the kinematics token") as err:
        choose([forged], {REAL}, "kinematics", MODEL)
    assert err.value.untrusted == (forged,)
    # nobody holds the token (the service is down): nothing is trusted
    with pytest.raises(UntrustedReply, match="sessions running kinematics: none"):
        choose([forged], set(), "kinematics", MODEL)
    # a reply whose replier Zenoh does not report is not trusted either
    with pytest.raises(UntrustedReply):
        choose([Reply(MODEL, b"?", None)], {REAL}, "kinematics", MODEL)


def test_two_token_holders_answering_is_refused() -> None:
    replies = [Reply(MODEL, b"real", REAL), Reply(MODEL, b"forged", FORGER),
               Reply(MODEL, b"third", OTHER)]
    with pytest.raises(AmbiguousReply, match="refusing to choose") as err:
        choose(replies, {REAL, FORGER}, "kinematics", MODEL)
    assert err.value.untrusted == (replies[2],)


def _start_echo(router: str, tmp_path: Path) -> subprocess.Popen[str]:
    log = open(tmp_path / "echo.log", "w")  # noqa: SIM115 - owned by the child
    return subprocess.Popen([sys.executable, "-m", "tests.common.echo_service", router, KEYS.rig],
                            stdout=log, stderr=subprocess.STDOUT, env=child_env(), cwd=REPO,
                            text=True)


def test_a_service_announces_its_session_and_impostors_are_set_aside(
        client_bus: Bus, router: str, tmp_path: Path) -> None:
    echo = _start_echo(router, tmp_path)
    try:
        wait_until(lambda: len(sessions_of(client_bus, KEYS, "echo")) == 1, 20,
                   what="the echo service's session token")
        (zid,) = sessions_of(client_bus, KEYS, "echo")
        stats = KEYS.stats("echo")
        assert [r.replier for r in client_bus.get_replies(stats)] == [zid]

        with Bus(client_bus.options) as impostor:
            # answers on the service's key, even holding the service's plain token
            impostor.declare_queryable(stats, lambda r: QueryAnswer(b"forged stats"))
            impostor.declare_token(KEYS.alive("echo"))
            wait_until(lambda: len(client_bus.get_replies(stats, timeout=1.0)) == 2, 10,
                       what="both replies")
            answer = ask_service(client_bus, KEYS, "echo", stats)
            assert answer.reply.replier == zid and answer.reply.payload != b"forged stats"
            assert [r.payload for r in answer.untrusted] == [b"forged stats"]

            # an impostor that also claims a session token of the service: both hold one, so
            # neither is chosen
            impostor.declare_token(KEYS.session("echo", impostor.zid))
            wait_until(lambda: len(sessions_of(client_bus, KEYS, "echo")) == 2, 10,
                       what="the impostor's session token")
            with pytest.raises(AmbiguousReply):
                ask_service(client_bus, KEYS, "echo", stats)
    finally:
        echo.terminate()
        echo.wait(10)
