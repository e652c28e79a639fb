"""Flood benchmark (issue 13, finding 6): 5,000 valid landmark messages/s for 5 s at one rig.

Goals: no silent loss (every message a publisher sent is, at its subscriber, handled or counted
as dropped, and every handled one has an outcome), ``stats`` answering within 100 ms throughout,
and the model of a demonstration equal to the clean run's once the flood ends.

One router, one ``handkse tracker`` and one ``handkse kinematics`` (state files, default limits,
as deployed) as child processes on TCP loopback; every publisher is a process of its own. The
demonstration is the synthetic key (participant 3, 167 frames, 5.6 s) replayed in real time with
its own stamps. Four phases, the services reset between them (counters keep counting):

1. ``clean``: the demonstration alone: the reference model.
2. ``absorbed flood``: the flood as finding 6 sent it: the demonstration's frames over and over,
   each stamped with the wall clock when it is sent, so the tracker takes every one it gets to
   as real data and the tracker -> kinematics -> tracker loop runs at capacity. The model this
   makes is meaningless and is reset afterwards; what counts is that nothing is lost silently,
   ``stats`` answers and the liveliness tokens stay.
3. ``refused flood during the demonstration``: the demonstration again, while the flood sends
   copies of its first frame (valid, but stale: a camera or a replay resending one frame). The
   tracker uses one of them or the real first frame (the same data), and refuses every other as
   ``duplicate_stamp`` or ``out_of_order_stamp``, so the flood is not absorbed: if the tracker keeps
   up (drops nothing) the model equals the clean run's. A real frame the tracker dropped is
   counted, and then the model may differ.
4. ``after``: the demonstration alone once more: the model equals the clean run's.

A watcher process polls both services' ``stats`` every 50 ms from the start of phase 1 to the end
of phase 4 (each query with a 1 s timeout) and records every appearance and disappearance of the
rig's liveliness tokens. Counts per phase are the differences of the services' ``stats``
(``received`` counts a sample once it is decoded or refused, ``dropped`` one the queue dropped;
docs/protocol.md, "Backpressure"): silent losses are ``sent - received - dropped`` on each hop
(the flood, the demonstration and kinematics' models to the tracker; the tracker's bodies to
kinematics), and handled samples without an outcome: landmarks the tracker took that became
neither a body nor a refusal nor a skip, bodies kinematics took that became neither a model nor
a refusal (nor were a not yet initialised body, which it ignores by design).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import machine, percentiles_ms
from bench.load import client_options, cpu_seconds
from services.common.bus import Bus, BusError
from services.common.keys import Keys
from services.common.processes import (
    REPO,
    ProcessGroup,
    child_env,
    client_args,
    free_tcp_endpoint,
    wait_for,
)
from services.common.protocol import HandBody, KinematicModel, ServiceStats
from services.common.recording import replay
from services.synthetic.generator import generate
from services.synthetic.replay import demonstration_recording, landmark_messages

RIG = "flood"
DEMO = ("key", 3)
FLOOD_RATE_HZ = 5000.0
FLOOD_SECONDS = 5.0
STATS_PERIOD_S = 0.05
STATS_TIMEOUT_S = 1.0
GOAL_STATS_MS = 100.0
SETTLE_TIMEOUT_S = 60.0
SERVICES = ("tracker", "kinematics")
PHASES = ("clean", "absorbed flood", "refused flood during the demonstration", "after")


def _stats(bus: Bus, keys: Keys, service: str, timeout: float = 2.0) -> ServiceStats:
    return ServiceStats.from_msgpack(bus.get(keys.stats(service), timeout=timeout)[0][1])


# --- helper processes ---


def flood(endpoint: str, rig: str, rate: float, seconds: float, mode: str, report: Path) -> None:
    """Flood process: print ``flood ready``, wait for a line on stdin, put ``rate * seconds``
    landmark messages on ``rig`` as evenly as the bus lets it, write ``report`` (JSON: ``sent``,
    ``seconds``, ``cpu_s``). ``mode`` ``fresh``: the demonstration's frames in turn, stamped at
    sending; ``first-frame``: copies of its first frame, stamp and all."""
    keys = Keys(rig)
    frames = landmark_messages(generate(*DEMO, 0))
    first = frames[0].to_msgpack()
    n = round(rate * seconds)
    with Bus(client_options(endpoint)) as bus:
        print("flood ready", flush=True)
        sys.stdin.readline()
        cpu0, t0 = time.process_time(), time.perf_counter()
        sent = 0
        while sent < n:
            due = min(n, int((time.perf_counter() - t0) * rate) + 1)
            while sent < due:
                if mode == "fresh":
                    frame = frames[sent % len(frames)]
                    payload = replace(frame, seq=sent, stamp_ns=time.time_ns()).to_msgpack()
                else:
                    payload = first
                bus.put(keys.hand_landmarks, payload)
                sent += 1
            time.sleep(0.0005)
        elapsed = time.perf_counter() - t0
        cpu = time.process_time() - cpu0
        time.sleep(0.2)  # let the last samples leave before the session closes
    report.write_text(json.dumps({"sent": sent, "seconds": elapsed, "cpu_s": cpu}))


def demonstration(endpoint: str, rig: str, report: Path) -> None:
    """Demonstration process: print ``demonstration ready``, wait for a line on stdin, replay
    :data:`DEMO` in real time with its own stamps, write ``report`` (JSON: ``stamps``)."""
    recording = demonstration_recording(generate(*DEMO, 0), rig)
    stamps: list[int] = []

    with Bus(client_options(endpoint)) as bus:
        def put(key: str, payload: bytes) -> None:
            bus.put(key, payload)

        print("demonstration ready", flush=True)
        sys.stdin.readline()
        replay(recording, put, rate=1.0)
        stamps = [m.log_time_ns for m in recording]
        time.sleep(0.2)
    report.write_text(json.dumps({"stamps": stamps}))


def watch(endpoint: str, rig: str, report: Path) -> None:
    """Watcher process: print ``watcher ready``; until a line on stdin, query each service's
    ``stats`` every :data:`STATS_PERIOD_S` (one thread per service) and record the liveliness
    tokens of ``rig``; write ``report`` (JSON: ``stats`` {service: [[wall_s, ms or null]]},
    ``tokens`` [[wall_s, key, alive]])."""
    keys = Keys(rig)
    samples: dict[str, list[tuple[float, float | None]]] = {s: [] for s in SERVICES}
    tokens: list[tuple[float, str, bool]] = []
    stop = threading.Event()

    def poll(bus: Bus, service: str) -> None:
        next_at = time.perf_counter()
        while not stop.is_set():
            sent_at, t0 = time.time(), time.perf_counter()
            try:
                bus.get(keys.stats(service), timeout=STATS_TIMEOUT_S)
                latency: float | None = (time.perf_counter() - t0) * 1e3
            except BusError:
                latency = None  # no answer within STATS_TIMEOUT_S
            samples[service].append((sent_at, latency))
            next_at = max(next_at + STATS_PERIOD_S, time.perf_counter())
            stop.wait(max(0.0, next_at - time.perf_counter()))

    with Bus(client_options(endpoint)) as bus:
        bus.watch_liveliness(keys.alive_all,
                             lambda key, alive: tokens.append((time.time(), key, alive)))
        threads = [threading.Thread(target=poll, args=(bus, s), daemon=True) for s in SERVICES]
        for t in threads:
            t.start()
        print("watcher ready", flush=True)
        sys.stdin.readline()
        stop.set()
        for t in threads:
            t.join(5.0)
    report.write_text(json.dumps({"stats": samples, "tokens": tokens}))


def _helper(group: ProcessGroup, name: str, role: str, endpoint: str,
            *extra: str) -> tuple[subprocess.Popen[bytes], Path]:
    """Start ``python -m bench.flood --role ROLE`` as ``name``; wait for its ready line."""
    report = group.workdir / f"{name}.json"
    cmd = [sys.executable, "-m", "bench.flood", "--role", role, "--endpoint", endpoint,
           "--rig", RIG, "--report", str(report), *extra]
    with open(group.log_path(name), "wb") as log:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=log,
                                stderr=subprocess.STDOUT, env=child_env(), cwd=REPO)
    group.procs[name] = proc
    group.wait_log(name, f"{role} ready", timeout=120.0)
    return proc, report


def _go(proc: subprocess.Popen[bytes]) -> None:
    assert proc.stdin is not None
    proc.stdin.write(b"go\n")
    proc.stdin.flush()


def _finish(group: ProcessGroup, name: str, proc: subprocess.Popen[bytes], report: Path,
            timeout: float) -> dict[str, Any]:
    wait_for(lambda: proc.poll() is not None, timeout, f"{name} to finish", period=0.05)
    if proc.returncode != 0 or not report.exists():
        raise RuntimeError(f"{name} failed ({proc.returncode}):\n{group.log(name)}")
    result: dict[str, Any] = json.loads(report.read_text())
    return result


# --- the run ---


@dataclass
class Phase:
    """One phase: what its publishers sent and what the services counted meanwhile."""

    name: str
    started: float                       # wall clock [s]
    ended: float = 0.0                   # wall clock [s], once the services settled
    landmarks_sent: int = 0
    flood_sent: int = 0
    flood_seconds: float = 0.0
    flood_cpu_s: float = 0.0
    demonstration_stamps: list[int] = field(default_factory=list)
    before: dict[str, ServiceStats] = field(default_factory=dict)
    after: dict[str, ServiceStats] = field(default_factory=dict)
    bodies: list[HandBody] = field(default_factory=list)
    model: KinematicModel | None = None
    settled: bool = True
    settle_s: float = 0.0
    cpu_s: dict[str, float] = field(default_factory=dict)


@dataclass
class FloodRun:
    rate: float
    seconds: float
    phases: list[Phase]
    stats_samples: dict[str, list[tuple[float, float | None]]]
    tokens: list[tuple[float, str, bool]]
    load_before: list[float]
    load_after: list[float]


def run_flood(workdir: Path | None = None, rate: float = FLOOD_RATE_HZ,
              seconds: float = FLOOD_SECONDS) -> FloodRun:
    """The four phases of the module docstring; the services' and helpers' logs in
    ``workdir``."""
    keys = Keys(RIG)
    endpoint = free_tcp_endpoint()
    group = ProcessGroup(Path(workdir or tempfile.mkdtemp(prefix="handkse-flood-")))
    bodies: list[bytes] = []
    phases: list[Phase] = []
    with group:
        group.start_router(endpoint)
        with Bus(client_options(endpoint)) as bus:
            bus.subscribe(keys.hand_body, lambda _k, payload: bodies.append(payload))
            for service in SERVICES:
                group.start(service, service, *client_args(endpoint, RIG), "--state-file",
                            str(group.workdir / f"{service}.state"))
            wanted = {keys.alive(s) for s in SERVICES}
            wait_for(lambda: wanted <= set(bus.alive(keys.alive_all)), 60.0,
                     f"services alive: {sorted(wanted)}", period=0.2)
            pids = {label: p.pid for label, p in group.procs.items()}
            watcher, watcher_report = _helper(group, "watcher", "watcher", endpoint)
            load_before = [round(x, 2) for x in os.getloadavg()]
            sent_total = 0

            def settled() -> bool:
                try:
                    t, k = (_stats(bus, keys, s) for s in SERVICES)
                except BusError:
                    return False
                return (t.received + t.dropped == sent_total + k.published
                        and k.received + k.dropped == t.published)

            for i, name in enumerate(PHASES, 1):
                demo = flooder = None
                if name != "absorbed flood":
                    demo = _helper(group, f"phase{i}-demonstration", "demonstration", endpoint)
                if "flood" in name:
                    mode = "fresh" if name == "absorbed flood" else "first-frame"
                    flooder = _helper(group, f"phase{i}-flood", "flood", endpoint, "--rate",
                                      str(rate), "--seconds", str(seconds), "--mode", mode)
                phase = Phase(name, started=time.time(),
                              before={s: _stats(bus, keys, s) for s in SERVICES})
                cpu0 = {label: cpu_seconds(pid) for label, pid in pids.items()}
                first_body = len(bodies)
                for helper in (flooder, demo):
                    if helper is not None:
                        _go(helper[0])
                if flooder is not None:
                    got = _finish(group, f"phase{i}-flood", *flooder,
                                  timeout=60.0 + 10 * seconds)
                    phase.flood_sent, phase.flood_seconds = got["sent"], got["seconds"]
                    phase.flood_cpu_s = got["cpu_s"]
                if demo is not None:
                    got = _finish(group, f"phase{i}-demonstration", *demo, timeout=120.0)
                    phase.demonstration_stamps = got["stamps"]
                phase.landmarks_sent = phase.flood_sent + len(phase.demonstration_stamps)
                sent_total += phase.landmarks_sent
                t_sent = time.perf_counter()
                try:
                    wait_for(settled, SETTLE_TIMEOUT_S, "the services to settle", period=0.05)
                except TimeoutError:
                    phase.settled = False
                phase.settle_s = time.perf_counter() - t_sent
                phase.ended = time.time()
                phase.cpu_s = {label: cpu_seconds(pid) - cpu0[label]
                               for label, pid in pids.items()}
                phase.after = {s: _stats(bus, keys, s) for s in SERVICES}
                phase.bodies = [HandBody.from_msgpack(p) for p in bodies[first_body:]]
                phase.model = KinematicModel.from_msgpack(bus.get(keys.kinematics_model)[0][1])
                phases.append(phase)
                for service in ("kinematics", "tracker"):
                    bus.get(keys.reset(service), timeout=10.0)
            for label in SERVICES:
                if not group.running(label):
                    raise RuntimeError(f"{label} died during the run:\n{group.log(label)}")
            _go(watcher)
            watched = _finish(group, "watcher", watcher, watcher_report, timeout=30.0)
            load_after = [round(x, 2) for x in os.getloadavg()]
    samples = {s: [(float(t), None if v is None else float(v)) for t, v in rows]
               for s, rows in watched["stats"].items()}
    tokens = [(float(t), str(k), bool(a)) for t, k, a in watched["tokens"]]
    return FloodRun(rate, seconds, phases, samples, tokens, load_before, load_after)


# --- report ---


def _superseded(stats: ServiceStats) -> int:
    """Priors replaced unread by a newer one (not lost: the newer one is used)."""
    return int(stats.skipped.get("superseded", 0))


def phase_counts(phase: Phase) -> dict[str, int]:
    """What each hop of the phase carried and what went missing where (module docstring)."""
    t0, t1 = phase.before["tracker"], phase.after["tracker"]
    k0, k1 = phase.before["kinematics"], phase.after["kinematics"]

    def delta(a: ServiceStats, b: ServiceStats, name: str) -> int:
        return int(getattr(b, name) - getattr(a, name))

    t = {n: delta(t0, t1, n) for n in ("received", "dropped", "published")}
    k = {n: delta(k0, k1, n) for n in ("received", "dropped", "published")}
    superseded_t = _superseded(t1) - _superseded(t0)
    return {
        "landmarks_sent": phase.landmarks_sent, "flood_sent": phase.flood_sent,
        "tracker_received": t["received"], "tracker_dropped": t["dropped"],
        "tracker_published": t["published"],
        "tracker_rejected": sum(t1.rejected.values()) - sum(t0.rejected.values()),
        "tracker_skipped": sum(t1.skipped.values()) - sum(t0.skipped.values()) - superseded_t,
        "tracker_models_superseded": superseded_t,
        "kinematics_received": k["received"], "kinematics_dropped": k["dropped"],
        "kinematics_published": k["published"],
        "kinematics_rejected": sum(k1.rejected.values()) - sum(k0.rejected.values()),
        "bodies_observed": len(phase.bodies),
        "bodies_not_initialised": sum(not b.initialized for b in phase.bodies),
    }


def silent_losses(counts: dict[str, int]) -> dict[str, int]:
    """Messages that vanished without a count, per hop and per service (all 0 is the goal)."""
    return {
        "to_tracker": (counts["landmarks_sent"] + counts["kinematics_published"]
                       - counts["tracker_received"] - counts["tracker_dropped"]),
        # the tracker received every model (to_tracker 0): the rest of received is landmarks
        "in_tracker": (counts["tracker_received"] - counts["kinematics_published"]
                       - counts["tracker_published"] - counts["tracker_rejected"]
                       - counts["tracker_skipped"]),
        "tracker_to_kinematics": (counts["tracker_published"] - counts["kinematics_received"]
                                  - counts["kinematics_dropped"]),
        "in_kinematics": (counts["kinematics_received"] - counts["kinematics_published"]
                          - counts["kinematics_rejected"] - counts["bodies_not_initialised"]),
    }


def comparable(model: KinematicModel) -> KinematicModel:
    """``model`` without what differs between runs of the same data: its sequence number."""
    return replace(model, seq=0)


def model_difference(model: KinematicModel, reference: KinematicModel) -> dict[str, Any]:
    """Whether ``model`` equals ``reference`` (bit for bit but ``seq``), and by how much not."""
    out: dict[str, Any] = {"equal": comparable(model) == comparable(reference),
                           "type": model.type, "reference_type": reference.type,
                           "updates": model.updates, "reference_updates": reference.updates}
    a, b = model.revolute, reference.revolute
    if a is not None and b is not None:
        out["axis_angle_deg"] = float(np.degrees(np.arccos(min(1.0, abs(float(a.axis @ b.axis))))))
        out["point_distance_mm"] = float(np.linalg.norm(a.point - b.point) * 1e3)
    out["probability_difference"] = max(abs(model.probabilities[k] - reference.probabilities[k])
                                        for k in reference.probabilities)
    return out


def _window(samples: list[tuple[float, float | None]], phase: Phase) -> list[float | None]:
    return [v for t, v in samples if phase.started <= t <= phase.ended]


def stats_latency(values: list[float | None]) -> dict[str, Any]:
    answered = [v for v in values if v is not None]
    out: dict[str, Any] = {"queries": len(values), "unanswered_within_1_s": len(values)
                           - len(answered),
                           "over_100_ms": sum(v > GOAL_STATS_MS for v in answered)}
    if answered:
        out["ms"] = percentiles_ms(np.asarray(answered) * 1e-3)
    return out


def token_losses(run: FloodRun, phase: Phase) -> dict[str, int]:
    """How often each service's tokens vanished during ``phase``."""
    lost: dict[str, int] = {}
    for t, key, alive in run.tokens:
        if not alive and phase.started <= t <= phase.ended:
            lost[key] = lost.get(key, 0) + 1
    return lost


