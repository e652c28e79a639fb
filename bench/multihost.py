"""Multi-host benchmark: the pipeline split over Linux network namespaces, and link cuts.

Layout (``tests/deploy/netns.py``): a ``router`` namespace joined by a veth pair to each of
``gpu`` (the detector side: a live synthetic replay, plus the operator/observer), ``cpu``
(tracker + kinematics) and ``robot`` (robot bridge, MuJoCo); every service is a Zenoh client of
``handkse router`` with a 2 s lease and multicast scouting off.

- :func:`run_demonstration` replays one demonstration through a placement (namespaces or
  loopback) and returns the final model and a dry-run articulation answer;
- :func:`run_outage` cuts the ``cpu`` link (3 s, then 15 s) during a long demonstration and
  measures when the observer saw the liveliness tokens vanish and come back, the first model
  after link up, and what the robot bridge answered meanwhile.

``python -m bench.multihost`` (root only) writes ``bench/results/multihost.json``;
``tests/deploy/test_multihost.py`` asserts on the same runs. Two child commands run inside a
namespace: ``replay`` (a synthetic demonstration stamped with the wall clock, so models are
live for the robot bridge's age check) and ``observe`` (liveliness, models and dry-run
articulations as JSON lines with ``time.monotonic()`` stamps; the clock is shared across
network namespaces).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from services.common.bus import Bus, BusError, ZenohOptions, wait_for_services
from services.common.keys import Keys
from services.common.processes import (
    REPO,
    ProcessGroup,
    child_env,
    client_args,
    free_tcp_endpoint,
)
from services.common.protocol import (
    ArticulateRequest,
    ArticulateResult,
    KinematicModel,
    ProtocolError,
)

LEASE_MS = 2000
PORT = 7447
RIG = "multihost"
ROLES = ("gpu", "cpu", "robot")
PIPELINE = ("tracker", "kinematics")
# Robot-bridge refusals that mean "no usable model from the kinematics service".
STALE_REASONS = ("stale_model", "no_model")
# The long demonstration for link cuts: the key stretched to about 55 s at 30 Hz.
OUTAGE_OBJECT, OUTAGE_DURATION_SCALE = "key", 10.0
DRY_RUN_EVERY_S = 0.2  # the observer's dry-run articulation period during the link cuts
MAX_PENDING_DRY_RUNS = 50
# Robot-bridge answers that say nothing about the model.
NOT_ABOUT_THE_MODEL = ("busy",)


# --- child commands (run inside a namespace) ---


def _options(endpoint: str, lease_ms: int) -> ZenohOptions:
    return ZenohOptions(mode="client", connect=(endpoint,), multicast_scouting=False,
                        lease_ms=lease_ms)


def live_replay(bus: Bus, keys: Keys, object_name: str, participant: int, seed: int,
                duration_scale: float, stop: threading.Event) -> tuple[int, int]:
    """Replay a synthetic demonstration in real time, stamped from now on the wall clock.

    Returns (messages published, stamp_ns of the last one).
    """
    from services.common.recording import replay
    from services.synthetic.generator import generate
    from services.synthetic.replay import demonstration_recording

    demo = generate(object_name, participant, seed, duration_scale=duration_scale)
    stamps = demo.stamps_ns - demo.stamps_ns[0] + time.time_ns()
    messages = demonstration_recording(replace(demo, stamps_ns=stamps), keys.rig)
    count = replay(messages, bus.put, rate=1.0, stop=stop)
    return count, int(stamps[count - 1]) if count else 0


def cmd_replay(args: argparse.Namespace) -> int:
    from services.common.service import stop_on_signals

    stop = threading.Event()
    stop_on_signals(stop)
    keys = Keys(args.rig)
    with Bus(_options(args.connect, args.lease_ms)) as bus:
        wait_for_services(bus, keys, list(PIPELINE), 60.0)
        count, last = live_replay(bus, keys, args.object, args.participant, args.seed,
                                  args.duration_scale, stop)
        time.sleep(0.2)  # let the last BLOCK-mode samples leave before the session closes
    print(f"replayed {count} messages, last stamp {last}", flush=True)
    return 0


class Observer:
    """Operator and observer on one session; every event is one JSON line with ``t``."""

    def __init__(self, bus: Bus, keys: Keys, out: Any) -> None:
        self.bus, self.keys, self.out = bus, keys, out
        self._lock = threading.Lock()
        self.latest_type = "prismatic"

    def emit(self, kind: str, **fields: Any) -> None:
        line = json.dumps({"t": time.monotonic(), "kind": kind, **fields})
        with self._lock:
            self.out.write(line + "\n")
            self.out.flush()

    def on_alive(self, key: str, alive: bool) -> None:
        self.emit("alive", service=key.rsplit("/", 1)[-1], alive=alive)

    def on_model(self, _key: str, payload: bytes) -> None:
        model = KinematicModel.from_msgpack(payload)
        self.latest_type = model.type
        self.emit("model", updates=model.updates, stamp_ns=model.stamp_ns, type=model.type,
                  seq=model.seq)

    def dry_run(self, kind: str = "dry_run") -> None:
        """Ask the robot bridge for a dry-run articulation along the kinematics service's model."""
        amount = 0.5 if self.latest_type == "revolute" else 0.05  # rad or m
        request = ArticulateRequest(amount=amount, duration_s=2.0, dry_run=True)
        t0 = time.monotonic()
        try:
            replies = self.bus.get(self.keys.robot_articulate, payload=request.to_msgpack(),
                                   timeout=30.0)
            result = ArticulateResult.from_msgpack(replies[0][1])
        except (BusError, ProtocolError) as exc:
            self.emit(kind, t0=t0, error=str(exc))
            return
        self.emit(kind, t0=t0, reason=result.reason, success=result.success)

    def final_model(self) -> None:
        try:
            payload = self.bus.get(self.keys.kinematics_model, timeout=5.0)[0][1]
        except BusError as exc:
            self.emit("final", error=str(exc))
            return
        self.emit("final", payload=payload.hex())


