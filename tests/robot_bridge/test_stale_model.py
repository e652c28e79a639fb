"""The robot bridge refuses to act on a stale model when the kinematics service is unreachable.

The node runs on an in-memory bus (scripted subscriptions, liveliness and queries) with a fake
monotonic clock; the simulated Panda (MuJoCo) only plans, every request is a dry run.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.bus import NoResponder, QueryAnswer, QueryRequest, QueryTimeout
from services.common.keys import Keys
from services.common.protocol import (
    ArticulateRequest,
    ArticulateResult,
    KinematicModel,
    RevoluteParams,
)
from services.common.service import Service
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.factory import make_backend
from services.robot_bridge.mujoco_backend import nominal_grasp_pose
from services.robot_bridge.safety import check_cached_model
from services.robot_bridge.service import RobotBridgeNode
from tests.common.fake_bus import Declaration, FakeBus

KEYS = Keys("unit")
DRY = ArticulateRequest(amount=math.pi / 4, duration_s=2.0, dry_run=True)


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class Rig:
    """A node on a :class:`MemoryBus`; ``serve`` scripts what the kinematics ``get`` does."""

    def __init__(self, config: RobotBridgeConfig) -> None:
        self.bus = FakeBus()                      # the node's session
        self.peer = FakeBus(self.bus.network)     # kinematics and the caller, on the same network
        self._tokens: dict[str, Declaration] = {}
        self.clock = FakeClock()
        self.service = Service("robot_bridge", self.bus, KEYS)
        self.serve: Callable[[], KinematicModel | None] = self._unreachable
        # what the kinematics/models query answers (every contact phase's model)
        self.serve_models: Callable[[], tuple[KinematicModel, ...]] = lambda: ()
        self.fetches = 0
        self.node = RobotBridgeNode(self.service, make_backend(config), config, self._fetch,
                                    clock=self.clock, fetch_models=self._fetch_models)
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self.node.run_robot, args=(self.stop,),
                                         daemon=True),
                        threading.Thread(target=self.service.run, args=(self.stop,),
                                         daemon=True)]
        for t in self.threads:
            t.start()

    @staticmethod
    def _unreachable() -> KinematicModel | None:
        raise NoResponder("get 'handkse/unit/kinematics/model': nothing answers on this key")

    def _fetch(self) -> KinematicModel | None:
        self.fetches += 1
        return self.serve()

    def _fetch_models(self) -> tuple[KinematicModel, ...]:
        return self.serve_models()

    def publish_model(self, model: KinematicModel) -> None:
        """A model arriving on the kinematics model key (the subscription path)."""
        before = self.node._latest
        self.peer.put(KEYS.kinematics_model, model.to_msgpack())
        # Control calls overtake queued samples, so no call_soon marker can wait for it.
        deadline = time.monotonic() + 5.0
        while self.node._latest is before:
            assert time.monotonic() < deadline, "the node did not take the model"
            time.sleep(0.002)

    def articulate(self, request: ArticulateRequest = DRY) -> ArticulateResult:
        """Ask as the bus would; an accepted request is answered later (a deferred answer)."""
        [(_, payload)] = self.peer.get(KEYS.robot_articulate, request.to_msgpack(), timeout=30.0)
        return ArticulateResult.from_msgpack(payload)

    def handler(self, key: str) -> Callable[[QueryRequest], QueryAnswer | Future[QueryAnswer]]:
        """The node's own queryable on ``key`` (to see whether it answers now or later)."""
        [declaration] = self.bus.network.queryables(key)
        return declaration.target  # type: ignore[no-any-return]

    def liveliness(self, key: str, alive: bool) -> None:
        """Kinematics' liveliness token appears (``alive``) or goes."""
        if alive and key not in self._tokens:
            self._tokens[key] = self.peer.declare_token(key)
        elif not alive and key in self._tokens:
            self._tokens.pop(key).undeclare()

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(5.0)


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig(RobotBridgeConfig(sim_realtime_factor=0.0))
    yield r
    r.close()


def _key_model(stamp_ns: int | None = None) -> KinematicModel:
    """The simulated key's true axis (identity hand-eye): a model the dry run accepts."""
    T0 = nominal_grasp_pose()
    axis, point = T0[:3, 2], T0[:3, 3]
    probs = {"rigid": 0.0, "prismatic": 0.0, "revolute": 1.0, "disconnected": 0.0}
    return KinematicModel(
        stamp_ns=time.time_ns() if stamp_ns is None else stamp_ns, type="revolute",
        probabilities=probs,
        revolute=RevoluteParams(axis=axis, point=point - (point @ axis) * axis, q=1.0, dq=0.0,
                                covariance=np.zeros((7, 7))))


