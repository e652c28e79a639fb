"""Per-frame latency of ``HandTracker.step`` (not a test): one hand, 30 Hz, 3 mm noise.

Run: ``python -m tests.tracker.latency [repeats]`` (pin to one core with ``taskset -c 1``).
Prints p50/p99 per repeat of a 40 s smooth 6-DOF motion (1200 frames, default config), and the
cost of a 6x6 numpy addition as a yardstick of the machine's per-call overhead.
"""

from __future__ import annotations

import sys
import time
import timeit

import numpy as np

from services.tracker.config import TrackerConfig
from services.tracker.tracker import HandTracker
from tests.tracker import handgen as hg
from tests.tracker.test_tracker import wobble


def main(repeats: int = 5) -> None:
    rng = np.random.default_rng(0)
    scenario = hg.Scenario(wobble, 40.0)
    frames = [(s, [hg.observe(scenario.T_frame_hand(hg.Scenario.time_of(s)), rng, 0.003)])
              for s in scenario.stamps()]
    a, b = np.ones((6, 6)), np.ones((6, 6))
    add_ns = min(timeit.repeat(lambda: a + b, number=20000, repeat=5)) / 20000 * 1e9
    print(f"yardstick: a 6x6 numpy add takes {add_ns:.0f} ns")
    for _ in range(repeats):
        tracker = HandTracker(TrackerConfig())
        times = []
        for stamp, hands in frames:
            t0 = time.perf_counter()
            tracker.step(stamp, hands)
            times.append(time.perf_counter() - t0)
        ms = np.array(times[10:]) * 1e3
        p50, p99 = np.percentile(ms, [50, 99])
        print(f"p50 {p50:.3f} ms  p99 {p99:.3f} ms  max {ms.max():.3f} ms  ({ms.size} frames)")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