def cmd_observe(args: argparse.Namespace) -> int:
    """Events until SIGTERM; then the final model (and a last dry run). Dry runs start every
    ``--dry-run-every`` s in their own thread, so a slow answer does not stop the sampling
    (the bridge answers ``busy`` while it is still on an earlier one)."""
    from services.common.service import stop_on_signals

    stop = threading.Event()
    stop_on_signals(stop)
    keys = Keys(args.rig)
    with open(args.events, "w") as out, Bus(_options(args.connect, args.lease_ms)) as bus:
        obs = Observer(bus, keys, out)
        bus.watch_liveliness(keys.alive_all, obs.on_alive)
        bus.subscribe(keys.kinematics_model, obs.on_model)
        obs.emit("ready")
        pending: list[threading.Thread] = []
        while not stop.is_set():
            pending = [t for t in pending if t.is_alive()]
            if args.dry_run_every > 0 and len(pending) < MAX_PENDING_DRY_RUNS:
                pending.append(threading.Thread(target=obs.dry_run, daemon=True))
                pending[-1].start()
            stop.wait(args.dry_run_every if args.dry_run_every > 0 else 0.1)
        for t in pending:
            t.join(35.0)
        obs.final_model()
        if args.final_dry_run:
            obs.dry_run("final_dry_run")
        obs.emit("stopped")
    return 0


# --- parent side ---


@dataclass(frozen=True)
class Placement:
    """Where one run's processes live: a command prefix per role (``router`` and ``ROLES``),
    the router's listen endpoint and the endpoint each role's clients connect to."""

    name: str
    listen: str
    connect: Mapping[str, str]
    prefix: Mapping[str, Sequence[str]]


def loopback_placement() -> Placement:
    """Everything on this host's loopback (the one-host reference)."""
    endpoint = free_tcp_endpoint()
    return Placement("loopback", endpoint, {r: endpoint for r in ROLES},
                     {r: () for r in ("router", *ROLES)})


def netns_placement(topology: Any) -> Placement:
    """The router in the hub namespace, each role in its own leaf (a ``netns.Topology``)."""
    return Placement(
        "netns", f"tcp/0.0.0.0:{PORT}",
        {r: f"tcp/{topology.leaves[r].hub_address}:{PORT}" for r in ROLES},
        {r: topology.prefix(r) for r in ("router", *ROLES)})


