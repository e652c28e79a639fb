"""Robot bridge service: articulate the object along the estimated model, publish the robot state.

- publishes ``RobotState`` on ``handkse/{rig}/robot/state`` at ``state_rate_hz`` (wall clock),
  while idle and while articulating (``mode`` idle / articulating / fault);
- answers ``handkse/{rig}/robot/articulate`` (``ArticulateRequest`` -> ``ArticulateResult``)
  on exactly that key (a wildcard query is refused, ``wildcard_query``). A model inside the
  request is used as given: only the operator identity may send requests (router access
  control). Without one the bridge queries the kinematics service (``get`` on
  ``handkse/{rig}/kinematics/model``) and uses only the reply of the session that holds the
  kinematics session token (:mod:`services.common.provenance`; other replies are counted
  ``untrusted_reply`` and logged, disagreeing kinematics sessions ``ambiguous_reply``). When no
  trusted answer comes (the service is down, the link is cut, no answer within
  ``model_query_timeout_s``, only untrusted replies) it falls back to the last model received
  from the service only if that arrived within ``max_cached_model_age_s`` (default 2 s, about
  one lease); otherwise it refuses with ``stale_model`` (``no_model`` if it never had one), the
  log saying why (query error, and since when the kinematics liveliness token is gone).
  ``dry_run`` checks and plans without moving;
- subscribes ``handkse/{rig}/kinematics/model`` (FIFO; the latest is kept with its arrival
  time) and watches the liveliness token ``handkse/{rig}/alive/kinematics``.

One request at a time (docs/robot_bridge.md#requests): a request that arrives while another is
being served, dry runs included, is answered ``busy`` at once, never queued. Each request has
a reply deadline, its arrival plus its ``timeout_s`` (``request_timeout_s`` when it has none),
earlier if its ``stamp_ns`` says it was sent long before; a request whose deadline has passed
when it could start is not started (``caller_gone``), nor one whose motion would end after it
(``timeout_too_short``). Refusals are counted by reason in ``ServiceStats.skipped``.

Threads: the bus thread only decodes a request, takes the one slot and hands it to the robot
thread, answering later (a deferred query answer), so the next request is answered meanwhile.
The robot thread owns the backend and publishes the state. The MuJoCo backend is paced to
``sim_realtime_factor`` x real time (0: as fast as possible).
"""

from __future__ import annotations

import argparse
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field, replace

import numpy as np

from services.common.bus import (
    Bus,
    BusError,
    QueryAnswer,
    QueryRejected,
    QueryRequest,
    Reply,
)
from services.common.bus import options_from_args as zenoh_options_from_args
from services.common.config import section_from_args
from services.common.errors import UserError
from services.common.keys import Keys
from services.common.protocol import (
    ArticulateRequest,
    ArticulateResult,
    KinematicModel,
    KinematicModelList,
    ProtocolError,
    RobotState,
)
from services.common.provenance import AmbiguousReply, QueryBus, UntrustedReply, ask_service
from services.common.se3 import se3_inverse
from services.common.service import BusLike, Service, stop_on_signals
from services.robot_bridge.backend import BackendState, RobotBackend
from services.robot_bridge.config import RobotBridgeConfig, config_from_args
from services.robot_bridge.executor import Bridge
from services.robot_bridge.factory import configured_backend
from services.robot_bridge.refinement import RefinementConfig, robot_body
from services.robot_bridge.safety import Refusal, check_cached_model, choose_segment
from services.robot_bridge.trajectory import ArticulationPlan

log = logging.getLogger(__name__)

ModelFetcher = Callable[[], KinematicModel | None]
# every contact phase's model (``kinematics/models``), for a request that names a segment
ModelListFetcher = Callable[[], tuple[KinematicModel, ...]]
# Time kept between the end of the planned motion and the caller's deadline, for the result
# to be sent and delivered [s].
REPLY_MARGIN_S = 0.5


@dataclass
class _Job:
    """One accepted request: arrival and reply ``deadline`` on the node's clock (s), the
    caller's ``timeout_s`` (given or assumed); ``answer`` completes the deferred query."""

    request: ArticulateRequest
    received_at: float
    deadline: float
    timeout_s: float
    answer: Future[QueryAnswer] = field(default_factory=Future)


