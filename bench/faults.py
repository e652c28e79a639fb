"""Fault benchmark (issue 8): recovery times of the pipeline on one host.

Runs the drills of :mod:`services.evaluation.drills.faults` (the ones
``tests/deploy/test_faults.py`` asserts): kill -9 and restart the kinematics service and the
tracker, kill -9 and restart the router, cut the link to the tracker and kinematics for 3 s and
15 s, each in the middle of the flap latch demonstration (participant 3) replayed at 2.5 x real
time, every session with a 2 s lease, ``repeats`` times in one rig, each pass starting with an
uninterrupted run.

Per fault, one value per run (seconds; monotonic clock of the observer):

- ``outage_detected_s``: fault -> the service's liveliness token vanishes at the observer;
- ``token_back_s``: restore (restart spawned, link up, router spawned) -> token back;
- ``first_model_s``: restore -> first new kinematic model at the observer (the demonstrator
  holds still until the tokens are back, then the replay goes on);
- ``updates_lost`` / ``bodies_lost``: model updates and HandBody messages fewer than in the
  uninterrupted run of the same pass (the frames replayed into the outage, plus whatever was
  queued in a killed process or on a cut link);
- ``tangent_error_deg`` with the fault, ``baseline.tangent_error_deg`` without;
- the robot bridge's dry-run answer during the outage and after recovery.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.common import write_result
from services.evaluation.drills.faults import LEASE_MS, Fault, FaultReport, FaultRig, run_scenario
from services.synthetic.generator import generate

OBJECT, PARTICIPANT, SEED = "flap_latch", 3, 0
RATE = 2.5
FAULTS = (Fault("kill_kinematics"), Fault("kill_tracker"), Fault("restart_router"),
          Fault("cut_link", 3.0), Fault("cut_link", 15.0))


def _r(x: float | None) -> float | None:
    return None if x is None else round(x, 3)


def _summary(runs: list[FaultReport], baselines: list[FaultReport]) -> dict[str, Any]:
    first = runs[0]
    out: dict[str, Any] = {
        "outage_detected_s": {v: [_r(r.detection_s.get(v)) for r in runs]
                              for v in first.detection_s},
        "token_back_s": {v: [_r(r.back_s.get(v)) for r in runs] for v in first.back_s},
        "first_model_s": [_r(r.first_model_s) for r in runs],
        "outage_s": [_r(r.outage_s) for r in runs],
        "frames_into_outage": first.frames_into_outage,
        "updates_before_fault": [r.updates_before for r in runs],
        "updates_lost": [b.final_updates - r.final_updates for r, b in zip(runs, baselines, strict=True)],
        "bodies_lost": [b.bodies - r.bodies for r, b in zip(runs, baselines, strict=True)],
        "tangent_error_deg": [_r(r.tangent_error_deg) for r in runs],
        "final_type": sorted({r.final_type for r in runs}),
        "bridge_during": [r.bridge_during for r in runs],
        "bridge_after": [r.bridge_after for r in runs],
        "not_running_or_traceback": sorted({*(n for r in runs for n in r.not_running),
                                            *(n for r in runs for n in r.tracebacks)}),
    }
    if first.restored_updates is not None:
        out["restored_updates"] = [r.restored_updates for r in runs]
    firsts = [r.first_model_s for r in runs if r.first_model_s is not None]
    if firsts:
        out["first_model_s_median"] = _r(statistics.median(firsts))
    return out


def main(repeats: int = 3) -> None:
    demo = generate(OBJECT, PARTICIPANT, SEED)
    baselines: list[FaultReport] = []
    runs: dict[str, list[FaultReport]] = {f.name: [] for f in FAULTS}
    t0 = time.monotonic()
    with FaultRig(Path(tempfile.mkdtemp(prefix="handkse-faults-"))) as rig:
        for i in range(repeats):
            baselines.append(run_scenario(rig, demo, Fault("none"), rate=RATE))
            for fault in FAULTS:
                rig.heal()
                report = run_scenario(rig, demo, fault, rate=RATE)
                runs[fault.name].append(report)
                print(f"pass {i + 1}/{repeats} {fault.name}: first model after "
                      f"{report.first_model_s} s, tangent error "
                      f"{report.tangent_error_deg:.1f} deg", flush=True)
    result = {
        "setup": {"object": OBJECT, "participant": PARTICIPANT, "seed": SEED, "rate": RATE,
                  "frames": baselines[0].frames, "lease_ms": LEASE_MS, "fault_at": 0.4,
                  "lost_fraction": 0.08, "repeats": repeats, "endpoints": "tcp loopback",
                  "link": "LinkProxy blackhole (silent link, new connections refused)",
                  "wall_s": round(time.monotonic() - t0, 1)},
        "baseline": {"tangent_error_deg": [_r(b.tangent_error_deg) for b in baselines],
                     "final_updates": [b.final_updates for b in baselines],
                     "bodies": [b.bodies for b in baselines],
                     "bridge_after": [b.bridge_after for b in baselines]},
        "faults": {name: _summary(reports, baselines) for name, reports in runs.items()},
    }
    write_result("faults", result)


if __name__ == "__main__":
    main()
