"""The robot bridge service over a real Zenoh router, as a separate process (MuJoCo backend)."""

from __future__ import annotations

import math
import subprocess
import threading
import time

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.bus import Bus, BusError, QueryAnswer
from services.common.keys import Keys
from services.common.protocol import (
    ArticulateRequest,
    ArticulateResult,
    KinematicModel,
    RevoluteParams,
    RobotState,
    ServiceStats,
)
from services.robot_bridge.mujoco_backend import nominal_grasp_pose
from tests.conftest import Processes, output_of, wait_until, zenoh_args

KEYS = Keys("robot")


def _start_bridge(procs: Processes, router: str, *extra: str) -> subprocess.Popen[str]:
    """``handkse robot-bridge`` as a child process."""
    p = procs.start("robot-bridge", "--rig", KEYS.rig, *zenoh_args(router), *extra,
                    name="robot_bridge")
    wait_until(lambda: "robot_bridge ready" in output_of(p) or p.poll() is not None, 60,
               what="robot bridge start")
    assert p.poll() is None, output_of(p)
    return p


def _key_model(stamp_ns: int) -> KinematicModel:
    """The simulated key's true axis (identity hand-eye: camera frame = robot base frame)."""
    T0 = nominal_grasp_pose()
    axis, point = T0[:3, 2], T0[:3, 3]
    probs = {"rigid": 0.0, "prismatic": 0.0, "revolute": 1.0, "disconnected": 0.0}
    return KinematicModel(stamp_ns=stamp_ns, type="revolute", probabilities=probs,
                          revolute=RevoluteParams(axis=axis, point=point - (point @ axis) * axis,
                                                  q=1.0, dq=0.0, covariance=np.zeros((7, 7))))


def _articulate(bus: Bus, request: ArticulateRequest, timeout: float = 30.0) -> ArticulateResult:
    replies = bus.get(KEYS.robot_articulate, payload=request.to_msgpack(), timeout=timeout)
    return ArticulateResult.from_msgpack(replies[0][1])


def test_articulate_over_zenoh_and_robot_state(procs: Processes, router: str,
                                               client_bus: Bus) -> None:
    states: list[RobotState] = []
    client_bus.subscribe(KEYS.robot_state, lambda k, p: states.append(RobotState.from_msgpack(p)))
    bridge = _start_bridge(procs, router)
    wait_until(lambda: KEYS.alive("robot_bridge") in client_bus.alive(KEYS.alive_all), 20,
               what="robot bridge liveliness")

    # RobotState at about 100 Hz while idle
    wait_until(lambda: len(states) >= 5, 10, what="robot states")
    n0, t0 = len(states), time.monotonic()
    time.sleep(1.0)
    rate = (len(states) - n0) / (time.monotonic() - t0)
    assert 50.0 < rate < 150.0
    idle = states[-1]
    assert idle.mode == "idle" and idle.backend == "mujoco" and idle.frame_id == "world"
    assert np.allclose(idle.T_base_ee, nominal_grasp_pose(), atol=1e-6)

    now = time.time_ns()
    # refusals: no model anywhere, a stale model, a bad payload
    assert _articulate(client_bus, ArticulateRequest(amount=1.0, duration_s=2.0)).reason == \
        "no_model"
    stale = ArticulateRequest(amount=1.0, duration_s=2.0, model=_key_model(now - 10**12))
    assert _articulate(client_bus, stale).reason == "stale_model"
    with pytest.raises(BusError, match="ArticulateRequest"):
        client_bus.get(KEYS.robot_articulate, payload=b"\x00garbage", timeout=5.0)

    # without a model in the request the bridge asks the kinematics service (this session
    # stands in for it: its model queryable and, as every service has, its session token)
    served = _key_model(time.time_ns())
    kinematics = client_bus.declare_queryable(
        KEYS.kinematics_model, lambda r: QueryAnswer(served.to_msgpack()))
    session = client_bus.declare_token(KEYS.session("kinematics", client_bus.zid))
    dry = _articulate(client_bus, ArticulateRequest(amount=math.pi / 2, duration_s=2.0,
                                                    dry_run=True))
    assert dry.success and dry.reason == "dry_run" and dry.duration_s == pytest.approx(2.5)
    kinematics.undeclare()
    session.undeclare()
    # ... and falls back to the last model published on the model key
    client_bus.put(KEYS.kinematics_model, _key_model(time.time_ns()).to_msgpack())
    dry_request = ArticulateRequest(amount=math.pi / 2, duration_s=2.0, dry_run=True)
    wait_until(lambda: _articulate(client_bus, dry_request).reason != "no_model", 10,
               what="the bridge has the published model")
    dry = _articulate(client_bus, dry_request)
    assert dry.reason == "dry_run"
    assert np.allclose(states[-1].q, idle.q, atol=1e-9)  # dry runs do not move

    # a real articulation: a quarter turn of the key in 2 s
    n_before = len(states)
    result = _articulate(client_bus, ArticulateRequest(
        amount=math.pi / 2, duration_s=2.0, model=_key_model(time.time_ns())))
    assert result.success and result.reason == "ok", result
    assert result.articulated == pytest.approx(math.pi / 2, rel=0.03)
    assert 0.0 < result.peak_force_n < 15.0
    moving = [s for s in states[n_before:] if s.mode == "articulating"]
    assert len(moving) > 50  # published during the motion, paced in real time (2.5 s)
    assert abs(states[-1].q[6] - idle.q[6]) > 0.5  # joint 7 turned (with the other joints)

    stats = ServiceStats.from_msgpack(client_bus.get(KEYS.stats("robot_bridge"))[0][1])
    assert stats.received >= 5 and stats.published > 200
    assert bridge.poll() is None


def test_requests_are_served_one_at_a_time(procs: Processes, router: str,
                                           client_bus: Bus) -> None:
    """Zenoh runs a queryable's callbacks one after the other: a second request waits for the
    first articulation to end (the bridge would answer ``busy`` if they overlapped)."""
    states: list[RobotState] = []
    client_bus.subscribe(KEYS.robot_state, lambda k, p: states.append(RobotState.from_msgpack(p)))
    _start_bridge(procs, router)
    wait_until(lambda: KEYS.alive("robot_bridge") in client_bus.alive(KEYS.alive_all), 20,
               what="robot bridge liveliness")
    done: list[tuple[float, ArticulateResult]] = []

    def first() -> None:
        r = _articulate(client_bus, ArticulateRequest(
            amount=math.pi / 4, duration_s=1.5, model=_key_model(time.time_ns())))
        done.append((time.monotonic(), r))

    t = threading.Thread(target=first)
    t.start()
    wait_until(lambda: any(s.mode == "articulating" for s in states), 20,
               what="the first articulation under way")
    second = _articulate(client_bus, ArticulateRequest(
        amount=math.pi / 4, duration_s=1.5, model=_key_model(time.time_ns()), dry_run=True))
    answered = time.monotonic()
    t.join(30)
    assert done and done[0][1].success
    if second.reason != "busy":
        assert second.reason == "dry_run" and answered >= done[0][0] - 0.05
