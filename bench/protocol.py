"""Protocol + bus benchmark: HandLandmarks codec time and publish->receive latency.

Latency: a publisher subprocess puts HandLandmarks at 1 kHz with ``stamp_ns`` = its
CLOCK_MONOTONIC send time; this process (a Zenoh peer connected over TCP loopback) subscribes and
subtracts. Both processes read the same system-wide monotonic clock, so this is one-way latency.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
import timeit

import numpy as np

from bench.common import percentiles_ms, write_result
from services.common.bus import Bus, ZenohOptions
from services.common.protocol import Hand, HandLandmarks


def _landmarks(stamp_ns: int = 0, seq: int = 0) -> HandLandmarks:
    rng = np.random.default_rng(0)
    hand = Hand(handedness="right", score=0.97,
                points=rng.normal(0.6, 0.05, (21, 3)).astype("<f4"),
                visibility=rng.uniform(0, 1, 21).astype("<f4"),
                pixels=rng.uniform(0, 720, (21, 2)).astype("<f4"))
    return HandLandmarks(seq=seq, stamp_ns=stamp_ns, hands=(hand,))


def codec(n: int = 20000) -> dict[str, float]:
    msg = _landmarks()
    wire = msg.to_msgpack()
    enc = min(timeit.repeat(msg.to_msgpack, number=n, repeat=5)) / n
    dec = min(timeit.repeat(lambda: HandLandmarks.from_msgpack(wire), number=n, repeat=5)) / n
    return {"bytes": len(wire), "encode_us": enc * 1e6, "decode_us": dec * 1e6,
            "encode_decode_us": (enc + dec) * 1e6}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def publisher(endpoint: str, count: int, rate_hz: float) -> None:
    """Subprocess body: publish ``count`` stamped messages at ``rate_hz``."""
    base = _landmarks()
    with Bus(ZenohOptions(mode="peer", connect=(endpoint,), multicast_scouting=False)) as bus:
        time.sleep(1.0)  # let the peer link settle before timing
        period = 1.0 / rate_hz
        t_next = time.perf_counter()
        for i in range(count):
            msg = HandLandmarks(seq=i, stamp_ns=time.monotonic_ns(), hands=base.hands)
            bus.put("bench/landmarks", msg.to_msgpack())
            t_next += period
            while time.perf_counter() < t_next:
                pass
        time.sleep(0.5)


def latency(count: int = 3000, rate_hz: float = 1000.0) -> dict[str, float]:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    received: list[float] = []
    done = threading.Event()

    def on_sample(_key: str, payload: bytes) -> None:
        now = time.monotonic_ns()
        msg = HandLandmarks.from_msgpack(payload)
        received.append((now - msg.stamp_ns) * 1e-9)
        if len(received) >= count:
            done.set()

    with Bus(ZenohOptions(mode="peer", listen=(endpoint,), multicast_scouting=False)) as bus:
        bus.subscribe("bench/landmarks", on_sample)
        proc = subprocess.Popen([sys.executable, "-c",
                                 "import bench.protocol as b; "
                                 f"b.publisher({endpoint!r}, {count}, {rate_hz})"])
        done.wait(count / rate_hz + 30)
        proc.wait(30)
    stats = percentiles_ms(received[100:])  # skip the connection warm-up
    stats["received"] = len(received)
    stats["sent"] = count
    return stats


def record_replay_timing(runs: int = 5) -> dict[str, float]:
    """``handkse record`` + ``handkse replay`` through a router (three processes): the worst
    inter-message timing error per run, ms (goal: within 5 ms)."""
    import tempfile
    from pathlib import Path

    from tests.common.test_recording import _messages, record_replay
    from tests.conftest import Processes, output_of, wait_until

    worst = []
    for run in range(runs):
        tmp = Path(tempfile.mkdtemp(prefix="handkse-bench-rec-"))
        procs = Processes(tmp)
        try:
            ep = f"unixsock-stream/{tmp}/router.sock"
            router = procs.start("router", "-l", ep, "--no-multicast-scouting", name="router")
            wait_until(lambda r=router: "router ready" in output_of(r), 20)
            msgs = _messages(40, seed=run)
            back = record_replay(procs, ep, tmp, msgs)
            want = np.diff([t for _, _, t in msgs])
            have = np.diff([m.log_time_ns for m in back])
            worst.append(float(np.abs(have - want).max() * 1e-6))
        finally:
            procs.stop_all()
    return {"worst_interval_error_ms_per_run": worst, "median_of_runs_ms": float(np.median(worst)),
            "goal_ms": 5.0}


def main() -> None:
    result = {"handlandmarks_codec": codec(), "publish_receive_latency_ms_1khz": latency(),
              "record_replay_timing": record_replay_timing()}
    write_result("protocol", result)


if __name__ == "__main__":
    main()
