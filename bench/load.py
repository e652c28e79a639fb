"""Load benchmark: the filter services under real-time and 5x replay, one and two rigs per router.

Issue 8, item 5. Goal: no drops in the filter services at 5x, end-to-end p99 < 10 ms (camera stamp
-> model published), the detector excluded. The flood of issue 13 (5,000 landmark messages/s:
nothing lost silently, ``stats`` answering, the model unchanged) is ``bench/flood.py``, run by
:func:`main` as well (``--flood-only`` runs it alone).

Each scenario starts a fresh router (TCP loopback) and, per rig, one ``handkse tracker`` and one
``handkse kinematics`` as child processes (:class:`~services.common.processes.ProcessGroup`).
One publisher *process* per rig replays synthetic demonstrations back to back with
:func:`services.common.recording.replay` at the scenario's rate. Each ``HandLandmarks`` gets
``stamp_ns = time.time_ns()`` just before it is encoded and put: that is the camera stamp, as if
the detector took no time. Between two demonstrations the publisher waits until both services
have handled everything it sent (their ``stats`` counters agree) and resets them, as an operator
does between demonstrations.

This process only observes: per rig it subscribes to landmarks, hand bodies and models and takes
``time.time_ns()`` first thing in each callback. The tracker stamps a ``HandBody`` with its
landmarks' stamp and the kinematics model carries the stamp of the last hand body it absorbed
(``KinematicModel.stamp_ns``), so ``t_receive - model.stamp_ns`` is camera stamp -> model
published **plus one extra router hop to this observer**; ``camera_to_landmarks_one_hop`` (the
landmarks themselves, seen here) measures that hop under the same load.

Drops per rig (:func:`rig_counts`, :func:`dropped`): landmarks the tracker never received,
bodies kinematics never received (both from the services' ``stats``) and what the services
counted as ``dropped``; apart from those, frames the tracker handled without publishing a body
(the synthetic demonstrations yield a body for every frame) and what the observer missed.
CPU per process: ``utime + stime`` from ``/proc/<pid>/stat`` over the run (publishers: their own
``process_time``, which includes :func:`~services.common.recording.replay`'s spin-wait), in
percent of one core and in ms per landmark frame. The services' per-stage latencies (tracker
``step``, kinematics ``update``) come from their ``stats`` (the last 2000 samples of each).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from bench.common import percentiles_ms, update_result, write_result
from services.common.bus import Bus, BusError, ZenohOptions
from services.common.keys import Keys
from services.common.processes import (
    REPO,
    STATEFUL,
    ProcessGroup,
    child_env,
    client_args,
    free_tcp_endpoint,
    wait_for,
)
from services.common.protocol import HandBody, HandLandmarks, KinematicModel, ServiceStats
from services.common.recording import replay
from services.synthetic.generator import generate
from services.synthetic.objects import OBJECTS
from services.synthetic.replay import demonstration_recording, landmark_messages

FILTERS = ("tracker", "kinematics")
GOAL_P99_MS = 10.0
SETTLE_TIMEOUT_S = 20.0
Demo = tuple[str, int]  # (object, participant)


def client_options(endpoint: str) -> ZenohOptions:
    return ZenohOptions(mode="client", connect=(endpoint,), multicast_scouting=False)


def service_stats(bus: Bus, keys: Keys, service: str) -> ServiceStats:
    return ServiceStats.from_msgpack(bus.get(keys.stats(service))[0][1])


def cpu_seconds(pid: int) -> float:
    """``utime + stime`` of a process so far [s] (Linux ``/proc/<pid>/stat``)."""
    text = Path(f"/proc/{pid}/stat").read_text()
    fields = text[text.rindex(")") + 2:].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


# --- publisher process (one per rig) ---


def _settled(bus: Bus, keys: Keys, sent: int) -> bool:
    """True when the rig's tracker and kinematics have handled everything sent so far.

    The tracker receives the landmarks and every model kinematics published;
    kinematics receives every body the tracker published.
    """
    try:
        t = service_stats(bus, keys, "tracker")
        k = service_stats(bus, keys, "kinematics")
    except BusError:  # a stats query that timed out under load: ask again
        return False
    return k.received == t.published and t.received == sent + k.published


def publish_rig(endpoint: str, rig: str, demos: Sequence[Demo], rate: float,
                report: Path, restamp: bool = True) -> None:
    """Publisher process: generate ``demos``, print ``publisher ready``, wait for a line on
    stdin, replay them on ``rig`` at ``rate`` and write ``report`` (JSON:
    ``{"rig", "stamps": [[stamp_ns, ...] per demonstration], "settle_timeouts", "cpu_s"}``).

    ``restamp``: stamp each frame with the wall clock at sending (latency measurable); else
    keep the demonstration's own capture spacing, shifted to start at the wall clock (the
    filters then see the same time steps at any ``rate``).
    """
    keys = Keys(rig)
    prepared = []
    for name, participant in demos:
        demo = generate(name, participant, 0)
        prepared.append((demonstration_recording(demo, rig), landmark_messages(demo)))
    stamps: list[list[int]] = []
    timeouts = 0
    with Bus(client_options(endpoint)) as bus:
        print("publisher ready", flush=True)
        sys.stdin.readline()
        cpu0 = time.process_time()
        seq = 0
        for i, (recording, messages) in enumerate(prepared):
            if i > 0:  # a new demonstration: the operator resets both services
                for service in ("kinematics", "tracker"):
                    bus.get(keys.reset(service), timeout=10.0)
            demo_stamps: list[int] = []
            frames = iter(messages)
            shift = time.time_ns() - messages[0].stamp_ns

            def put(key: str, _payload: bytes, frames: Any = frames,
                    demo_stamps: list[int] = demo_stamps, shift: int = shift) -> None:
                nonlocal seq
                frame = next(frames)
                stamp = time.time_ns() if restamp else frame.stamp_ns + shift
                message = replace(frame, seq=seq, stamp_ns=stamp)
                bus.put(key, message.to_msgpack())
                demo_stamps.append(stamp)
                seq += 1

            replay(recording, put, rate=rate)
            stamps.append(demo_stamps)
            sent = sum(len(s) for s in stamps)
            try:
                wait_for(lambda sent=sent: _settled(bus, keys, sent), SETTLE_TIMEOUT_S,
                         f"{rig}: services handled {sent} landmarks", period=0.05)
            except TimeoutError:
                timeouts += 1
        cpu_s = time.process_time() - cpu0
        time.sleep(0.2)  # let the last samples leave before the session closes
    report.write_text(json.dumps({"rig": rig, "stamps": stamps, "settle_timeouts": timeouts,
                                  "cpu_s": cpu_s}))


def _start_publisher(group: ProcessGroup, endpoint: str, rig: str, demos: Sequence[Demo],
                     rate: float, restamp: bool) -> tuple[subprocess.Popen[bytes], Path]:
    report = group.workdir / f"{rig}-publisher.json"
    cmd = [sys.executable, "-m", "bench.load", "--publish", rig, "--endpoint", endpoint,
           "--rate", str(rate), "--report", str(report), *(f"{o}:{p}" for o, p in demos),
           *([] if restamp else ["--capture-stamps"])]
    with open(group.log_path(f"{rig}-publisher"), "wb") as log:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=log,
                                stderr=subprocess.STDOUT, env=child_env(), cwd=REPO)
    group.procs[f"{rig}-publisher"] = proc  # stopped with the group
    return proc, report


# --- observer (this process) ---


@dataclass
class RigTrace:
    """What the observer saw of one rig: ``(t_receive_ns, payload)`` per message."""

    landmarks: list[tuple[int, bytes]] = field(default_factory=list)
    bodies: list[tuple[int, bytes]] = field(default_factory=list)
    models: list[tuple[int, bytes]] = field(default_factory=list)


def _recorder(samples: list[tuple[int, bytes]]) -> Any:
    def on_sample(_key: str, payload: bytes) -> None:
        samples.append((time.time_ns(), payload))

    return on_sample


@dataclass
class RigRun:
    """One rig's run, decoded."""

    rig: str
    demos: list[Demo]
    sent_stamps: list[list[int]]                 # per demonstration
    settle_timeouts: int
    landmarks: list[tuple[int, int]]              # (t_receive_ns, stamp_ns)
    bodies: list[tuple[int, HandBody]]
    models: list[tuple[int, KinematicModel]]
    stats: dict[str, ServiceStats]

    @property
    def sent(self) -> int:
        return sum(len(s) for s in self.sent_stamps)


