"""The robot bridge service over a real Zenoh router, as a separate process (MuJoCo backend)."""

from __future__ import annotations

import math
import subprocess
import threading
import time
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("mujoco")

from services.common.bus import Bus, BusError, QueryAnswer, QueryTimeout
from services.common.keys import Keys
from services.common.protocol import (
    ArticulateRequest,
    ArticulateResult,
    KinematicModel,
    RevoluteParams,
    RobotState,
    ServiceStats,
)
from services.common.se3 import so3_log
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


def _stats(bus: Bus) -> ServiceStats:
    return ServiceStats.from_msgpack(bus.get(KEYS.stats("robot_bridge"))[0][1])


def _turned(T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Angle (rad) the hand turned from pose ``T_a`` to ``T_b``."""
    return float(np.linalg.norm(so3_log(T_b[:3, :3] @ T_a[:3, :3].T)))


def _watch_states(bus: Bus) -> list[RobotState]:
    states: list[RobotState] = []
    bus.subscribe(KEYS.robot_state, lambda k, p: states.append(RobotState.from_msgpack(p)))
    wait_until(lambda: len(states) >= 3, 10, what="robot states")
    return states


def test_concurrent_requests_one_runs_the_others_are_busy(procs: Processes, router: str,
                                                          client_bus: Bus) -> None:
    """One articulation at a time: of simultaneous requests exactly one runs; the others, and
    one sent while it runs, are answered ``busy`` before it ends, never queued to run later."""
    _start_bridge(procs, router)
    wait_until(lambda: KEYS.alive("robot_bridge") in client_bus.alive(KEYS.alive_all), 20,
               what="robot bridge liveliness")
    states = _watch_states(client_bus)
    T_before = states[-1].T_base_ee
    answers: list[tuple[str, ArticulateResult]] = []  # in the order they arrived
    lock = threading.Lock()
    start = threading.Barrier(3)

    def ask(name: str, duration_s: float, wait: bool = True) -> None:
        request = ArticulateRequest(amount=math.pi / 4, duration_s=duration_s,
                                    model=_key_model(time.time_ns()), timeout_s=30.0)
        if wait:
            start.wait(10.0)
        result = _articulate(client_bus, request)
        with lock:
            answers.append((name, result))

    threads = [threading.Thread(target=ask, args=(f"simultaneous {i}", 1.5)) for i in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60.0)
    reasons = sorted(r.reason for _, r in answers)
    assert reasons == ["busy", "busy", "ok"], answers
    assert answers[-1][1].reason == "ok"  # both busy answers came before the articulation ended
    # exactly one quarter turn was made (the hand turns with the key), not two or three
    assert _turned(T_before, states[-1].T_base_ee) == pytest.approx(math.pi / 4, abs=0.05)

    # a request sent while one is running is busy too, and is not run afterwards
    answers.clear()
    n_states = len(states)
    T_start = states[-1].T_base_ee
    running = threading.Thread(target=ask, args=("running", 3.0, False))
    running.start()
    wait_until(lambda: any(s.mode == "articulating" for s in states[n_states:]), 20,
               what="the articulation to start")
    ask("while running", 1.5, wait=False)
    running.join(60.0)
    assert [(name, r.reason) for name, r in answers] == [("while running", "busy"),
                                                         ("running", "ok")], answers

    # the slot is free again once answered; the busy request never ran: two quarter turns
    answers.clear()
    ask("after", 1.5, wait=False)
    assert answers[0][1].reason == "ok", answers
    wait_until(lambda: states[-1].mode == "idle", 10, what="idle after the articulation")
    assert _turned(T_start, states[-1].T_base_ee) == pytest.approx(math.pi / 2, abs=0.05)
    assert _stats(client_bus).skipped.get("busy") == 3


def test_a_caller_that_timed_out_is_never_started(procs: Processes, router: str,
                                                  client_bus: Bus) -> None:
    """The bridge starts nothing whose reply can no longer be delivered: a caller that gave up
    while the bridge waited for the model, a request stamped longer ago than its timeout, a
    motion longer than the caller waits."""
    bridge = _start_bridge(procs, router, "--set", "robot_bridge.model_query_timeout_s=30")
    wait_until(lambda: KEYS.alive("robot_bridge") in client_bus.alive(KEYS.alive_all), 20,
               what="robot bridge liveliness")
    states = _watch_states(client_bus)
    q_before = states[-1].q.copy()

    # the kinematics service answers the bridge's model query only after the caller gave up
    asked, released = threading.Event(), threading.Event()

    def slow_kinematics(_request: object) -> QueryAnswer:
        asked.set()
        released.wait(30.0)
        return QueryAnswer(_key_model(time.time_ns()).to_msgpack())

    kinematics = client_bus.declare_queryable(KEYS.kinematics_model, slow_kinematics)
    session = client_bus.declare_token(KEYS.session("kinematics", client_bus.zid))
    request = ArticulateRequest(amount=math.pi / 4, duration_s=1.5, timeout_s=1.0)
    with pytest.raises(QueryTimeout):
        client_bus.get(KEYS.robot_articulate, payload=request.to_msgpack(), timeout=1.0)
    assert asked.is_set()  # the bridge was waiting for the model when the caller gave up
    released.set()
    wait_until(lambda: _stats(client_bus).skipped.get("caller_gone") == 1, 30,
               what="the bridge to drop the request of the caller that timed out")
    assert "caller stopped waiting" in output_of(bridge)
    kinematics.undeclare()
    session.undeclare()

    # a request stamped 3 s ago with a 2 s timeout: its caller has gone (here it still listens)
    late = ArticulateRequest(stamp_ns=time.time_ns() - 3 * 10**9, amount=math.pi / 4,
                             duration_s=1.5, timeout_s=2.0, model=_key_model(time.time_ns()))
    assert _articulate(client_bus, late).reason == "caller_gone"
    # 2 s of motion and 0.5 s hold do not fit in a 2 s timeout; a dry run says so too
    short = ArticulateRequest(amount=math.pi / 4, duration_s=2.0, timeout_s=2.0,
                              model=_key_model(time.time_ns()))
    assert _articulate(client_bus, short).reason == "timeout_too_short"
    assert _articulate(client_bus, replace(short, dry_run=True)).reason == "timeout_too_short"

    assert all(s.mode != "articulating" for s in states)
    assert np.allclose(states[-1].q, q_before, atol=1e-6)
    # ... and a request that fits is served
    fits = replace(short, timeout_s=10.0)
    assert _articulate(client_bus, fits).reason == "ok"
    assert _stats(client_bus).skipped == {"caller_gone": 2, "timeout_too_short": 2}
