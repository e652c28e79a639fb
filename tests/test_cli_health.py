"""``handkse health``: the container health check, against a real router and real services."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import Processes, zenoh_args


def _lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


def test_health_answers_from_the_liveliness_tokens(procs: Processes, router: str) -> None:
    z = zenoh_args(router)
    procs.start("tracker", *z, name="tracker")
    procs.start("replay", "--synthetic", "bolt", "--loop", *z, name="replay")
    up = procs.run("health", "tracker", "replay", "router", "--timeout", "30", *z)
    assert up.returncode == 0, up.stdout + up.stderr
    assert "alive: tracker, replay, router" in up.stdout
    down = procs.run("health", "tracker", "robot-bridge", "--timeout", "1", *z)
    assert down.returncode == 1, down.stdout + down.stderr
    assert _lines(down.stderr) == [
        "handkse health: robot_bridge not alive on rig default after 1 s (is it running and "
        "connected to the same router?)"]
    other_rig = procs.run("health", "tracker", "--rig", "lab", "--timeout", "1", *z)
    assert other_rig.returncode == 1


def test_health_fails_without_a_router(procs: Processes, tmp_path: Path) -> None:
    result = procs.run("health", "tracker", "--timeout", "1",
                       *zenoh_args(f"unixsock-stream/{tmp_path}/no-router.sock"))
    assert result.returncode != 0
    assert len(_lines(result.stderr)) == 1 and "Traceback" not in result.stderr
    assert "tracker" in result.stderr or "zenoh" in result.stderr