@dataclass
class ScenarioRun:
    name: str
    rate: float
    wall_s: float
    rigs: dict[str, RigRun]
    cpu_percent: dict[str, float]
    load_before: list[float]
    load_after: list[float]


def _start_services(group: ProcessGroup, endpoint: str, rigs: Sequence[str],
                    state_files: bool) -> None:
    for rig in rigs:
        for service in FILTERS:
            state = (["--state-file", str(group.workdir / f"{rig}-{service}.state")]
                     if state_files and service in STATEFUL else [])
            group.start(f"{rig}-{service}", service, *client_args(endpoint, rig), *state)


def run_scenario(name: str, rigs: dict[str, Sequence[Demo]], rate: float,
                 workdir: Path | None = None, state_files: bool = True,
                 restamp: bool = True) -> ScenarioRun:
    """Router + a tracker/kinematics pair per rig; replay each rig's demonstrations at ``rate``.

    ``state_files``: run the services with ``--state-file`` as deployed (kinematics writes its
    state after every update). ``restamp``: see :func:`publish_rig`; without it the latencies
    mean nothing.
    """
    endpoint = free_tcp_endpoint()
    traces = {rig: RigTrace() for rig in rigs}
    group = ProcessGroup(Path(workdir or tempfile.mkdtemp(prefix="handkse-load-")))
    with group:
        group.start_router(endpoint)
        with Bus(client_options(endpoint)) as bus:
            for rig in rigs:
                keys = Keys(rig)
                bus.subscribe(keys.hand_landmarks, _recorder(traces[rig].landmarks))
                bus.subscribe(keys.hand_body, _recorder(traces[rig].bodies))
                bus.subscribe(keys.kinematics_model, _recorder(traces[rig].models))
            _start_services(group, endpoint, list(rigs), state_files)
            wanted = {Keys(rig).alive(s) for rig in rigs for s in FILTERS}
            wait_for(lambda: wanted <= {k for r in rigs for k in bus.alive(Keys(r).alive_all)},
                     60.0, f"services alive: {sorted(wanted)}", period=0.2)
            publishers = {rig: _start_publisher(group, endpoint, rig, demos, rate, restamp)
                          for rig, demos in rigs.items()}
            for rig in rigs:
                group.wait_log(f"{rig}-publisher", "publisher ready", timeout=120.0)
            pids = {label: proc.pid for label, proc in group.procs.items()
                    if not label.endswith("publisher")}  # publishers measure themselves
            pids["observer"] = os.getpid()
            load_before = [round(x, 2) for x in os.getloadavg()]
            cpu0 = {label: cpu_seconds(pid) for label, pid in pids.items()}
            t0 = time.monotonic()
            for proc, _ in publishers.values():
                assert proc.stdin is not None
                proc.stdin.write(b"go\n")
                proc.stdin.flush()
            limit = 60.0 + max(len(d) for d in rigs.values()) * (SETTLE_TIMEOUT_S + 30.0 / rate)
            wait_for(lambda: all(p.poll() is not None for p, _ in publishers.values()), limit,
                     "the publishers to finish", period=0.05)
            wall = time.monotonic() - t0
            cpu1 = {label: cpu_seconds(pid) for label, pid in pids.items()}
            load_after = [round(x, 2) for x in os.getloadavg()]
            stats = {rig: {s: service_stats(bus, Keys(rig), s) for s in FILTERS} for rig in rigs}
            for label in group.procs:
                if not label.endswith("publisher") and not group.running(label):
                    raise RuntimeError(f"{label} died during the run:\n{group.log(label)}")
            got = {}
            for rig, (proc, report) in publishers.items():
                if proc.returncode != 0 or not report.exists():
                    raise RuntimeError(f"publisher of {rig} failed ({proc.returncode}):\n"
                                       f"{group.log(f'{rig}-publisher')}")
                got[rig] = json.loads(report.read_text())
    runs = {}
    for rig, demos in rigs.items():
        trace = traces[rig]
        runs[rig] = RigRun(
            rig=rig, demos=list(demos), sent_stamps=got[rig]["stamps"],
            settle_timeouts=got[rig]["settle_timeouts"],
            landmarks=[(t, HandLandmarks.from_msgpack(p).stamp_ns) for t, p in trace.landmarks],
            bodies=[(t, HandBody.from_msgpack(p)) for t, p in trace.bodies],
            models=[(t, KinematicModel.from_msgpack(p)) for t, p in trace.models],
            stats=stats[rig])
    cpu = {label: round(100.0 * (cpu1[label] - cpu0[label]) / wall, 1) for label in pids}
    cpu.update({f"{rig}-publisher": round(100.0 * got[rig]["cpu_s"] / wall, 1) for rig in rigs})
    return ScenarioRun(name=name, rate=rate, wall_s=wall, rigs=runs, cpu_percent=cpu,
                       load_before=load_before, load_after=load_after)


