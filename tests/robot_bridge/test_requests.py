"""One request at a time, and nothing started whose caller has stopped waiting.

The node runs on the in-memory bus of :mod:`tests.robot_bridge.test_stale_model` with a fake
monotonic clock that the scripted kinematics query advances (a slow model query); the
real-process versions are in :mod:`tests.robot_bridge.test_service`.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.bus import QueryAnswer, QueryRequest
from services.common.protocol import ArticulateRequest, ArticulateResult, KinematicModel
from services.robot_bridge.config import RobotBridgeConfig
from tests.robot_bridge.test_stale_model import KEYS, Rig, _key_model

DRY = ArticulateRequest(amount=math.pi / 4, duration_s=2.0, dry_run=True)  # 2.5 s with the hold


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig(RobotBridgeConfig(sim_realtime_factor=0.0))
    yield r
    r.close()


def _ask(rig: Rig, request: ArticulateRequest) -> QueryAnswer | Future[QueryAnswer]:
    """The articulate handler's own answer: a ``QueryAnswer`` now, or a future."""
    handler = rig.handler(KEYS.robot_articulate)
    return handler(QueryRequest(KEYS.robot_articulate, {}, request.to_msgpack()))


def _result(answer: QueryAnswer | Future[QueryAnswer]) -> ArticulateResult:
    if isinstance(answer, Future):
        answer = answer.result(timeout=30.0)
    return ArticulateResult.from_msgpack(answer.payload)


def _slow_model(rig: Rig, seconds: float) -> None:
    """The kinematics query takes ``seconds`` on the node's clock, then answers a model."""

    def serve() -> KinematicModel:
        rig.clock.t += seconds
        return _key_model()

    rig.serve = serve


def test_a_request_while_one_is_served_is_busy_at_once(rig: Rig) -> None:
    asked, released = threading.Event(), threading.Event()

    def blocked() -> KinematicModel:
        asked.set()
        assert released.wait(10.0)
        return _key_model()

    rig.serve = blocked
    first = _ask(rig, DRY)
    assert isinstance(first, Future) and asked.wait(10.0)
    for request in (DRY, ArticulateRequest(amount=0.3, duration_s=2.0, model=_key_model())):
        second = _ask(rig, request)  # answered by the handler itself: never queued
        assert isinstance(second, QueryAnswer)
        assert (_result(second).success, _result(second).reason) == (False, "busy")
    assert not first.done()
    released.set()
    assert _result(first).reason == "dry_run"
    rig.serve = _key_model
    assert rig.articulate().reason == "dry_run"  # the slot is free once answered
    assert rig.fetches == 2  # the busy requests never asked for a model
    assert rig.service.stats().skipped == {"busy": 2}


def test_a_caller_that_gave_up_during_the_model_query_is_not_started(rig: Rig) -> None:
    q0 = rig.node.backend.read().q.copy()
    _slow_model(rig, 1.5)
    request = ArticulateRequest(amount=0.3, duration_s=2.0, timeout_s=1.0)
    result = rig.articulate(request)
    assert (result.success, result.reason) == (False, "caller_gone")
    assert rig.node.bridge.last_execution is None
    assert np.allclose(rig.node.backend.read().q, q0)
    assert rig.service.stats().skipped == {"caller_gone": 1}


def test_a_request_without_timeout_gets_the_default(rig: Rig) -> None:
    assert RobotBridgeConfig().request_timeout_s == 10.0
    _slow_model(rig, 10.5)
    assert rig.articulate().reason == "caller_gone"
    _slow_model(rig, 5.0)
    assert rig.articulate().reason == "dry_run"


def test_the_motion_must_end_within_the_callers_timeout(rig: Rig) -> None:
    # 2 s of motion, 0.5 s hold and 0.5 s to reply: 3 s
    assert rig.articulate(ArticulateRequest(amount=math.pi / 4, duration_s=2.0, dry_run=True,
                                            model=_key_model(), timeout_s=2.9)).reason == \
        "timeout_too_short"
    assert rig.articulate(ArticulateRequest(amount=math.pi / 4, duration_s=2.0, dry_run=True,
                                            model=_key_model(), timeout_s=3.1)).reason == \
        "dry_run"
    # time spent on the model query counts: 3.1 s - 1 s is too short
    _slow_model(rig, 1.0)
    assert rig.articulate(ArticulateRequest(amount=math.pi / 4, duration_s=2.0, dry_run=True,
                                            timeout_s=3.1)).reason == "timeout_too_short"


def test_a_request_stamped_longer_ago_than_its_timeout_is_not_started(rig: Rig) -> None:
    now = time.time_ns()
    late = ArticulateRequest(stamp_ns=now - 5 * 10**9, amount=math.pi / 4, duration_s=2.0,
                             dry_run=True, model=_key_model(), timeout_s=4.0)
    assert rig.articulate(late).reason == "caller_gone"
    recent = ArticulateRequest(stamp_ns=now - 10**8, amount=math.pi / 4, duration_s=2.0,
                               dry_run=True, model=_key_model(), timeout_s=4.0)
    assert rig.articulate(recent).reason == "dry_run"
    # a stamp ahead of this clock (another host's clock) does not shorten the timeout
    ahead = ArticulateRequest(stamp_ns=now + 60 * 10**9, amount=math.pi / 4, duration_s=2.0,
                              dry_run=True, model=_key_model(), timeout_s=4.0)
    assert rig.articulate(ahead).reason == "dry_run"