def test_served_model_is_used(rig: Rig) -> None:
    rig.serve = _key_model
    result = rig.articulate()
    assert (result.success, result.reason) == (True, "dry_run")
    assert rig.fetches == 1


def test_unreachable_without_any_model_is_no_model(rig: Rig) -> None:
    assert rig.articulate().reason == "no_model"
    assert rig.fetches == 1


def test_recent_published_model_bridges_a_short_outage(rig: Rig) -> None:
    rig.publish_model(_key_model())
    rig.clock.t += 1.5  # within max_cached_model_age_s = 2 s
    result = rig.articulate()
    assert (result.success, result.reason) == (True, "dry_run")


@pytest.mark.parametrize("error", [NoResponder("nothing answers"), QueryTimeout("no answer")])
def test_old_published_model_is_stale_when_kinematics_unreachable(
        rig: Rig, error: Exception, caplog: pytest.LogCaptureFixture) -> None:
    rig.publish_model(_key_model())  # its stamp is fresh: only the arrival time is old

    def fail() -> KinematicModel | None:
        raise error

    rig.serve = fail
    rig.clock.t += 2.5
    with caplog.at_level(logging.WARNING, logger="services.robot_bridge.service"):
        result = rig.articulate()
    assert (result.success, result.reason) == (False, "stale_model")
    assert "kinematics service unreachable" in caplog.text
    assert "received 2.5 s ago" in caplog.text


def test_liveliness_loss_is_reported_in_the_refusal(rig: Rig,
                                                    caplog: pytest.LogCaptureFixture) -> None:
    alive_key = KEYS.alive("kinematics")
    rig.liveliness(alive_key, True)
    rig.publish_model(_key_model())
    rig.clock.t += 0.5
    rig.liveliness(alive_key, False)
    rig.clock.t += 4.0
    with caplog.at_level(logging.WARNING, logger="services.robot_bridge.service"):
        assert rig.articulate().reason == "stale_model"
    assert "liveliness token is gone since 4.0 s" in caplog.text
    # back: the service answers again and its current model is used
    rig.liveliness(alive_key, True)
    rig.serve = _key_model
    assert rig.articulate().reason == "dry_run"


def test_a_fetched_model_refreshes_the_fallback(rig: Rig) -> None:
    rig.serve = _key_model
    assert rig.articulate().reason == "dry_run"
    rig.serve = Rig._unreachable
    rig.clock.t += 1.0
    assert rig.articulate().reason == "dry_run"  # fetched 1 s ago: still within the window
    rig.clock.t += 1.5
    assert rig.articulate().reason == "stale_model"


def test_the_fallback_still_checks_the_model_stamp(rig: Rig) -> None:
    """A recently *received* model that is old by its stamp stays ``stale_model``."""
    rig.publish_model(_key_model(stamp_ns=time.time_ns() - 10**12))
    assert rig.articulate().reason == "stale_model"


def test_a_model_in_the_request_needs_no_service(rig: Rig) -> None:
    result = rig.articulate(ArticulateRequest(amount=math.pi / 4, duration_s=2.0, dry_run=True,
                                              model=_key_model()))
    assert result.reason == "dry_run"
    assert rig.fetches == 0


def test_zero_window_never_falls_back() -> None:
    r = Rig(RobotBridgeConfig(sim_realtime_factor=0.0, max_cached_model_age_s=0.0))
    try:
        r.publish_model(_key_model())
        r.clock.t += 0.01
        assert r.articulate().reason == "stale_model"
    finally:
        r.close()


def test_check_cached_model() -> None:
    assert check_cached_model(1.0, 2.0, "down") is None
    assert check_cached_model(2.0, 2.0, "down") is None
    stale = check_cached_model(2.01, 2.0, "down")
    assert stale is not None and stale.reason == "stale_model" and stale.detail.startswith("down")
    none = check_cached_model(None, 2.0, "down")
    assert none is not None and none.reason == "no_model"


def test_config_rejects_a_negative_window() -> None:
    with pytest.raises(ValueError, match="max_cached_model_age_s"):
        RobotBridgeConfig(max_cached_model_age_s=-1.0)
    assert RobotBridgeConfig().max_cached_model_age_s == 2.0
