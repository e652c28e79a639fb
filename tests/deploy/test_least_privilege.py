"""Least privilege (issue 13, finding 1): the deployment's router policy
(``docker/zenoh/router.json5``), enforced by Zenoh's own access control on a real router, against
the attacks the earlier policy let through.

Each attack runs twice on the same router configuration: once with its access control switched
off (the attack succeeds, so it is real), once with the policy (refused). Identities
authenticate with user name and password as in the deployment.

Declarations reach the router asynchronously. A router handles what one session sends in
order, so a test waits until something the attacker sent *after* the attack has taken effect
(its own stats queryable answers, its own sample arrives); by then the attack has been let
through or refused.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pytest

from services.common.bus import (
    Bus,
    BusError,
    NoResponder,
    QueryAnswer,
    QueryTimeout,
    ZenohOptions,
)
from services.common.keys import Keys
from services.common.processes import client_args
from services.common.protocol import (
    ArticulateRequest,
    ArticulateResult,
    KinematicModel,
    RobotState,
    ServiceStats,
)
from services.common.provenance import sessions_of
from tests.conftest import Processes, output_of, wait_until

ROUTER_CONFIG = Path(__file__).resolve().parents[2] / "docker" / "zenoh" / "router.json5"
IDENTITIES = ("camera", "detector", "tracker", "kinematics", "robot", "viewer", "operator")
KEYS = Keys("lp")
NO_ANSWER = (NoResponder, QueryTimeout)


@dataclass
class Deployment:
    """A router loaded from the project's policy file; ``policy`` False switches its access
    control off (everything else, credentials included, as deployed)."""

    endpoint: str
    policy: bool
    sessions: list[Bus] = field(default_factory=list)

    def client(self, user: str) -> Bus:
        bus = Bus(ZenohOptions(mode="client", connect=(self.endpoint,), multicast_scouting=False,
                               connect_timeout_ms=5000, cfg=_credentials(user)))
        self.sessions.append(bus)
        return bus

    def cli_args(self, user: str) -> list[str]:
        """Command-line arguments making a handkse process a client as ``user``."""
        return [*client_args(self.endpoint, KEYS.rig),
                *(a for c in _credentials(user) for a in ("--cfg", c))]


def _credentials(user: str) -> tuple[str, str]:
    return (f'transport/auth/usrpwd/user:"{user}"',
            f'transport/auth/usrpwd/password:"{user}-secret"')


@pytest.fixture
def deploy(tmp_path: Path) -> Iterator[Callable[[bool], Deployment]]:
    creds = tmp_path / "credentials.txt"
    creds.write_text("".join(f"{u}:{u}-secret\n" for u in IDENTITIES))
    routers: list[Bus] = []
    deployments: list[Deployment] = []

    def start(policy: bool) -> Deployment:
        endpoint = f"unixsock-stream/{tmp_path}/router-{len(routers)}.sock"
        cfg = [f'transport/auth/usrpwd/dictionary_file:"{creds}"']
        if not policy:
            cfg.append("access_control/enabled:false")
        routers.append(Bus(ZenohOptions(config_file=str(ROUTER_CONFIG), mode="router",
                                        listen=(endpoint,), cfg=tuple(cfg))))
        deployments.append(Deployment(endpoint, policy))
        return deployments[-1]

    yield start
    for d in deployments:
        for bus in reversed(d.sessions):
            bus.close()
    for router in routers:
        router.close()


POLICY = pytest.mark.parametrize("policy", [False, True], ids=["no-access-control", "policy"])


def _settle(sender: Bus, service: str, asker: Bus) -> None:
    """Wait until the router has handled what ``sender`` declared so far: ``sender`` declares
    its own stats queryable last, and ``asker`` waits for it to answer."""
    sender.declare_queryable(KEYS.stats(service), lambda r: QueryAnswer(service.encode()))
    wait_until(lambda: _answers(asker, KEYS.stats(service)), 10,
               what=f"{service}'s stats queryable")


def _answers(bus: Bus, selector: str) -> bool:
    try:
        return bool(bus.get(selector, timeout=1.0))
    except BusError:
        return False


# --- the attacks of finding 1, at the bus ---


@POLICY
def test_only_kinematics_answers_model_queries(deploy: Callable[[bool], Deployment],
                                               policy: bool) -> None:
    d = deploy(policy)
    camera, robot, operator = d.client("camera"), d.client("robot"), d.client("operator")
    camera.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(b"forged"))
    _settle(camera, "camera", operator)
    # kinematics is down: the camera identity's queryable is all there is
    for asker in (robot, operator):
        if policy:
            with pytest.raises(NO_ANSWER):
                asker.get(KEYS.kinematics_model, timeout=1.0)
        else:
            assert asker.get(KEYS.kinematics_model) == [(KEYS.kinematics_model, b"forged")]

    # kinematics is up: the operator hears only its session
    kinematics = d.client("kinematics")
    kinematics.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(b"real"))
    _settle(kinematics, "kinematics", operator)
    replies = operator.get_replies(KEYS.kinematics_model)
    heard = sorted((r.payload, r.replier) for r in replies)
    expected = [(b"real", kinematics.zid)]
    assert heard == (expected if policy else sorted([*expected, (b"forged", camera.zid)]))


@POLICY
def test_only_the_robot_answers_articulate(deploy: Callable[[bool], Deployment],
                                           policy: bool) -> None:
    d = deploy(policy)
    camera, robot, operator = d.client("camera"), d.client("robot"), d.client("operator")
    camera.declare_queryable(KEYS.robot_articulate, lambda r: QueryAnswer(b"fake success"))
    _settle(camera, "camera", operator)
    robot.declare_queryable(KEYS.robot_articulate, lambda r: QueryAnswer(b"moved"))
    _settle(robot, "robot_bridge", operator)
    replies = operator.get_replies(KEYS.robot_articulate)
    heard = sorted((r.payload, r.replier) for r in replies)
    expected = [(b"moved", robot.zid)]
    assert heard == (expected if policy else sorted([*expected, (b"fake success", camera.zid)]))


@POLICY
def test_a_service_holds_only_its_own_tokens(deploy: Callable[[bool], Deployment],
                                             policy: bool) -> None:
    d = deploy(policy)
    camera, operator = d.client("camera"), d.client("operator")
    camera.declare_token(KEYS.alive("detector"))
    camera.declare_token(KEYS.session("kinematics", camera.zid))
    camera.declare_token(KEYS.alive("camera"))  # its own, declared last
    wait_until(lambda: KEYS.alive("camera") in operator.alive(KEYS.alive_all), 10,
               what="the camera's own token")
    seen = set(operator.alive(f"{KEYS.root}/alive/**"))
    impostures = {KEYS.alive("detector"), KEYS.session("kinematics", camera.zid)}
    assert (seen & impostures) == (set() if policy else impostures)


@POLICY
def test_only_the_tracker_publishes_hand_bodies(deploy: Callable[[bool], Deployment],
                                                policy: bool) -> None:
    d = deploy(policy)
    kinematics, viewer = d.client("kinematics"), d.client("viewer")
    robot, tracker = d.client("robot"), d.client("tracker")
    bodies: list[bytes] = []
    seen: list[tuple[str, bytes]] = []
    kinematics.subscribe(KEYS.hand_body, lambda k, p: bodies.append(p))
    viewer.subscribe(KEYS.all, lambda k, p: seen.append((k, p)))
    wait_until(lambda: _delivered(tracker, KEYS.hand_body, bodies), 10,
               what="the tracker's hand bodies reaching kinematics")
    robot.put(KEYS.hand_body, b"forged body")
    robot.put(KEYS.robot_state, b"robot's own state")  # after the forgery, on the same link
    wait_until(lambda: (KEYS.robot_state, b"robot's own state") in seen, 10,
               what="the robot's own sample")
    forged = (KEYS.hand_body, b"forged body")
    assert (forged in seen) == (not policy)
    # the viewer reads but publishes nothing either
    viewer.put(KEYS.hand_body, b"viewer body")
    tracker.put(KEYS.hand_body, b"last real body")
    wait_until(lambda: b"last real body" in bodies, 10, what="the tracker's last body")
    assert (b"forged body" in bodies) == (not policy)
    assert (b"viewer body" in bodies) == (not policy)


@POLICY
def test_only_the_robot_publishes_its_grasp_pose_and_kinematics_hears_it(
        deploy: Callable[[bool], Deployment], policy: bool) -> None:
    """``robot/body`` (fused by ``kinematics --fuse-robot-body``) reaches kinematics under the
    policy, from the robot identity only."""
    d = deploy(policy)
    kinematics, robot, tracker = d.client("kinematics"), d.client("robot"), d.client("tracker")
    received: list[bytes] = []
    kinematics.subscribe(KEYS.robot_body, lambda k, p: received.append(p))
    wait_until(lambda: _delivered(robot, KEYS.robot_body, received), 10,
               what="the robot's grasp pose reaching kinematics")
    tracker.put(KEYS.robot_body, b"forged grasp")
    robot.put(KEYS.robot_body, b"last real grasp")
    wait_until(lambda: b"last real grasp" in received, 10, what="the robot's last grasp pose")
    assert (b"forged grasp" in received) == (not policy)


def _delivered(sender: Bus, key: str, received: list[bytes]) -> bool:
    sender.put(key, b"probe")
    time.sleep(0.05)
    return b"probe" in received


# --- what people may do under the policy ---


def test_the_operator_may_ask_and_control(deploy: Callable[[bool], Deployment]) -> None:
    d = deploy(True)
    kinematics, tracker, robot = d.client("kinematics"), d.client("tracker"), d.client("robot")
    operator = d.client("operator")
    kinematics.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(b"model"))
    kinematics.declare_queryable(KEYS.reset("kinematics"), lambda r: QueryAnswer(b"reset"))
    tracker.declare_queryable(KEYS.reset("tracker"), lambda r: QueryAnswer(b"tracker reset"))
    robot.declare_queryable(KEYS.robot_articulate, lambda r: QueryAnswer(b"moved"))
    for service, bus in (("kinematics", kinematics), ("tracker", tracker),
                         ("robot_bridge", robot)):
        _settle(bus, service, operator)
    assert operator.get(KEYS.kinematics_model) == [(KEYS.kinematics_model, b"model")]
    assert operator.get(KEYS.reset("kinematics")) == [(KEYS.reset("kinematics"), b"reset")]
    assert operator.get(KEYS.reset("tracker")) == [(KEYS.reset("tracker"), b"tracker reset")]
    assert operator.get(KEYS.robot_articulate) == [(KEYS.robot_articulate, b"moved")]
    assert sorted(p for _, p in operator.get(KEYS.stats("*"))) == [
        b"kinematics", b"robot_bridge", b"tracker"]
    # services do not control each other, and the robot asks only for the model
    with pytest.raises(NO_ANSWER):
        tracker.get(KEYS.robot_articulate, timeout=1.0)
    with pytest.raises(NO_ANSWER):
        robot.get(KEYS.reset("kinematics"), timeout=1.0)
    assert robot.get(KEYS.kinematics_model) == [(KEYS.kinematics_model, b"model")]
    # a wildcard get is as wide as no rule of the operator: refused at the router, so it
    # cannot reach a reset queryable
    resets: list[str] = []
    kinematics.declare_queryable(KEYS.reset("kinematics"),
                                 lambda r: (resets.append(r.key), QueryAnswer(b"reset"))[1])
    _settle(kinematics, "kinematics", operator)
    for selector in (KEYS.all, KEYS.reset("*")):
        with pytest.raises(NO_ANSWER):
            operator.get(selector, timeout=1.0)
    assert resets == []


def test_a_viewer_reads_but_cannot_control(deploy: Callable[[bool], Deployment]) -> None:
    d = deploy(True)
    kinematics, robot, viewer = d.client("kinematics"), d.client("robot"), d.client("viewer")
    kinematics.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(b"model"))
    kinematics.declare_queryable(KEYS.reset("kinematics"), lambda r: QueryAnswer(b"reset"))
    kinematics.declare_token(KEYS.alive("kinematics"))
    robot.declare_queryable(KEYS.robot_articulate, lambda r: QueryAnswer(b"moved"))
    _settle(robot, "robot_bridge", viewer)
    _settle(kinematics, "kinematics", viewer)
    models: list[bytes] = []
    viewer.subscribe(KEYS.all, lambda k, p: models.append(p) if k == KEYS.kinematics_model
                     else None)
    wait_until(lambda: _delivered(kinematics, KEYS.kinematics_model, models), 10,
               what="published models reaching the viewer")
    assert viewer.get(KEYS.kinematics_model) == [(KEYS.kinematics_model, b"model")]
    assert viewer.get(KEYS.stats("kinematics")) == [(KEYS.stats("kinematics"), b"kinematics")]
    assert KEYS.alive("kinematics") in viewer.alive(KEYS.alive_all)
    for control in (KEYS.reset("kinematics"), KEYS.robot_articulate):
        with pytest.raises(NO_ANSWER):
            viewer.get(control, timeout=1.0)
    # nor may it serve: its queryable on the model is never asked
    viewer.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(b"viewer's model"))
    assert viewer.get(KEYS.stats("kinematics"))  # a round trip after the declaration
    assert [r.replier for r in robot.get_replies(KEYS.kinematics_model)] == [kinematics.zid]


# --- the robot bridge as deployed (a real process), against an impostor of kinematics ---


def _bridge(procs: Processes, d: Deployment, watcher: Bus) -> None:
    """The robot bridge as the ``robot`` identity; returns once ``watcher`` sees its token
    (declared after its queryables)."""
    pytest.importorskip("mujoco")
    p = procs.start("robot-bridge", *d.cli_args("robot"), name="robot_bridge")
    wait_until(lambda: KEYS.alive("robot_bridge") in watcher.alive(KEYS.alive_all)
               or p.poll() is not None, 60, what="robot bridge start")
    assert p.poll() is None, output_of(p)


def _articulate(bus: Bus, request: ArticulateRequest) -> ArticulateResult:
    replies = bus.get(KEYS.robot_articulate, payload=request.to_msgpack(), timeout=60.0)
    return ArticulateResult.from_msgpack(replies[0][1])


def _bridge_stats(bus: Bus) -> ServiceStats:
    return ServiceStats.from_msgpack(bus.get(KEYS.stats("robot_bridge"))[0][1])


@POLICY
def test_an_impostor_of_kinematics_cannot_move_the_robot(
        deploy: Callable[[bool], Deployment], procs: Processes, policy: bool) -> None:
    """Kinematics is down; the camera identity impersonates it completely: the model
    queryable, the kinematics token and a kinematics session token of its own."""
    from tests.robot_bridge.test_service import _key_model

    d = deploy(policy)
    camera, operator = d.client("camera"), d.client("operator")
    _bridge(procs, d, operator)
    states: list[RobotState] = []
    operator.subscribe(KEYS.robot_state, lambda k, p: states.append(RobotState.from_msgpack(p)))
    wait_until(lambda: len(states) >= 3, 30, what="robot states")
    forged = _key_model(time.time_ns())  # the simulated key's true axis: an articulable model
    camera.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(forged.to_msgpack()))
    camera.declare_token(KEYS.alive("kinematics"))
    camera.declare_token(KEYS.session("kinematics", camera.zid))
    _settle(camera, "camera", operator)
    if not policy:
        # reproduced: the bridge takes the impostor's model (only a dry run here)
        result = _articulate(operator, ArticulateRequest(amount=math.pi / 4, duration_s=1.0,
                                                         dry_run=True))
        assert (result.success, result.reason) == (True, "dry_run")
        return
    q_before = states[-1].q.copy()
    result = _articulate(operator, ArticulateRequest(amount=math.pi / 4, duration_s=1.0))
    assert (result.success, result.reason) == (False, "no_model")
    n = len(states)
    wait_until(lambda: len(states) >= n + 3, 10, what="robot states after the request")
    assert np.allclose(states[-1].q, q_before, atol=1e-9)
    assert all(s.mode == "idle" for s in states[n:])
    # the router stopped it: the forged reply never reached the bridge
    assert _bridge_stats(operator).rejected.get("untrusted_reply", 0) == 0

    # the real kinematics service, under the same policy, is heard: the bridge decides on its
    # model (no demonstration yet) exactly as on that model sent in the request
    kin = procs.start("kinematics", *d.cli_args("kinematics"), name="kinematics")
    wait_until(lambda: len(sessions_of(operator, KEYS, "kinematics")) == 1
               or kin.poll() is not None, 30, what="the kinematics session token")
    assert kin.poll() is None, output_of(kin)
    real = KinematicModel.from_msgpack(operator.get(KEYS.kinematics_model)[0][1])
    dry = ArticulateRequest(amount=math.pi / 4, duration_s=1.0, dry_run=True)
    fetched = _articulate(operator, dry)
    assert fetched.reason not in ("no_model", "dry_run")
    assert fetched.reason == _articulate(operator, replace(dry, model=real)).reason


def test_the_bridge_keeps_only_the_kinematics_sessions_reply(
        deploy: Callable[[bool], Deployment], procs: Processes) -> None:
    """Without access control the bridge's own check is all there is: a second queryable on the
    model key, whose session holds no kinematics session token, is counted and ignored; and
    neither a wildcard query nor the impostor moves the robot."""
    from tests.robot_bridge.test_service import _key_model

    d = deploy(False)
    kin = procs.start("kinematics", *d.cli_args("kinematics"), name="kinematics")
    wait_until(lambda: "kinematics ready" in output_of(kin) or kin.poll() is not None, 30,
               what="kinematics start")
    camera, operator = d.client("camera"), d.client("operator")
    _bridge(procs, d, operator)
    wait_until(lambda: len(sessions_of(operator, KEYS, "kinematics")) == 1, 20,
               what="the kinematics session token")
    (kinematics_zid,) = sessions_of(operator, KEYS, "kinematics")
    forged = _key_model(time.time_ns())
    camera.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(forged.to_msgpack()))
    camera.declare_token(KEYS.alive("kinematics"))  # the plain token proves nothing
    wait_until(lambda: len(operator.get_replies(KEYS.kinematics_model, timeout=1.0)) == 2, 10,
               what="both model queryables")

    dry = ArticulateRequest(amount=math.pi / 4, duration_s=1.0, dry_run=True)
    with_impostor = _articulate(operator, dry)
    # the real model (no demonstration yet) cannot be articulated; the forged one could
    assert not with_impostor.success and with_impostor.reason != "dry_run"
    assert _bridge_stats(operator).rejected.get("untrusted_reply", 0) >= 1
    camera.close()
    wait_until(lambda: len(operator.get_replies(KEYS.kinematics_model, timeout=1.0)) == 1, 10,
               what="the impostor gone")
    assert _articulate(operator, dry).reason == with_impostor.reason

    # `handkse get model` shows the kinematics session's model too
    impostor = d.client("camera")
    impostor.declare_queryable(KEYS.kinematics_model, lambda r: QueryAnswer(forged.to_msgpack()))
    wait_until(lambda: len(operator.get_replies(KEYS.kinematics_model, timeout=1.0)) == 2, 10,
               what="the impostor back")
    got = procs.run("get", "model", "--json", *d.cli_args("operator"))
    assert got.returncode == 0, got.stderr
    assert json.loads(got.stdout)["updates"] == 0 and json.loads(got.stdout)["type"] == "unknown"
    assert f"ignored a reply from session {impostor.zid}" in got.stderr
    assert kinematics_zid != impostor.zid

    # a wildcard query carrying a real request does not start a motion
    states: list[RobotState] = []
    operator.subscribe(KEYS.robot_state, lambda k, p: states.append(RobotState.from_msgpack(p)))
    wait_until(lambda: len(states) >= 3, 10, what="robot states")
    q_before = states[-1].q.copy()
    move = ArticulateRequest(amount=math.pi / 4, duration_s=1.0, model=forged)
    with pytest.raises(BusError, match="acts only on a query for exactly this key"):
        operator.get(f"{KEYS.root}/robot/*", payload=move.to_msgpack(), timeout=10.0)
    assert _bridge_stats(operator).rejected.get("wildcard_query") == 1
    n = len(states)
    wait_until(lambda: len(states) >= n + 3, 10, what="robot states after the query")
    assert np.allclose(states[-1].q, q_before, atol=1e-9)