class EventLog:
    """The observer's JSON lines, read incrementally."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.events: list[dict[str, Any]] = []
        self._offset = 0

    def read(self) -> list[dict[str, Any]]:
        if self.path.exists():
            with open(self.path, "rb") as f:
                f.seek(self._offset)
                data = f.read()
            end = data.rfind(b"\n") + 1  # a partly written last line waits for the next read
            for line in data[:end].splitlines():
                self.events.append(json.loads(line))
            self._offset += end
        return self.events

    def of(self, kind: str, after: float = float("-inf")) -> list[dict[str, Any]]:
        return [e for e in self.read() if e["kind"] == kind and e["t"] > after]


@dataclass
class Run:
    """The processes of one run in ``group``: router, pipeline, robot bridge, observer, replay."""

    group: ProcessGroup
    placement: Placement
    workdir: Path
    log: EventLog = field(init=False)

    def __post_init__(self) -> None:
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.log = EventLog(self.workdir / "observer.jsonl")
        self.log.path.unlink(missing_ok=True)  # events of an earlier run must not count

    def _zenoh(self, role: str) -> list[str]:
        return [*client_args(self.placement.connect[role], RIG),
                "--set", f"zenoh.lease_ms={LEASE_MS}"]

    def _child(self, name: str, role: str, *args: str) -> subprocess.Popen[bytes]:
        """``python -m bench.multihost <args>`` in ``role``'s place, owned by the group."""
        log = open(self.group.log_path(name), "ab")  # noqa: SIM115 - owned by the child
        cmd = [*self.placement.prefix[role], sys.executable, "-m", "bench.multihost", *args,
               "-e", self.placement.connect[role], "--rig", RIG, "--lease-ms", str(LEASE_MS)]
        p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=child_env(),
                             cwd=REPO)
        log.close()
        self.group.procs[name] = p
        return p

    def start(self, robot: bool = True, dry_run_every_s: float = 0.0,
              timeout: float = 90.0) -> float:
        """Start everything but the replay; returns seconds until every token was seen."""
        t0 = time.monotonic()
        g, pre = self.group, self.placement.prefix
        g.start("router", "router", "-l", self.placement.listen, "--no-multicast-scouting",
                "--set", f"zenoh.lease_ms={LEASE_MS}", prefix=pre["router"])
        g.wait_log("router", "router ready", timeout)
        for service in PIPELINE:
            extra = ["--state-file", str(self.workdir / f"{service}.state")]
            g.start(service, service, *self._zenoh("cpu"), *extra, prefix=pre["cpu"])
        services = list(PIPELINE)
        if robot:
            g.start("robot_bridge", "robot-bridge", *self._zenoh("robot"), prefix=pre["robot"])
            services.append("robot_bridge")
        self._child("observer", "gpu", "observe", "--events", str(self.log.path),
                    "--dry-run-every", str(dry_run_every_s), "--final-dry-run")
        self.wait(lambda: all(self.alive(s) for s in services), timeout,
                  f"liveliness tokens of {services}", ("observer", *services))
        return time.monotonic() - t0

    def start_replay(self, object_name: str, duration_scale: float = 1.0,
                     participant: int = 3, seed: int = 0) -> subprocess.Popen[bytes]:
        return self._child("replay", "gpu", "replay", "--object", object_name,
                           "--participant", str(participant), "--seed", str(seed),
                           "--duration-scale", str(duration_scale))

    def alive(self, service: str, after: float = float("-inf")) -> bool:
        """Whether the last liveliness event of ``service`` after ``after`` says alive."""
        events = [e for e in self.log.of("alive", after) if e["service"] == service]
        return bool(events) and bool(events[-1]["alive"])

    def wait(self, predicate: Callable[[], bool], timeout: float, what: str,
             watch: Sequence[str] = (), logs: Sequence[str] = ()) -> None:
        """Poll ``predicate``; raise naming ``what``, with the log tails of the ``watch`` and
        ``logs`` processes, on timeout or when a watched process exits."""
        deadline = time.monotonic() + timeout
        while not predicate():
            dead = [n for n in watch if not self.group.running(n)]
            if dead or time.monotonic() > deadline:
                why = f"{dead} exited" if dead else f"timed out after {timeout:.0f} s"
                tails = "\n".join(f"--- {n}:\n{self.group.log(n)[-3000:]}"
                                  for n in dict.fromkeys([*dead, *watch, *logs]))
                raise TimeoutError(f"{why} waiting for {what} ({len(self.log.of('model'))} "
                                   f"models seen)\n{tails}")
            time.sleep(0.1)

    def stop_observer(self, timeout: float = 60.0) -> None:
        """SIGTERM the observer; it queries the final model and a dry run, then exits."""
        p = self.group.procs["observer"]
        p.send_signal(signal.SIGTERM)
        p.wait(timeout)

    def crashed(self, names: Sequence[str]) -> dict[str, str]:
        """Processes in ``names`` that exited or logged a traceback, with their log tail."""
        return {n: self.group.log(n)[-3000:] for n in names
                if not self.group.running(n) or "Traceback" in self.group.log(n)}