class RobotBridgeNode:
    """Binds a :class:`Bridge` on one backend to the bus through a :class:`Service`.

    ``clock`` (monotonic seconds) times the age of received models, of the kinematics
    liveliness state and of requests; tests pass a fake one.
    """

    def __init__(self, service: Service, backend: RobotBackend, config: RobotBridgeConfig,
                 fetch_model: ModelFetcher | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 fetch_models: ModelListFetcher | None = None) -> None:
        self.service = service
        self.backend = backend
        self.config = config
        self.bridge = Bridge(backend, config, RefinementConfig() if config.closed_loop else None)
        self.fetch_model = fetch_model
        self.fetch_models = fetch_models
        self.clock = clock
        self._target: np.ndarray | None = None  # the pose commanded at the last tick
        self.mode = "idle"
        self._latest: KinematicModel | None = None
        self._latest_at = 0.0                       # clock() when _latest arrived
        self._kinematics_alive: bool | None = None  # None: no liveliness news yet
        self._kinematics_alive_at = clock()         # clock() of the last liveliness change
        self._lock = threading.Lock()
        self._jobs: queue.Queue[_Job] = queue.Queue()
        self._job: _Job | None = None  # the request being served (under _lock)
        self._refusal_logged: dict[str, float] = {}  # reason -> monotonic time of its last log
        self._next_publish = 0.0
        self._pace: tuple[float, float] | None = None  # (wall start, backend start time)
        keys = service.keys
        service.subscribe(keys.kinematics_model, KinematicModel, self.on_model)
        service.bus.declare_queryable(keys.robot_articulate, service.exact_key_only(
            keys.robot_articulate, self.answer_articulate))
        # The real Bus watches liveliness; a minimal BusLike fake may not (state stays unknown).
        watch = getattr(service.bus, "watch_liveliness", None)
        if watch is not None:
            watch(keys.alive("kinematics"), self.on_kinematics_liveliness)

    # --- bus side ---

    def on_model(self, model: KinematicModel) -> None:
        self._remember(model)

    def _remember(self, model: KinematicModel) -> None:
        with self._lock:
            self._latest = model
            self._latest_at = self.clock()

    def on_kinematics_liveliness(self, _key: str, alive: bool) -> None:
        """The kinematics service's token appeared (``alive``) or vanished (crash, lease)."""
        with self._lock:
            if alive != self._kinematics_alive:
                self._kinematics_alive = alive
                self._kinematics_alive_at = self.clock()
        if not alive:
            log.warning("kinematics service is not alive (liveliness token gone)")

    def answer_articulate(self, request: QueryRequest) -> QueryAnswer | Future[QueryAnswer]:
        """Runs on a bus thread: decode, take the one slot or answer ``busy``; the robot thread
        answers an accepted request later (the returned future)."""
        self.service.received += 1
        if request.payload is None:
            self.service.reject("missing_payload", "robot/articulate query without a payload")
            raise QueryRejected("robot/articulate needs an ArticulateRequest payload")
        try:
            req = ArticulateRequest.from_msgpack(request.payload)
        except ProtocolError as exc:
            self.service.reject(exc.reason, str(exc))
            raise QueryRejected(f"bad ArticulateRequest: {exc}") from exc
        now = self.clock()
        timeout = self.config.request_timeout_s if req.timeout_s is None else req.timeout_s
        job = _Job(req, received_at=now, deadline=now + _reply_window_s(req, timeout),
                   timeout_s=timeout)
        with self._lock:
            running = self._job
            if running is None:
                self._job = job
        if running is not None:
            return QueryAnswer(self._refused(Refusal(
                "busy", f"serving a request received {now - running.received_at:.1f} s ago "
                        "(one articulation at a time): send it again once that one is "
                        "answered")).to_msgpack())
        self._jobs.put(job)
        return job.answer

    def _refused(self, refusal: Refusal) -> ArticulateResult:
        """The result of a refused request, counted in ``skipped`` by reason and logged (at
        most once a second per reason, with the count: a flood of requests cannot flood the
        log)."""
        count, due = self._count(refusal.reason)
        if due:
            log.warning("articulate refused: %s (%s; %d so far)", refusal.reason,
                        refusal.detail, count)
        return _refusal(refusal)

    def _count(self, reason: str) -> tuple[int, bool]:
        """Count a refusal; (the count so far, whether a log line is due)."""
        with self._lock:
            skipped = self.service.skipped
            count = skipped[reason] = skipped.get(reason, 0) + 1
            now = time.monotonic()
            due = now - self._refusal_logged.get(reason, -math.inf) >= 1.0
            if due:
                self._refusal_logged[reason] = now
        return count, due

    # --- robot thread ---

    def run_robot(self, stop: threading.Event) -> None:
        """The robot thread: serve accepted requests, publish the state at the configured rate."""
        period = 1.0 / self.config.state_rate_hz
        while not stop.is_set():
            try:
                job = self._jobs.get(timeout=period)
            except queue.Empty:
                job = None
            if job is not None:
                self._serve(job, stop)
            self._publish_state(self.backend.read(), force=True)
        while True:  # shutting down: answer what was accepted but not started
            try:
                job = self._jobs.get_nowait()
            except queue.Empty:
                break
            self._finish(job, self._refused(Refusal("cancelled", "the bridge is stopping; "
                                                                 "nothing was started")))

    def _serve(self, job: _Job, stop: threading.Event) -> None:
        try:
            result = self._execute(job, stop)
        except Exception as exc:  # reported to the caller; the service keeps running
            log.exception("articulation failed")
            self.mode = "fault"
            result = _refusal(Refusal("robot_error", f"the articulation failed "
                                                     f"({type(exc).__name__}: {exc}); see the "
                                                     "robot bridge's log"))
        self._finish(job, result)

    def _finish(self, job: _Job, result: ArticulateResult) -> None:
        """Free the slot, then answer (so the caller's next request finds the bridge free)."""
        with self._lock:
            if self._job is job:
                self._job = None
        job.answer.set_result(QueryAnswer(result.to_msgpack()))

    def _execute(self, job: _Job, stop: threading.Event) -> ArticulateResult:
        request = job.request
        # The deadline is checked last (the gate), so that a request is told first what is
        # wrong with it or its model; a caller gone meanwhile costs at most the model query.
        model = request.model or (self._model_from_service() if request.segment is None
                                  else self._segment_from_service(request.segment))
        if isinstance(model, Refusal):
            return self._refused(model)
        self._pace = None
        result = self.bridge.articulate(request, model, now_ns=time.time_ns(),
                                        on_tick=self._on_tick, cancel=stop,
                                        gate=lambda plan: self._check_deadline(job, plan))
        if not result.success and self.bridge.last_execution is None:
            self._count(result.reason)  # refused by a check (logged by the bridge): nothing moved
        self.mode = "fault" if result.reason == "robot_error" else "idle"
        log.info("articulate: success=%s reason=%s articulated=%.4f peak %.1f N mean %.1f N",
                 result.success, result.reason, result.articulated, result.peak_force_n,
                 result.mean_force_n)
        return result

    def _check_deadline(self, job: _Job, plan: ArticulationPlan) -> Refusal | None:
        """Start only what can be answered: the caller is still waiting and the planned motion
        (duration and hold, at the simulation's pace) ends ``REPLY_MARGIN_S`` before its
        deadline."""
        now = self.clock()
        if now >= job.deadline:
            return Refusal("caller_gone",
                           f"the caller stopped waiting {now - job.deadline:.1f} s ago (timeout "
                           f"{job.timeout_s:.1f} s; the request arrived "
                           f"{now - job.received_at:.1f} s ago); not started: send a longer "
                           "ArticulateRequest.timeout_s")
        factor = self.config.sim_realtime_factor if self.backend.name == "mujoco" else 1.0
        motion_s = plan.total_s / factor if factor > 0.0 else plan.total_s
        left_s = job.deadline - now
        if motion_s + REPLY_MARGIN_S > left_s:
            return Refusal("timeout_too_short",
                           f"the motion takes {motion_s:.1f} s (+{REPLY_MARGIN_S} s to reply) but "
                           f"the caller waits only {left_s:.1f} s more (timeout "
                           f"{job.timeout_s:.1f} s); send a longer ArticulateRequest.timeout_s")
        return None

    def _model_from_service(self) -> KinematicModel | Refusal:
        """The kinematics service's current model; if it cannot be asked, the last model
        received from it when that is recent enough (``max_cached_model_age_s``), else a
        ``stale_model``/``no_model`` refusal saying why."""
        why = "no kinematics query is configured"
        if self.fetch_model is not None:
            try:
                model = self.fetch_model()
            except UntrustedReply as exc:
                why = f"no trustworthy answer from the kinematics service ({exc})"
            except BusError as exc:
                why = f"kinematics service unreachable ({exc})"
            except ProtocolError as exc:
                why = f"the kinematics service sent an invalid model ({exc})"
            else:
                if model is not None:
                    self._remember(model)
                    return model
                why = "the kinematics service answered without a model"
        now = self.clock()
        with self._lock:
            latest, latest_at = self._latest, self._latest_at
            alive, alive_at = self._kinematics_alive, self._kinematics_alive_at
        if alive is False:
            why += f"; its liveliness token is gone since {now - alive_at:.1f} s"
        age = None if latest is None else now - latest_at
        refusal = check_cached_model(age, self.config.max_cached_model_age_s, why)
        if refusal is not None:
            return refusal
        assert latest is not None
        log.warning("%s; using the last model received %.1f s ago", why, age)
        return latest

    def _segment_from_service(self, segment: int) -> KinematicModel | Refusal:
        """Contact phase ``segment``'s model from the kinematics service's ``kinematics/models``
        (:func:`~services.robot_bridge.safety.choose_segment`), or a refusal saying why."""
        if self.fetch_models is None:
            return Refusal("no_model", f"contact phase {segment} was asked for, but no "
                                       "kinematics/models query is configured")
        try:
            models = self.fetch_models()
        except (UntrustedReply, BusError, ProtocolError) as exc:
            return Refusal("no_model", f"the kinematics service's contact phases could not be "
                                       f"asked ({exc}): try again, or send a model")
        return choose_segment(models, segment)

    def _on_tick(self, state: BackendState, moving: bool,
                 target: np.ndarray | None = None) -> None:
        """Per control tick: publish at the state rate (with the commanded pose ``target``);
        pace a simulation to real time."""
        self.mode = "articulating"
        self._target = target
        self._publish_state(state)
        factor = self.config.sim_realtime_factor
        if self.backend.name != "mujoco" or factor <= 0.0:
            return
        now = time.monotonic()
        if self._pace is None:
            self._pace = (now, state.t_s)
            return
        ahead = (state.t_s - self._pace[1]) / factor - (now - self._pace[0])
        if ahead > 0.002:
            time.sleep(ahead)

    def _publish_state(self, state: BackendState, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now < self._next_publish:
            return
        self._next_publish = now + 1.0 / self.config.state_rate_hz
        keys = self.service.keys
        msg = RobotState(seq=self.service.next_seq(keys.robot_state), stamp_ns=time.time_ns(),
                         frame_id="world", q=np.asarray(state.q, "<f8"),
                         dq=np.asarray(state.dq, "<f8"),
                         T_base_ee=_rigid(state.T_base_ee),
                         wrench=np.asarray(state.wrench, "<f8"), mode=self.mode,
                         backend=self.backend.name,
                         T_base_target=(_rigid(self._target) if self.mode == "articulating"
                                        and self._target is not None else None))
        self.service.publish(keys.robot_state, msg)
        # --- robot/body: the grasp pose as a HandBody in the camera frame, while articulating
        # (docs/protocol.md#robotbody); services.robot_bridge.refinement.robot_body.
        if self.mode == "articulating":
            T_frame_base = se3_inverse(self.config.base_T_camera())
            body = robot_body(time.time_ns(), "camera", T_frame_base, _rigid(state.T_base_ee),
                              np.zeros(6))
            self.service.publish(keys.robot_body, replace(
                body, seq=self.service.next_seq(keys.robot_body)))  # type: ignore[type-var]


def _reply_window_s(request: ArticulateRequest, timeout_s: float) -> float:
    """Seconds from its arrival until the caller stops waiting: ``timeout_s``, less the time
    since the request's ``stamp_ns`` (wall clock) when that is set and in the past (a request
    held up on the way; a stamp in the future, another host's clock ahead, is ignored)."""
    if request.stamp_ns > 0:
        sent_ago_s = (time.time_ns() - request.stamp_ns) * 1e-9
        if sent_ago_s > 0.0:
            return timeout_s - sent_ago_s
    return timeout_s


def _rigid(T: np.ndarray) -> np.ndarray:
    """A pose with its rotation re-orthonormalised (simulation round-off would fail decoding)."""
    out = np.array(T, "<f8")
    u, _, vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = u @ vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _refusal(refusal: Refusal) -> ArticulateResult:
    return ArticulateResult(success=False, reason=refusal.reason, articulated=0.0,
                            peak_force_n=0.0, mean_force_n=0.0, duration_s=0.0,
                            detail=refusal.detail)


def _ask_kinematics(bus: QueryBus, keys: Keys, key: str, timeout_s: float,
                    reject: Callable[[str, str], None]) -> bytes:
    """The kinematics service's answer on ``key``; replies from any other session are set aside
    and reported to ``reject(reason, detail)`` (``Service.reject``: counted and logged)."""
    try:
        answer = ask_service(bus, keys, "kinematics", key, timeout=timeout_s)
    except UntrustedReply as exc:
        _report(exc.untrusted, reject)
        if isinstance(exc, AmbiguousReply):
            reject("ambiguous_reply", str(exc))
        raise
    _report(answer.untrusted, reject)
    return answer.reply.payload


def kinematics_model_fetcher(bus: QueryBus, keys: Keys, timeout_s: float,
                             reject: Callable[[str, str], None]) -> ModelFetcher:
    """Ask the kinematics service for its model (only its own session's reply is used)."""
    return lambda: KinematicModel.from_msgpack(
        _ask_kinematics(bus, keys, keys.kinematics_model, timeout_s, reject))


def kinematics_models_fetcher(bus: QueryBus, keys: Keys, timeout_s: float,
                              reject: Callable[[str, str], None]) -> ModelListFetcher:
    """Ask the kinematics service for every contact phase's model (``KinematicModelList``;
    only its own session's reply is used)."""
    return lambda: KinematicModelList.from_msgpack(
        _ask_kinematics(bus, keys, keys.kinematics_models, timeout_s, reject)).models


def _report(untrusted: tuple[Reply, ...], reject: Callable[[str, str], None]) -> None:
    for reply in untrusted:
        reject("untrusted_reply", f"model reply on {reply.key} from session {reply.replier}, "
               "which does not hold the kinematics token: ignored")


def run(bus: BusLike, keys: Keys, config: RobotBridgeConfig, backend: RobotBackend,
        stop: threading.Event, fetch_model: ModelFetcher | None = None) -> None:
    """Run the service until ``stop`` is set (robot thread + service loop).

    Without ``fetch_model``, on a real :class:`Bus`, the bridge asks the kinematics service
    (:func:`kinematics_model_fetcher`).
    """
    service = Service("robot_bridge", bus, keys)
    fetch_models = None
    if isinstance(bus, Bus):
        fetch_models = kinematics_models_fetcher(bus, keys, config.model_query_timeout_s,
                                                 service.reject)
    if fetch_model is None and isinstance(bus, Bus):
        fetch_model = kinematics_model_fetcher(bus, keys, config.model_query_timeout_s,
                                               service.reject)
    node = RobotBridgeNode(service, backend, config, fetch_model, fetch_models=fetch_models)
    robot = threading.Thread(target=node.run_robot, args=(stop,), name="robot", daemon=True)
    robot.start()
    try:
        service.run(stop)
    finally:
        stop.set()
        robot.join(10.0)
        backend.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--backend`` and ``--sim-object`` (override ``robot_bridge.backend`` and
    ``robot_bridge.sim_object``); the CLI adds rig/config/zenoh itself."""
    parser.add_argument("--backend", choices=("mujoco", "panda"),
                        help="robot backend (default: robot_bridge.backend, mujoco)")
    parser.add_argument("--closed-loop", action="store_true",
                        help="refine a revolute model from the robot's own motion while "
                             "articulating (robot_bridge.closed_loop; simulation only)")
    parser.add_argument("--sim-object", metavar="SOURCE",
                        help="simulated object: key, window_lock or bolt at the nominal grasp; "
                             "synthetic:OBJECT[:PARTICIPANT[:SEED[:VARIANT]]], the true object of that "
                             "synthetic demonstration; or an object calibration FILE.toml "
                             "(docs/robot_bridge.md#simulated-object); default "
                             "robot_bridge.sim_object")


def main(args: argparse.Namespace) -> int:
    """``handkse robot-bridge``: config from ``--config``/``--set``, backend from the config."""
    config = config_from_args(args)
    try:
        if getattr(args, "backend", None):
            config = replace(config, backend=args.backend)
        if getattr(args, "sim_object", None):
            config = replace(config, sim_object=args.sim_object)
        if getattr(args, "closed_loop", False):
            config = replace(config, closed_loop=True)
    except ValueError as exc:
        raise UserError(f"--sim-object: {exc}") from None
    if getattr(args, "sim_object", None) and config.backend != "mujoco":
        log.warning("--sim-object %s is ignored: the %s backend drives a real robot",
                    args.sim_object, config.backend)
    try:
        config, backend, what = configured_backend(config)
    except ValueError as exc:  # an object that cannot be read or grasped, a robot not set up
        raise UserError(str(exc)) from None
    stop = threading.Event()
    stop_on_signals(stop)
    keys = Keys(args.rig)
    log.info("driving %s", what)
    with Bus(zenoh_options_from_args(args, section_from_args(args, "zenoh"))) as bus:
        print(f"robot_bridge ready ({backend.name}: {what})", flush=True)
        run(bus, keys, config, backend, stop)
    return 0
