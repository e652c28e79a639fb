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
  ``dry_run`` checks and plans without moving; a second request while one runs gets ``busy``;
- subscribes ``handkse/{rig}/kinematics/model`` (FIFO; the latest is kept with its arrival
  time) and watches the liveliness token ``handkse/{rig}/alive/kinematics``.

Threads: the bus threads only decode requests and hand them to the single robot thread, which
owns the backend (one articulation at a time) and publishes the state. The MuJoCo backend is
paced to ``sim_realtime_factor`` x real time (0: as fast as possible).
"""

from __future__ import annotations

import argparse
import logging
import queue
import threading
import time
from collections.abc import Callable
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
from services.common.keys import Keys
from services.common.protocol import (
    ArticulateRequest,
    ArticulateResult,
    KinematicModel,
    ProtocolError,
    RobotState,
)
from services.common.provenance import AmbiguousReply, QueryBus, UntrustedReply, ask_service
from services.common.service import BusLike, Service, stop_on_signals
from services.robot_bridge.backend import BackendState, RobotBackend
from services.robot_bridge.config import RobotBridgeConfig, config_from_args
from services.robot_bridge.executor import Bridge
from services.robot_bridge.factory import make_backend
from services.robot_bridge.safety import Refusal, check_cached_model

log = logging.getLogger(__name__)

ModelFetcher = Callable[[], KinematicModel | None]
# Extra seconds a request may wait beyond its planned motion (queueing, settling, pacing).
_REQUEST_SLACK_S = 30.0


@dataclass
class _Job:
    request: ArticulateRequest
    done: threading.Event = field(default_factory=threading.Event)
    result: ArticulateResult | None = None


class RobotBridgeNode:
    """Binds a :class:`Bridge` on one backend to the bus through a :class:`Service`.

    ``clock`` (monotonic seconds) times the age of received models and of the kinematics
    liveliness state; tests pass a fake one.
    """

    def __init__(self, service: Service, backend: RobotBackend, config: RobotBridgeConfig,
                 fetch_model: ModelFetcher | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.service = service
        self.backend = backend
        self.config = config
        self.bridge = Bridge(backend, config)
        self.fetch_model = fetch_model
        self.clock = clock
        self.mode = "idle"
        self._latest: KinematicModel | None = None
        self._latest_at = 0.0                       # clock() when _latest arrived
        self._kinematics_alive: bool | None = None  # None: no liveliness news yet
        self._kinematics_alive_at = clock()         # clock() of the last liveliness change
        self._lock = threading.Lock()
        self._jobs: queue.Queue[_Job] = queue.Queue()
        self._busy = threading.Event()
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

    def answer_articulate(self, request: QueryRequest) -> QueryAnswer:
        """Runs on a bus thread: decode, queue for the robot thread, wait for its result."""
        self.service.received += 1
        if request.payload is None:
            self.service.reject("missing_payload", "robot/articulate query without a payload")
            raise QueryRejected("robot/articulate needs an ArticulateRequest payload")
        try:
            req = ArticulateRequest.from_msgpack(request.payload)
        except ProtocolError as exc:
            self.service.reject(exc.reason, str(exc))
            raise QueryRejected(f"bad ArticulateRequest: {exc}") from exc
        if self._busy.is_set():
            return QueryAnswer(_refusal("busy").to_msgpack())
        self._busy.set()
        job = _Job(req)
        self._jobs.put(job)
        factor = self.config.sim_realtime_factor if self.backend.name == "mujoco" else 1.0
        planned = req.duration_s + self.config.hold_s + self.config.settle_s
        limit = _REQUEST_SLACK_S + (planned / factor if factor > 0 else planned)
        if not job.done.wait(limit) or job.result is None:
            raise QueryRejected(f"articulation did not finish within {limit:.0f} s")
        return QueryAnswer(job.result.to_msgpack())

    # --- robot thread ---

    def run_robot(self, stop: threading.Event) -> None:
        """The robot thread: execute queued requests, publish the state at the configured rate."""
        period = 1.0 / self.config.state_rate_hz
        while not stop.is_set():
            try:
                job = self._jobs.get(timeout=period)
            except queue.Empty:
                job = None
            if job is not None:
                try:
                    job.result = self._execute(job.request, stop)
                except Exception as exc:  # reported to the caller; the service keeps running
                    log.exception("articulation failed")
                    self.mode = "fault"
                    job.result = _refusal("robot_error", f"{exc}")
                finally:
                    self._busy.clear()
                    job.done.set()
            self._publish_state(self.backend.read(), force=True)

    def _execute(self, request: ArticulateRequest, stop: threading.Event) -> ArticulateResult:
        model = request.model or self._model_from_service()
        if isinstance(model, Refusal):
            return _refusal(model.reason, model.detail)
        self._pace = None
        result = self.bridge.articulate(request, model, now_ns=time.time_ns(),
                                        on_tick=self._on_tick, cancel=stop)
        self.mode = "fault" if result.reason == "robot_error" else "idle"
        log.info("articulate: success=%s reason=%s articulated=%.4f peak %.1f N mean %.1f N",
                 result.success, result.reason, result.articulated, result.peak_force_n,
                 result.mean_force_n)
        return result

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

    def _on_tick(self, state: BackendState, moving: bool) -> None:
        """Per control tick: publish at the state rate; pace a simulation to real time."""
        self.mode = "articulating"
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
                         backend=self.backend.name)
        self.service.publish(keys.robot_state, msg)


def _rigid(T: np.ndarray) -> np.ndarray:
    """A pose with its rotation re-orthonormalised (simulation round-off would fail decoding)."""
    out = np.array(T, "<f8")
    u, _, vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = u @ vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _refusal(reason: str, detail: str = "") -> ArticulateResult:
    if detail:
        log.warning("articulate refused: %s (%s)", reason, detail)
    return ArticulateResult(success=False, reason=reason, articulated=0.0, peak_force_n=0.0,
                            mean_force_n=0.0, duration_s=0.0)


def kinematics_model_fetcher(bus: QueryBus, keys: Keys, timeout_s: float,
                             reject: Callable[[str, str], None]) -> ModelFetcher:
    """Ask the kinematics service for its model; replies from any other session are set aside
    and reported to ``reject(reason, detail)`` (``Service.reject``: counted and logged)."""

    def fetch() -> KinematicModel | None:
        try:
            answer = ask_service(bus, keys, "kinematics", keys.kinematics_model,
                                 timeout=timeout_s)
        except UntrustedReply as exc:
            _report(exc.untrusted, reject)
            if isinstance(exc, AmbiguousReply):
                reject("ambiguous_reply", str(exc))
            raise
        _report(answer.untrusted, reject)
        return KinematicModel.from_msgpack(answer.reply.payload)

    return fetch


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
    if fetch_model is None and isinstance(bus, Bus):
        fetch_model = kinematics_model_fetcher(bus, keys, config.model_query_timeout_s,
                                               service.reject)
    node = RobotBridgeNode(service, backend, config, fetch_model)
    robot = threading.Thread(target=node.run_robot, args=(stop,), name="robot", daemon=True)
    robot.start()
    try:
        service.run(stop)
    finally:
        stop.set()
        robot.join(10.0)
        backend.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--backend`` (overrides ``robot_bridge.backend``); the CLI adds rig/config/zenoh itself."""
    parser.add_argument("--backend", choices=("mujoco", "panda"),
                        help="robot backend (default: robot_bridge.backend, mujoco)")


def main(args: argparse.Namespace) -> int:
    """``handkse robot-bridge``: config from ``--config``/``--set``, backend from the config."""
    config = config_from_args(args)
    if getattr(args, "backend", None):
        config = replace(config, backend=args.backend)
    stop = threading.Event()
    stop_on_signals(stop)
    keys = Keys(args.rig)
    backend = make_backend(config)
    with Bus(zenoh_options_from_args(args, section_from_args(args, "zenoh"))) as bus:
        print(f"robot_bridge ready ({backend.name})", flush=True)
        run(bus, keys, config, backend, stop)
    return 0