@dataclass(frozen=True)
class DemoRun:
    """Result of one demonstration through one placement."""

    placement: str
    model: KinematicModel
    tangent_error_deg: float
    models_seen: int
    dry_run: dict[str, Any]          # the observer's final dry-run event
    startup_s: float                 # processes started until every token was seen
    replay_s: float                  # replay start until the pipeline settled


def run_demonstration(placement: Placement, workdir: Path, object_name: str = "slider",
                      robot: bool = True) -> DemoRun:
    """One demonstration (participant 3, seed 0) through ``placement``; the final model."""
    from services.evaluation.pipeline import demo_tangent_error_deg
    from services.synthetic.generator import generate

    with ProcessGroup(workdir) as group:
        run = Run(group, placement, workdir)
        startup = run.start(robot=robot)
        t0 = time.monotonic()
        replay = run.start_replay(object_name)
        run.wait(lambda: replay.poll() is not None, 120.0, "the replay to finish",
                 ("router", *PIPELINE))
        if replay.returncode != 0:
            raise RuntimeError(f"replay failed:\n{group.log('replay')}")
        last_stamp = int(group.log("replay").rsplit("last stamp", 1)[1].split()[0])
        _wait_settled(run, last_stamp)
        replay_s = time.monotonic() - t0
        run.stop_observer()
        final = run.log.of("final")
        if not final or "payload" not in final[-1]:
            raise RuntimeError(f"no final model: {final}\n{group.log('observer')}")
        model = KinematicModel.from_msgpack(bytes.fromhex(final[-1]["payload"]))
        dry = run.log.of("final_dry_run")
        crashed = run.crashed(["router", *PIPELINE, *(["robot_bridge"] if robot else [])])
        if crashed:
            raise RuntimeError(f"processes crashed: {crashed}")
    error = demo_tangent_error_deg(model, generate(object_name, 3, 0))
    return DemoRun(placement.name, model, error, len(run.log.of("model")),
                   dry[-1] if dry else {}, startup, replay_s)


def _wait_settled(run: Run, last_stamp: int, quiet_s: float = 2.0, timeout: float = 60.0
                  ) -> None:
    """Wait for the model of the last replayed frame, or for ``quiet_s`` without a new one."""

    def settled() -> bool:
        models = run.log.of("model")
        return bool(models) and (models[-1]["stamp_ns"] >= last_stamp
                                 or time.monotonic() - models[-1]["t"] > quiet_s)

    run.wait(settled, timeout, "the model of the last replayed frame",
             ("router", *PIPELINE, "observer"), ("replay",))


@dataclass
class Cut:
    """One link cut of the ``cpu`` namespace and what the observer saw around it.

    ``down``/``up`` are ``time.monotonic()`` when ``ip link set down``/``up`` had returned.
    ``vanished`` is seconds from ``down`` to each token's disappearance (None: it stayed until
    link up); ``back`` and ``first_model_s`` are seconds from ``up`` (None: never).
    ``dry_runs_during`` lists (start, answer) in seconds after ``down`` and the reason of every
    dry run started while the link was down.
    """

    duration_s: float
    down: float
    up: float
    up_start: float = 0.0  # when ``ip link set up`` was started
    vanished: dict[str, float | None] = field(default_factory=dict)
    back: dict[str, float | None] = field(default_factory=dict)
    first_model_s: float | None = None
    updates_before: int = -1
    first_updates_after: int = -1
    models_after: int = 0
    dry_runs_during: list[tuple[float, float, str]] = field(default_factory=list)
    dry_run_after: str | None = None
    robot_token_lost: bool = False

    def answered_during(self, grace_s: float = 0.0) -> list[str]:
        """Reasons of the dry runs started ``grace_s`` or more after link down and answered
        before link up (so decided inside that window), leaving out ``busy``."""
        window = self.up_start - self.down
        return [reason for start, end, reason in self.dry_runs_during
                if start >= grace_s and end < window and reason not in NOT_ABOUT_THE_MODEL]

    def started_during(self) -> list[str]:
        """Reasons of all dry runs started while the link was down, whenever answered."""
        return [reason for _, _, reason in self.dry_runs_during]

    @property
    def first_refusal_s(self) -> float | None:
        """Seconds from link down to the first stale/no-model answer."""
        return min((end for _, end, reason in self.dry_runs_during if reason in STALE_REASONS),
                   default=None)

    @property
    def slowest_answer_s(self) -> float | None:
        """The longest a dry run started during the outage waited for its answer."""
        return max((end - start for start, end, _ in self.dry_runs_during), default=None)

    def to_json(self) -> dict[str, Any]:
        r = lambda x: None if x is None else round(x, 3)  # noqa: E731
        return {"cut_s": self.duration_s, "tokens_vanished_after_s": {
                    k: r(v) for k, v in self.vanished.items()},
                "tokens_back_after_link_up_s": {k: r(v) for k, v in self.back.items()},
                "first_model_after_link_up_s": r(self.first_model_s),
                "updates_before": self.updates_before,
                "first_updates_after": self.first_updates_after,
                "robot_dry_runs_started_during_outage": len(self.dry_runs_during),
                "robot_answers_before_link_up": dict(Counter(self.answered_during())),
                "robot_answers_after_cache_expiry": dict(Counter(
                    self.answered_during(stale_grace_s()))),
                "first_robot_refusal_after_s": r(self.first_refusal_s),
                "slowest_robot_answer_during_outage_s": r(self.slowest_answer_s),
                "robot_dry_run_after_recovery": self.dry_run_after,
                "robot_bridge_token_lost": self.robot_token_lost}


