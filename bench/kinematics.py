"""Kinematics benchmark: per-update latency with all four filters, memory over a 10-min stream.

Feeds the estimator a noisy revolute hand-body stream at 30 Hz for 10 simulated minutes
(18000 updates; the hand swings back and forth) on one core, timing every update and reading
the process RSS before and after. Then, segmentation on (what the kinematics service runs): the
:class:`~services.kinematics.segments.SegmentedEstimator` on whole household demonstrations
(reach, grasp, stroke, release, withdrawal; the true hand poses with pose noise and the true
landmarks), a ``reset`` between them, every update timed (onsets replay buffered frames and
releases roll back: those updates are the slow ones).
"""

from __future__ import annotations

import resource
import time

import numpy as np

from bench.common import percentiles_ms, write_result
from services.common.se3 import se3_exp, skew
from services.kinematics.config import KinematicsConfig
from services.kinematics.estimator import KinematicEstimator
from services.kinematics.segments import SegmentedEstimator

SEGMENTED_OBJECTS = ("cabinet_door", "kitchen_drawer", "faucet_lever", "sliding_door", "box_lid",
                     "round_dial")


def _rss_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def stream(minutes: float = 10.0, rate_hz: float = 30.0, seed: int = 0):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    axis = np.array([0.0, 0.6, 0.8])
    point = np.array([0.1, 0.0, 0.6])
    screw = np.concatenate([-skew(axis) @ point, axis])
    T0 = np.eye(4)
    T0[:3, 3] = point + np.array([0.08, 0.0, 0.0])
    cov = np.diag([0.003**2] * 3 + [np.radians(1.0) ** 2] * 3)
    n = int(minutes * 60 * rate_hz)
    for i in range(n):
        q = 0.8 * np.sin(2 * np.pi * i / (rate_hz * 8))
        noise = rng.normal(size=6) * np.sqrt(np.diag(cov))
        yield int(i * 1e9 / rate_hz), se3_exp(noise) @ se3_exp(q * screw) @ T0, cov


def segmented_times(rounds: int = 3) -> tuple[list[float], int]:
    """Per-update seconds of the segmented estimator over whole demonstrations, and how many
    contact phases it kept."""
    from services.synthetic.generator import generate

    rng = np.random.default_rng(1)
    cov = np.diag([0.003**2] * 3 + [np.radians(1.0) ** 2] * 3)
    est = SegmentedEstimator(KinematicsConfig())
    times: list[float] = []
    kept = 0
    for r in range(rounds):
        for name in SEGMENTED_OBJECTS:
            demo = generate(name, 4 + r % 2, r, variant="whole")
            est.reset()
            tr = demo.truth
            for i, stamp in enumerate(demo.stamps_ns):
                T = se3_exp(rng.normal(size=6) * np.sqrt(np.diag(cov))) @ tr.T_camera_hand[i]
                t0 = time.perf_counter()
                est.update(int(stamp), T, cov, tr.landmarks_true[i])
                times.append(time.perf_counter() - t0)
            kept += len(est.models)
    return times, kept


def main() -> None:
    est = KinematicEstimator(KinematicsConfig())
    rss0 = _rss_mib()
    times = []
    rss_mid = 0.0
    for i, (stamp, T, cov) in enumerate(stream()):
        t0 = time.perf_counter()
        est.update(stamp, T, cov)
        times.append(time.perf_counter() - t0)
        if i == 1800:
            rss_mid = _rss_mib()
    rss1 = _rss_mib()
    model = est.model
    segmented, kept = segmented_times()
    write_result("kinematics", {
        "update_latency_ms": percentiles_ms(times),
        "updates": len(times),
        "rss_mib": {"start": round(rss0, 1), "after_1_min": round(rss_mid, 1),
                    "after_10_min": round(rss1, 1)},
        "final_type": model.type,
        "final_probabilities": {k: round(v, 4) for k, v in model.probabilities.items()},
        "segmented_update_latency_ms": percentiles_ms(segmented),
        "segmented_demonstrations": 3 * len(SEGMENTED_OBJECTS),
        "segmented_phases_kept": kept,
        "goal": "p50 <= 0.3 ms, bounded memory; segmented p50 <= 0.5 ms",
    })


if __name__ == "__main__":
    main()