# --- report ---


def rig_counts(run: RigRun) -> dict[str, int]:
    """Counts of one rig: what was sent, what each stage handled, what went missing where.

    ``tracker_landmarks`` is the tracker's ``received`` less the models it also received (the
    publisher waited until it had every model kinematics published). ``tracker_no_body``:
    landmarks the tracker handled without publishing a body or counting a rejection (its own
    skips, which ``stats`` does not report).
    """
    sent = {s for demo in run.sent_stamps for s in demo}
    bodies = {b.stamp_ns for _, b in run.bodies}
    initialised = {b.stamp_ns for _, b in run.bodies if b.initialized}
    # every initialised body is answered by a model; before the segmentation decides the first
    # contact phase (its warm-up) that model is still the empty one (no updates), and the
    # phase, dated back to the first frame, absorbs those bodies afterwards
    models = {m.stamp_ns for _, m in run.models}
    t, k = run.stats["tracker"], run.stats["kinematics"]
    tracker_landmarks = t.received - k.published
    return {
        "landmarks_sent": run.sent,
        "tracker_landmarks": tracker_landmarks,
        "tracker_published": t.published,
        "tracker_rejected": sum(t.rejected.values()),
        "tracker_no_body": tracker_landmarks - t.published - sum(t.rejected.values()),
        "kinematics_received": k.received,
        "kinematics_rejected": sum(k.rejected.values()),
        "services_dropped": t.dropped + k.dropped,
        "hand_bodies": len(run.bodies),
        "models": sum(m.updates > 0 for _, m in run.models),
        "landmarks_without_body": len(sent - bodies),
        "initialised_bodies_without_model": len(initialised - models),
        "bodies_not_from_this_rig": len(bodies - sent),
        "models_not_from_this_rig": len(models - initialised),
        "settle_timeouts": run.settle_timeouts,
    }