def stale_grace_s() -> float:
    """From link down, how long the robot bridge may still act on the model it received last:
    its ``max_cached_model_age_s`` plus 0.2 s for samples already in flight at the cut."""
    from services.robot_bridge.config import RobotBridgeConfig

    return float(getattr(RobotBridgeConfig(), "max_cached_model_age_s", 0.0)) + 0.2


def _reason(event: Mapping[str, Any]) -> str:
    return str(event.get("reason", f"error: {event.get('error')}"))


def _usable_dry_run(run: Run, after: float) -> dict[str, Any] | None:
    """The first dry run started after ``after`` that was not refused for a missing model."""
    return next((d for d in run.log.of("dry_run") if d["t0"] > after and "reason" in d
                 and d["reason"] not in (*STALE_REASONS, *NOT_ABOUT_THE_MODEL)), None)


def cut_link(run: Run, topology: Any, duration_s: float, recover_timeout: float = 45.0,
             min_models: int = 10) -> Cut:
    """Cut ``cpu`` for ``duration_s``, restore it, and wait until the pipeline is back: both
    tokens seen again, ``min_models`` new models and a dry run answered on a live model."""
    models = run.log.of("model")
    before = models[-1]["updates"] if models else -1
    topology.link_down("cpu")
    down = time.monotonic()
    try:
        time.sleep(duration_s)  # the outage itself, not a synchronisation
    finally:
        up_start = time.monotonic()
        topology.link_up("cpu")
    up = time.monotonic()
    cut = Cut(duration_s, down, up, updates_before=before)

    def recovered() -> bool:
        after = run.log.of("model", up)
        return (all(run.alive(s, up) for s in PIPELINE) and len(after) >= min_models
                and _usable_dry_run(run, after[0]["t"]) is not None)

    with contextlib.suppress(TimeoutError):  # the caller asserts on what is missing
        run.wait(recovered, recover_timeout, f"recovery after a {duration_s:g} s cut",
                 ("router", *PIPELINE, "robot_bridge", "observer"))
    alive = run.log.of("alive", down)
    for s in PIPELINE:
        gone = [e["t"] for e in alive if e["service"] == s and not e["alive"] and e["t"] <= up]
        cut.vanished[s] = gone[0] - down if gone else None
        back = [e["t"] for e in alive if e["service"] == s and e["alive"] and e["t"] > up]
        cut.back[s] = back[0] - up if back else None
    cut.robot_token_lost = any(e["service"] == "robot_bridge" and not e["alive"] for e in alive)
    after = run.log.of("model", up)
    cut.models_after = len(after)
    if after:
        cut.first_model_s = after[0]["t"] - up
        cut.first_updates_after = after[0]["updates"]
        usable = _usable_dry_run(run, after[0]["t"])
        cut.dry_run_after = _reason(usable) if usable else None
    cut.up_start = up_start
    return cut


def _fill_dry_runs(cut: Cut, run: Run) -> None:
    """The dry runs started during ``cut`` (call once the observer has stopped, so that late
    answers are in)."""
    cut.dry_runs_during = sorted((d["t0"] - cut.down, d["t"] - cut.down, _reason(d))
                                 for d in run.log.of("dry_run")
                                 if cut.down <= d["t0"] < cut.up_start)