def summarise_flood(run: FloodRun) -> dict[str, Any]:
    reference = run.phases[0].model
    assert reference is not None
    phases: dict[str, Any] = {}
    all_latencies: list[float | None] = []
    for phase in run.phases:
        counts = phase_counts(phase)
        assert phase.model is not None
        entry: dict[str, Any] = {
            "seconds": round(phase.ended - phase.started, 2),
            "settled": phase.settled, "settle_s": round(phase.settle_s, 2),
            "counts": counts, "silent_losses": silent_losses(counts),
            "rejected": {s: {k: v - phase.before[s].rejected.get(k, 0)
                             for k, v in phase.after[s].rejected.items()
                             if v != phase.before[s].rejected.get(k, 0)} for s in SERVICES},
            "stats": {s: stats_latency(_window(run.stats_samples[s], phase)) for s in SERVICES},
            "tokens_lost": token_losses(run, phase),
            "cpu_percent_of_one_core": {
                label: round(100.0 * cpu / max(phase.ended - phase.started, 1e-9), 1)
                for label, cpu in phase.cpu_s.items()},
        }
        if phase.flood_sent:
            entry["flood"] = {"sent": phase.flood_sent, "seconds": round(phase.flood_seconds, 2),
                              "rate_per_s": round(phase.flood_sent / phase.flood_seconds, 1),
                              "publisher_cpu_percent": round(
                                  100.0 * phase.flood_cpu_s / phase.flood_seconds, 1)}
        if phase.demonstration_stamps:
            seen = {b.stamp_ns for b in phase.bodies}
            entry["real_frames_without_a_body"] = len(set(phase.demonstration_stamps) - seen)
            entry["model"] = model_difference(phase.model, reference)
        phases[phase.name] = entry
        for s in SERVICES:
            all_latencies += _window(run.stats_samples[s], phase)
    overall = stats_latency(all_latencies)
    losses = sum(v for p in phases.values() for v in p["silent_losses"].values())
    worst = overall.get("ms", {}).get("max", math.inf)
    return {
        "method": __doc__.split("\n\n", 1)[1].strip().replace("\n", " "),
        "flood": {"rate_per_s": run.rate, "seconds": run.seconds},
        "machine": machine(),
        "load_avg_1_5_15": {"before": run.load_before, "after": run.load_after},
        "phases": phases,
        "stats_throughout": overall,
        "goal": {
            "no_silent_losses": losses == 0 and all(p["settled"] for p in phases.values()),
            f"stats_answered_within_{GOAL_STATS_MS:g}_ms_throughout":
                overall["unanswered_within_1_s"] == 0 and worst < GOAL_STATS_MS,
            "model_equal_to_the_clean_run_once_the_flood_ended":
                bool(phases["after"]["model"]["equal"]),
            "model_equal_to_the_clean_run_during_the_refused_flood":
                bool(phases["refused flood during the demonstration"]["model"]["equal"]),
            "no_liveliness_token_lost": not any(p["tokens_lost"] for p in phases.values()),
        },
    }


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--role", choices=("flood", "demonstration", "watcher"), required=True)
    parser.add_argument("--endpoint", required=True)
    parser.add_argument("--rig", required=True)
    parser.add_argument("--report", type=Path, required=True)
    parser.add_argument("--rate", type=float, default=FLOOD_RATE_HZ)
    parser.add_argument("--seconds", type=float, default=FLOOD_SECONDS)
    parser.add_argument("--mode", choices=("fresh", "first-frame"), default="fresh")
    args = parser.parse_args()
    if args.role == "flood":
        flood(args.endpoint, args.rig, args.rate, args.seconds, args.mode, args.report)
    elif args.role == "demonstration":
        demonstration(args.endpoint, args.rig, args.report)
    else:
        watch(args.endpoint, args.rig, args.report)
