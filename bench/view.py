"""``handkse bench view``: does the view keep up, and how big is an ``.rrd``?

1. Live: router, tracker and kinematics as processes, ``handkse view --save --no-images`` and
   ``handkse record`` as two more clients; the key demonstration (participant 3, 30 Hz) replayed
   in real time. Measured: the view process's CPU share while the demonstration plays (CPU time
   from /proc over the wall time from the replay's start, and over the demonstration's duration
   alone; the goal is to keep up with 30 Hz on one core, i.e. a share well below 1), whether it
   logged every message, and the ``.rrd`` size per second of
   demonstration, with the 10 s figure (goal: < 20 MB without images) extrapolated linearly.
2. Capacity: the recorded messages logged again in this process, as fast as possible, into an
   ``.rrd`` (one thread): messages and camera-frame equivalents (landmarks + body + model) per
   second.
"""

from __future__ import annotations

import os
import re
import tempfile
import time
from pathlib import Path

from bench.common import write_result
from services.common.processes import ProcessGroup, client_args, free_tcp_endpoint, wait_for
from services.common.recording import read_recording

OBJECT = "key"
RIG = "bench"


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def _logged(text: str) -> int:
    counts = re.findall(r"view: logged (\d+) messages", text)
    return int(counts[-1]) if counts else 0


def live(workdir: Path) -> dict[str, object]:
    endpoint = free_tcp_endpoint()
    z = client_args(endpoint, RIG)
    rrd, recording = workdir / "view.rrd", workdir / "bus.mcap"
    with ProcessGroup(workdir) as group:
        group.start_pipeline(endpoint, RIG)
        view = group.start("view", "view", *z, "--save", str(rrd), "--no-images")
        group.start("record", "record", str(recording), *z)
        group.wait_log("view", "view: subscribed", 60)
        group.wait_log("record", "recording", 60)
        cpu0, t0 = _cpu_seconds(view.pid), time.monotonic()
        replay = group.start("replay", "replay", "--synthetic", OBJECT, *z, "--wait-for", "tracker",
                             "--wait-for", "kinematics", "--wait-for", "view")
        replay.wait(120)
        wall, cpu = time.monotonic() - t0, _cpu_seconds(view.pid) - cpu0
        published = int(re.search(r"replayed (\d+)", group.log("replay")).group(1))  # type: ignore[union-attr]
        time.sleep(3.0)  # let the pipeline drain
        group.kill("record", 15)
        expected = sum(1 for _ in read_recording(recording))
        wait_for(lambda: _logged(group.log("view")) >= expected, 30, "the view to log all")
        group.kill("view", 15)
    messages = list(read_recording(recording))
    stamps = [m.publish_time_ns for m in messages if m.key.endswith("/hand/landmarks")]
    duration_s = (max(stamps) - min(stamps)) * 1e-9
    size = rrd.stat().st_size
    return {"object": OBJECT, "landmark_frames": published, "demonstration_s": round(duration_s, 2),
            "wall_s": round(wall, 2), "view_cpu_s": round(cpu, 3),
            "view_cpu_share_of_one_core": round(cpu / wall, 3),
            # the replay waits for the services first: over the demonstration alone, an upper bound
            "view_cpu_share_over_demonstration": round(cpu / duration_s, 3),
            "messages_on_bus": expected, "messages_logged": _logged(group.log("view")),
            "rrd_bytes": size, "rrd_mb_per_s": round(size / duration_s / 1e6, 3),
            "rrd_mb_per_10_s_extrapolated": round(10.0 * size / duration_s / 1e6, 2),
            "recording": str(recording)}


def capacity(recording: Path, workdir: Path, repeats: int = 3) -> dict[str, float]:
    import rerun as rr

    from services.view.rerun_scene import RerunScene, SceneOptions

    messages = [(m.key, m.payload) for m in read_recording(recording)]
    frames = sum(1 for k, _ in messages if k.endswith("/hand/landmarks"))
    best = float("inf")
    for i in range(repeats):
        rec = rr.RecordingStream("handkse-bench")
        rec.set_sinks(rr.FileSink(str(workdir / f"capacity-{i}.rrd")))
        scene = RerunScene(rec, SceneOptions(images=False))
        t0 = time.perf_counter()
        for key, payload in messages:
            scene.handle(key, payload)
        rec.flush(timeout_sec=30.0)
        best = min(best, time.perf_counter() - t0)
        rec.disconnect()
    return {"messages": len(messages), "seconds": round(best, 3),
            "messages_per_s": round(len(messages) / best, 1),
            "frames_per_s": round(frames / best, 1)}


def main() -> None:
    workdir = Path(tempfile.mkdtemp(prefix="handkse-bench-view-"))
    result = live(workdir)
    result["capacity"] = capacity(Path(str(result.pop("recording"))), workdir)
    write_result("view", result)


if __name__ == "__main__":
    main()