@dataclass
class OutageRun:
    cuts: list[Cut]
    dry_run_before: str | None       # a dry run after the first model, before the first cut
    crashed: dict[str, str]          # process -> log tail, for any that exited or failed
    startup_s: float


def run_outage(topology: Any, workdir: Path, cuts: Sequence[float] = (3.0, 15.0)
               ) -> OutageRun:
    """A long live demonstration through the namespaces with ``cpu`` cut for each duration."""
    with ProcessGroup(workdir) as group:
        run = Run(group, netns_placement(topology), workdir)
        startup = run.start(robot=True, dry_run_every_s=DRY_RUN_EVERY_S)
        run.start_replay(OUTAGE_OBJECT, OUTAGE_DURATION_SCALE)
        watch = ("router", *PIPELINE, "robot_bridge", "observer", "replay")
        run.wait(lambda: any(m["updates"] > 0 for m in run.log.of("model")), 60.0,
                 "the first model", watch)
        first = next(m["t"] for m in run.log.of("model") if m["updates"] > 0)
        run.wait(lambda: _usable_dry_run(run, first) is not None, 30.0,
                 "a dry run on a live model before the cuts", watch)
        usable = _usable_dry_run(run, first)
        done = [cut_link(run, topology, d) for d in cuts]
        crashed = run.crashed(["router", *PIPELINE, "robot_bridge"])
        run.stop_observer()
        for cut in done:
            _fill_dry_runs(cut, run)
        if not group.running("replay") and group.procs["replay"].returncode != 0:
            crashed["replay"] = group.log("replay")[-3000:]
    return OutageRun(done, _reason(usable) if usable else None, crashed, startup)


# --- benchmark entry ---


def main() -> None:
    from bench.common import write_result
    from tests.deploy.netns import Topology, remove_stale, unavailable_reason

    reason = unavailable_reason()
    if reason is not None:
        print(f"skipping multihost: {reason}")
        return
    remove_stale()
    with tempfile.TemporaryDirectory(prefix="handkse-multihost-") as tmp:
        with Topology(ROLES) as topology:
            outage = run_outage(topology, Path(tmp) / "outage")
            ns = run_demonstration(netns_placement(topology), Path(tmp) / "netns")
        one = run_demonstration(loopback_placement(), Path(tmp) / "loopback")
    write_result("multihost", {
        "layout": "router namespace + veth /30 links to gpu (replay, observer), cpu (tracker, "
                  "kinematics), robot (robot bridge, MuJoCo); Zenoh clients, lease "
                  f"{LEASE_MS} ms, multicast scouting off",
        "lease_ms": LEASE_MS,
        "outage": {"object": OUTAGE_OBJECT, "duration_scale": OUTAGE_DURATION_SCALE,
                   "startup_s": round(outage.startup_s, 2),
                   "robot_dry_run_before_cuts": outage.dry_run_before,
                   "dry_run_every_s": DRY_RUN_EVERY_S, "stale_grace_s": stale_grace_s(),
                   "cuts": [c.to_json() for c in outage.cuts],
                   "crashed": sorted(outage.crashed)},
        "same_model": {d.placement: {"tangent_error_deg": round(d.tangent_error_deg, 3),
                                     "type": d.model.type, "updates": d.model.updates,
                                     "startup_s": round(d.startup_s, 2),
                                     "replay_to_settled_s": round(d.replay_s, 2),
                                     "robot_dry_run": d.dry_run.get("reason")}
                       for d in (ns, one)},
    })


def _child_main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.multihost",
                                     description="multihost benchmark and its child commands")
    sub = parser.add_subparsers(dest="command")
    for name in ("replay", "observe"):
        p = sub.add_parser(name)
        p.add_argument("-e", "--connect", required=True, help="router endpoint")
        p.add_argument("--rig", default=RIG)
        p.add_argument("--lease-ms", type=int, default=LEASE_MS)
        if name == "replay":
            p.add_argument("--object", default="slider")
            p.add_argument("--participant", type=int, default=3)
            p.add_argument("--seed", type=int, default=0)
            p.add_argument("--duration-scale", type=float, default=1.0)
        else:
            p.add_argument("--events", type=Path, required=True, help="JSON-lines output")
            p.add_argument("--dry-run-every", type=float, default=0.0,
                           help="seconds between dry-run articulations (0: none)")
            p.add_argument("--final-dry-run", action="store_true")
    args = parser.parse_args(argv)
    if args.command == "replay":
        return cmd_replay(args)
    if args.command == "observe":
        return cmd_observe(args)
    main()
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    sys.exit(_child_main(sys.argv[1:]))