def dropped(counts: dict[str, int]) -> int:
    """Messages lost on the way (transport or queues): landmarks the tracker never handled,
    bodies kinematics never handled, and what the services counted as dropped. Frames the
    tracker handled without a body are reported apart (``tracker_no_body``)."""
    return (counts["landmarks_sent"] - counts["tracker_landmarks"]
            + counts["tracker_published"] - counts["kinematics_received"]
            + counts["services_dropped"])


def latencies_s(run: RigRun) -> dict[str, list[float]]:
    """Per-message latencies [s] seen by the observer (see the module docstring)."""
    body_at = {b.stamp_ns: t for t, b in run.bodies}
    models = [(t, m) for t, m in run.models if m.updates > 0]
    return {
        "camera_to_model": [(t - m.stamp_ns) * 1e-9 for t, m in models],
        "camera_to_hand_body": [(t - b.stamp_ns) * 1e-9 for t, b in run.bodies],
        "camera_to_landmarks_one_hop": [(t - s) * 1e-9 for t, s in run.landmarks],
        "hand_body_to_model": [(t - body_at[m.stamp_ns]) * 1e-9 for t, m in models
                               if m.stamp_ns in body_at],
    }


def summarise(run: ScenarioRun) -> dict[str, Any]:
    """The JSON form of a scenario, with the goal checks."""
    merged: dict[str, list[float]] = {}
    per_rig: dict[str, Any] = {}
    for rig, r in run.rigs.items():
        lat = latencies_s(r)
        for k, v in lat.items():
            merged.setdefault(k, []).extend(v)
        counts = rig_counts(r)
        per_rig[rig] = {
            "demonstrations": [f"{o}/p{p}" for o, p in r.demos],
            "counts": counts, "dropped": dropped(counts),
            "camera_to_model_ms": (percentiles_ms(lat["camera_to_model"])
                                   if lat["camera_to_model"] else None),
            "service_stats": {s: {"received": st.received, "published": st.published,
                                  "dropped": st.dropped, "rejected": dict(st.rejected),
                                  "latency_ms": {k: dict(v) for k, v in st.latency_ms.items()}}
                              for s, st in r.stats.items()},
        }
    latency = {k: percentiles_ms(v) for k, v in merged.items() if v}
    total_dropped = sum(v["dropped"] for v in per_rig.values())
    no_body = sum(v["counts"]["tracker_no_body"] for v in per_rig.values())
    p99 = latency["camera_to_model"]["p99"] if "camera_to_model" in latency else math.inf
    sent = sum(r.sent for r in run.rigs.values())
    # CPU time per landmark frame: a rig's processes per frame of that rig, shared ones per frame
    per_frame = {}
    for label, percent in run.cpu_percent.items():
        rig = label.split("-", 1)[0]
        frames = run.rigs[rig].sent if rig in run.rigs else sent
        per_frame[label] = round(percent / 100.0 * run.wall_s / frames * 1e3, 2)
    return {
        "rigs": len(run.rigs), "rate": run.rate, "wall_s": round(run.wall_s, 1),
        "landmarks_sent": sent, "landmarks_per_s": round(sent / run.wall_s, 1),
        "dropped": total_dropped,
        "frames_without_body": no_body,
        "latency_ms": latency,
        "cpu_percent_of_one_core": run.cpu_percent,
        # all processes of the run together, against what the machine has (100 per core)
        "cpu_total_percent": round(sum(run.cpu_percent.values()), 1),
        "cpu_available_percent": 100 * (os.cpu_count() or 1),
        "cpu_ms_per_frame": per_frame,
        "load_avg_1_5_15": {"before": run.load_before, "after": run.load_after},
        "goal": {"no_drops": total_dropped == 0,
                 f"camera_to_model_p99_below_{GOAL_P99_MS:g}_ms": p99 < GOAL_P99_MS},
        "per_rig": per_rig,
    }


