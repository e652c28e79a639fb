"""Fault drills on one host: crash, restart or cut parts of a running pipeline mid-demonstration
and measure how it recovers (issue 8). Used by ``tests/deploy/test_faults.py`` and
``bench/faults.py``.

:class:`FaultRig` starts, on TCP loopback, a router, the tracker and the kinematics service (the
"CPU host") connected to the router *through* a :class:`~services.evaluation.drills.linkproxy.LinkProxy`
(the link that :meth:`FaultRig.inject` can cut), and a robot bridge (MuJoCo, dry runs only)
plus this process's observer session connected directly. Every session, the router's included,
has a lease of ``lease_ms`` (2 s), as in the deployment. The tracker and the kinematics service
keep ``--state-file`` snapshots in the work directory (``ProcessGroup.start_service``).

:func:`run_scenario` replays a synthetic demonstration (stamps shifted to the wall clock, so
the bridge's model-age check applies) at ``rate`` x real time and injects one :class:`Fault`
after ``fault_at`` of its frames. The replay goes on for ``lost_fraction`` of the frames (they
are lost in the outage), then the demonstrator holds still through the outage: after the
restore (restart, link-up, router start) it waits until the observer sees the tokens of the
affected services again, and replays the rest. Times are ``time.monotonic`` seconds at the
observer; a token "vanishes" when the observer gets its liveliness DELETE, "comes back" with
its PUT. Recovery times count from the restore.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from services.common.bus import Bus, BusError, ZenohOptions
from services.common.keys import Keys
from services.common.processes import ProcessGroup, client_args, free_tcp_endpoint, wait_for
from services.common.protocol import ArticulateRequest, ArticulateResult, KinematicModel
from services.common.recording import RecordedMessage
from services.evaluation.drills.linkproxy import LinkProxy
from services.evaluation.pipeline import demo_tangent_error_deg
from services.synthetic.generator import Demonstration
from services.synthetic.replay import demonstration_recording

LEASE_MS = 2000
BEHIND_LINK = ("tracker", "kinematics")       # clients of the router through the link proxy
SERVICES = (*BEHIND_LINK, "robot_bridge")     # every service the rig runs
FAULT_KINDS = ("none", "kill_kinematics", "kill_tracker", "restart_router", "cut_link")
# The bridge's fallback window (robot_bridge.max_cached_model_age_s default) [s].
BRIDGE_CACHE_WINDOW_S = 2.0


@dataclass(frozen=True)
class Fault:
    """One fault: ``kind`` (see :data:`FAULT_KINDS`); ``cut_s``: link-down time for cut_link."""

    kind: str
    cut_s: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"fault kind {self.kind!r} is not one of {FAULT_KINDS}")
        if (self.kind == "cut_link") != (self.cut_s > 0.0):
            raise ValueError("cut_s > 0 goes with kind 'cut_link' only")

    @property
    def name(self) -> str:
        return f"cut_link_{self.cut_s:g}s" if self.kind == "cut_link" else self.kind

    @property
    def victims(self) -> tuple[str, ...]:
        """Services whose liveliness token must vanish for the observer."""
        return {"none": (), "kill_kinematics": ("kinematics",), "kill_tracker": ("tracker",),
                "restart_router": SERVICES, "cut_link": BEHIND_LINK}[self.kind]


@dataclass
class FaultReport:
    """What one scenario measured. Delays in seconds; ``None``: did not happen in time."""

    fault: str
    frames: int                       # frames of the demonstration
    frames_into_outage: int           # frames replayed while the fault was on (lost)
    frames_after_recovery: int        # frames replayed after the victims were back
    updates_before: int               # model updates seen by the observer at the fault
    detection_s: dict[str, float | None] = field(default_factory=dict)  # fault -> token gone
    outage_s: float = 0.0             # fault -> restore (restart, link-up)
    back_s: dict[str, float | None] = field(default_factory=dict)       # restore -> token back
    restored_updates: int | None = None  # kinematics restart: updates of the restored model
    first_model_s: float | None = None   # restore -> first new model at the observer
    first_model_updates: int | None = None
    final_updates: int = 0
    updates_after_recovery: int = 0   # updates absorbed from the first new model on
    bodies: int = 0                   # HandBody messages seen by the observer
    final_type: str = ""
    tangent_error_deg: float = float("nan")
    bridge_during: str | None = None  # dry-run reason during the outage (None: not asked)
    bridge_after: str | None = None   # dry-run reason after recovery
    not_running: list[str] = field(default_factory=list)
    tracebacks: list[str] = field(default_factory=list)
    wall_s: float = 0.0

    def as_dict(self) -> dict[str, object]:
        return dataclasses.asdict(self)


def restamped(demo: Demonstration, end_ns: int | None = None) -> Demonstration:
    """``demo`` with its stamps shifted so the last frame is stamped ``end_ns`` (default now):
    the model carries wall-clock stamps, as from a live camera."""
    end = time.time_ns() if end_ns is None else end_ns
    return dataclasses.replace(demo, stamps_ns=demo.stamps_ns + (end - int(demo.stamps_ns[-1])))


class Player:
    """Publishes recorded frames segment by segment, each segment paced at ``rate`` x the
    recorded spacing (between segments the demonstrator holds still)."""

    def __init__(self, messages: Sequence[RecordedMessage],
                 publish: Callable[[str, bytes], None], rate: float) -> None:
        if rate <= 0:
            raise ValueError(f"rate must be > 0, got {rate}")
        self.messages = messages
        self.publish = publish
        self.rate = rate

    def play(self, start: int, stop: int) -> None:
        if start >= stop:
            return
        t0, log0 = time.perf_counter(), self.messages[start].log_time_ns
        for msg in self.messages[start:stop]:
            delay = t0 + (msg.log_time_ns - log0) * 1e-9 / self.rate - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            self.publish(msg.key, msg.payload)


class FaultRig:
    """The processes of a drill and an observer session; close it (or use ``with``)."""

    def __init__(self, workdir: Path, rig: str = "faults", lease_ms: int = LEASE_MS,
                 bridge: bool = True) -> None:
        self.workdir = Path(workdir)
        self.keys = Keys(rig)
        self.lease_ms = lease_ms
        self.bridge = bridge
        self.group = ProcessGroup(self.workdir)
        self.endpoint = free_tcp_endpoint()
        host, _, port = self.endpoint.removeprefix("tcp/").rpartition(":")
        self.proxy = LinkProxy((host, int(port)))
        self.bus: Bus | None = None
        self._lock = threading.Lock()
        self.models: list[tuple[float, KinematicModel]] = []
        self.body_times: list[float] = []
        self.token_events: list[tuple[float, str, bool]] = []
        self._alive: set[str] = set()

    # --- life cycle ---

    @property
    def lease_args(self) -> list[str]:
        return ["--set", f"zenoh.lease_ms={self.lease_ms}"]

    def start(self, timeout: float = 60.0) -> None:
        """Start every process (in parallel) and wait until every token is visible."""
        self._start_router()
        for service in BEHIND_LINK:
            self._start_service(service)
        if self.bridge:
            self._start_bridge()
        self.bus = Bus(ZenohOptions(mode="client", connect=(self.endpoint,),
                                    multicast_scouting=False, lease_ms=self.lease_ms))
        self.bus.subscribe(self.keys.kinematics_model, self._on_model)
        self.bus.subscribe(self.keys.hand_body, self._on_body)
        self.bus.watch_liveliness(self.keys.alive_all, self._on_token)
        wanted = SERVICES if self.bridge else BEHIND_LINK
        wait_for(lambda: all(self.alive(s) for s in wanted), timeout,
                 f"services {list(wanted)} alive:\n{self.logs()}")

    def close(self) -> None:
        if self.bus is not None:
            self.bus.close()
            self.bus = None
        self.group.stop_all()
        self.proxy.close()

    def __enter__(self) -> FaultRig:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _start_router(self) -> None:
        self.group.start_router(self.endpoint, *self.lease_args)

    def _start_service(self, service: str) -> None:
        self.group.start_service(service, self.proxy.endpoint, self.keys.rig,
                                 extra=self.lease_args)

    def _start_bridge(self) -> None:
        self.group.start("robot_bridge", "robot-bridge",
                         *client_args(self.endpoint, self.keys.rig), *self.lease_args,
                         "--set", "robot_bridge.sim_realtime_factor=0")

    # --- observer ---

    def _on_model(self, _key: str, payload: bytes) -> None:
        model = KinematicModel.from_msgpack(payload)
        with self._lock:
            self.models.append((time.monotonic(), model))

    def _on_body(self, _key: str, _payload: bytes) -> None:
        with self._lock:
            self.body_times.append(time.monotonic())

    def _on_token(self, key: str, alive: bool) -> None:
        service = key.rsplit("/", 1)[-1]
        with self._lock:
            self.token_events.append((time.monotonic(), service, alive))
            (self._alive.add if alive else self._alive.discard)(service)

    def alive(self, service: str) -> bool:
        """Whether the observer currently sees ``service``'s liveliness token."""
        with self._lock:
            return service in self._alive

    def token_change(self, service: str, alive: bool, after: float, timeout: float
                     ) -> float | None:
        """Time of the first event ``service`` -> ``alive`` at or after ``after``; waits up to
        ``timeout`` s from now; None if none came."""
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                for t, s, a in self.token_events:
                    if t >= after and s == service and a == alive:
                        return t
            if time.monotonic() > deadline:
                return None
            time.sleep(0.01)

    def body_count(self) -> int:
        with self._lock:
            return len(self.body_times)

    def last_model(self) -> tuple[float, KinematicModel] | None:
        with self._lock:
            return self.models[-1] if self.models else None

    def first_model_after(self, after: float, timeout: float
                          ) -> tuple[float, KinematicModel] | None:
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                for t, m in self.models:
                    if t >= after:
                        return t, m
            if time.monotonic() > deadline:
                return None
            time.sleep(0.01)

    def wait_settled(self, quiet_s: float = 1.0, timeout: float = 20.0) -> None:
        """Wait until no model arrived for ``quiet_s`` (the pipeline drained)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            last = self.last_model()
            if last is None or time.monotonic() - last[0] >= quiet_s:
                return
            time.sleep(0.05)

    # --- requests ---

    @property
    def observer(self) -> Bus:
        if self.bus is None:
            raise RuntimeError("the fault rig is not started")
        return self.bus

    def get_model(self, timeout: float = 5.0) -> KinematicModel:
        return KinematicModel.from_msgpack(
            self.observer.get(self.keys.kinematics_model, timeout=timeout)[0][1])

    def dry_run(self, joint_type: str) -> str:
        """Ask the robot bridge for a dry-run articulation by the latest model; its reason."""
        amount = 1.0 if joint_type == "revolute" else 0.05
        request = ArticulateRequest(amount=amount, duration_s=3.0, dry_run=True)
        replies = self.observer.get(self.keys.robot_articulate, payload=request.to_msgpack(),
                                    timeout=30.0)
        return ArticulateResult.from_msgpack(replies[0][1]).reason

    def fresh_demonstration(self, timeout: float = 20.0) -> None:
        """Reset the tracker and the kinematics service; clear what the observer recorded."""
        for service in BEHIND_LINK:
            self.observer.get(self.keys.reset(service), timeout=5.0)
        # a reset publishes nothing: let models published before it drain, then start clean
        self.wait_settled(quiet_s=0.3, timeout=timeout)
        with self._lock:
            self.models.clear()
            self.body_times.clear()

    # --- faults ---

    def inject(self, fault: Fault) -> None:
        if fault.kind == "kill_kinematics":
            self.group.kill("kinematics")
        elif fault.kind == "kill_tracker":
            self.group.kill("tracker")
        elif fault.kind == "restart_router":
            self.group.kill("router")
        elif fault.kind == "cut_link":
            self.proxy.cut()

    def restore(self, fault: Fault) -> None:
        if fault.kind == "kill_kinematics":
            self._start_service("kinematics")
        elif fault.kind == "kill_tracker":
            self._start_service("tracker")
        elif fault.kind == "restart_router":
            self._start_router()
        elif fault.kind == "cut_link":
            self.proxy.restore()

    def heal(self, timeout: float = 60.0) -> None:
        """Undo whatever a failed drill left behind: link up, dead processes restarted."""
        self.proxy.restore()
        if not self.group.running("router"):
            self._start_router()
        for service in BEHIND_LINK:
            if not self.group.running(service):
                self._start_service(service)
        if self.bridge and not self.group.running("robot_bridge"):
            self._start_bridge()
        wanted = SERVICES if self.bridge else BEHIND_LINK
        wait_for(lambda: all(self.alive(s) for s in wanted), timeout,
                 f"services {list(wanted)} alive:\n{self.logs()}")

    def health(self) -> tuple[list[str], list[str]]:
        """(processes not running, processes whose log holds a Python traceback)."""
        names = ["router", *(SERVICES if self.bridge else BEHIND_LINK)]
        return ([n for n in names if not self.group.running(n)],
                [n for n in names if "Traceback (most recent call last)" in self.group.log(n)])

    def logs(self, tail: int = 3000) -> str:
        names = ["router", *(SERVICES if self.bridge else BEHIND_LINK)]
        return "\n".join(f"--- {n}.log\n{self.group.log(n)[-tail:]}" for n in names)


def run_scenario(rig: FaultRig, demo: Demonstration, fault: Fault, *, rate: float = 2.5,
                 fault_at: float = 0.4, lost_fraction: float = 0.08,
                 detect_timeout_s: float | None = None, recover_timeout_s: float = 30.0
                 ) -> FaultReport:
    """Replay ``demo`` through ``rig`` with ``fault`` injected part-way; see the module doc."""
    t_begin = time.monotonic()
    rig.fresh_demonstration()
    messages = demonstration_recording(restamped(demo), rig.keys.rig)
    n = len(messages)
    k1 = round(fault_at * n) if fault.kind != "none" else n
    k2 = min(n, k1 + max(1, round(lost_fraction * n))) if fault.kind != "none" else n
    player = Player(messages, rig.observer.put, rate)
    report = FaultReport(fault=fault.name, frames=n, frames_into_outage=k2 - k1,
                         frames_after_recovery=n - k2, updates_before=0)
    joint_type = demo.truth.joint.type
    detect_timeout = detect_timeout_s or rig.lease_ms / 1000 + 5.0

    player.play(0, k1)
    if fault.kind != "none":
        # Strike when the pipeline has caught up with the replay (on a loaded machine it lags),
        # so every fault hits an estimate of about the same size.
        _wait_caught_up(rig, k1)
        last = rig.last_model()
        report.updates_before = last[1].updates if last else 0
        t_fault = time.monotonic()
        rig.inject(fault)
        player.play(k1, k2)
        for v in fault.victims:
            t = rig.token_change(v, False, t_fault, detect_timeout)
            report.detection_s[v] = None if t is None else t - t_fault
        if rig.bridge and fault.kind != "restart_router":  # (router down: nobody can ask)
            _wait_model_older_than(rig, BRIDGE_CACHE_WINDOW_S + 0.5)
            report.bridge_during = _try_dry_run(rig, joint_type)
        if fault.kind == "cut_link":
            time.sleep(max(0.0, t_fault + fault.cut_s - time.monotonic()))
        t_restore = time.monotonic()
        report.outage_s = t_restore - t_fault
        rig.restore(fault)
        for v in fault.victims:
            t = rig.token_change(v, True, t_restore, recover_timeout_s)
            report.back_s[v] = None if t is None else t - t_restore
        if fault.kind == "kill_kinematics" and report.back_s.get("kinematics") is not None:
            try:  # before any new frame: what the restarted service restored
                report.restored_updates = rig.get_model().updates
            except BusError:
                report.restored_updates = None
        rest = threading.Thread(target=player.play, args=(k2, n), name="replay", daemon=True)
        rest.start()
        first = rig.first_model_after(t_restore, recover_timeout_s)
        if first is not None:
            report.first_model_s = first[0] - t_restore
            report.first_model_updates = first[1].updates
        rest.join()
    rig.wait_settled()
    try:
        final = rig.get_model()
        report.final_updates = final.updates
        report.final_type = final.type
        report.tangent_error_deg = demo_tangent_error_deg(final, demo)
        if report.first_model_updates is not None:
            report.updates_after_recovery = final.updates - report.first_model_updates + 1
    except BusError:
        report.final_type = "unreachable"
    report.bodies = rig.body_count()
    if rig.bridge:
        report.bridge_after = _try_dry_run(rig, joint_type)
    report.not_running, report.tracebacks = rig.health()
    report.wall_s = time.monotonic() - t_begin
    return report


def _wait_caught_up(rig: FaultRig, frames: int, timeout: float = 15.0) -> None:
    """Wait until the observer saw a HandBody per replayed frame and the models settled."""
    deadline = time.monotonic() + timeout
    while rig.body_count() < frames and time.monotonic() < deadline:
        time.sleep(0.02)
    rig.wait_settled(quiet_s=0.3, timeout=max(0.5, deadline - time.monotonic()))


def _wait_model_older_than(rig: FaultRig, age_s: float, timeout: float = 10.0) -> None:
    """Wait until the last model the observer saw is ``age_s`` old (none: return at once)."""
    deadline = time.monotonic() + timeout
    while (last := rig.last_model()) is not None and time.monotonic() - last[0] < age_s:
        if time.monotonic() > deadline:
            return
        time.sleep(0.05)


def _try_dry_run(rig: FaultRig, joint_type: str) -> str:
    try:
        return rig.dry_run(joint_type)
    except BusError as exc:
        return f"error: {exc}"
