"""The service runner's control queryables on the fake bus: ``reset`` acts only on its exact
key, and a running service announces the session that runs it."""

from __future__ import annotations

import pytest

from services.common.bus import BusError
from services.common.keys import Keys
from tests.common.service_harness import ServiceHarness, serving
from tests.conftest import wait_until

KEYS = Keys("svcq")


def test_reset_acts_only_on_its_exact_key() -> None:
    harness = ServiceHarness("tracker", KEYS)
    resets: list[int] = []
    harness.service.on_reset(lambda: resets.append(1))
    with serving(harness.service):
        # exploring every key: stats answers, reset refuses (its error is not among the replies)
        assert [key for key, _ in harness.bus.get(KEYS.all)] == [KEYS.stats("tracker")]
        for selector in (KEYS.reset("*"), "handkse/*/tracker/reset"):
            with pytest.raises(BusError, match="acts only on a query for exactly this key"):
                harness.bus.get(selector)
    assert resets == []
    assert harness.stats().rejected == {"wildcard_query": 3}
    assert harness.reset().ok and resets == [1]


def test_a_running_service_holds_its_session_token() -> None:
    harness = ServiceHarness("kinematics", KEYS)
    with serving(harness.service):
        session = KEYS.session("kinematics", harness.bus.zid)
        # declared when the loop starts, on its thread
        wait_until(lambda: harness.bus.alive(KEYS.sessions("kinematics")) == [session],
                   what="the session token")
        assert harness.bus.alive(KEYS.alive_all) == [KEYS.alive("kinematics")]