ALL_DEMOS: list[Demo] = [(o, p) for p in (1, 2, 3) for o in OBJECTS]


def scenarios() -> list[tuple[str, dict[str, list[Demo]], float, bool]]:
    """``(name, rigs, rate, state_files)``: 1 rig at 1x (ten objects, participant 3), 1 rig and
    2 rigs at 5x (thirty demonstrations per rig, the second rig in reverse order so the rigs
    run different objects at the same time), and 2 rigs at 5x without state files (where the
    time goes)."""
    one = [(o, 3) for o in OBJECTS]
    two = {"a": ALL_DEMOS, "b": ALL_DEMOS[::-1]}
    return [("1 rig at 1x", {"a": one}, 1.0, True),
            ("1 rig at 5x", {"a": ALL_DEMOS}, 5.0, True),
            ("2 rigs at 5x", two, 5.0, True),
            ("2 rigs at 5x, no state files", two, 5.0, False)]


def main(flood_only: bool = False) -> None:
    """Every scenario and the flood (``bench/flood.py``), written to ``bench/results/load.json``;
    ``flood_only`` runs the flood alone and replaces only its entry there."""
    from bench.flood import run_flood, summarise_flood

    if flood_only:
        print("-- flood", flush=True)
        update_result("load", "flood", summarise_flood(run_flood()))
        return
    results: dict[str, Any] = {
        "goal": "no drops in the filter services at 5x; camera stamp -> model published "
                f"p99 < {GOAL_P99_MS:g} ms (detector excluded)",
        "method": "router + tracker/kinematics per rig as processes on TCP loopback; one "
                  "publisher process per rig (replay, stamp = time_ns at send); the observer "
                  "measures time_ns - stamp_ns on receipt, i.e. including one extra router hop "
                  "(camera_to_landmarks_one_hop measures that hop); services reset between "
                  "demonstrations",
        "scenarios": {},
    }
    for name, rigs, rate, state_files in scenarios():
        print(f"-- {name}", flush=True)
        run = run_scenario(name, rigs, rate, state_files=state_files)
        results["scenarios"][name] = {"state_files": state_files, **summarise(run)}
    print("-- flood", flush=True)
    results["flood"] = summarise_flood(run_flood())
    write_result("load", results)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--publish", metavar="RIG", help="run as the publisher of RIG")
    parser.add_argument("--endpoint", help="router endpoint (publisher)")
    parser.add_argument("--rate", type=float, default=1.0, help="replay rate (publisher)")
    parser.add_argument("--report", type=Path, help="report file (publisher)")
    parser.add_argument("--capture-stamps", action="store_true",
                        help="keep the capture spacing of the stamps (publisher)")
    parser.add_argument("--flood-only", action="store_true",
                        help="run only the flood and replace its entry in bench/results/load.json")
    parser.add_argument("demos", nargs="*", metavar="OBJECT:PARTICIPANT")
    args = parser.parse_args()
    if args.publish:
        demos = [(d.split(":")[0], int(d.split(":")[1])) for d in args.demos]
        publish_rig(args.endpoint, args.publish, demos, args.rate, args.report,
                    restamp=not args.capture_stamps)
    else:
        main(flood_only=args.flood_only)
