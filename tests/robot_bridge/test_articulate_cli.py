"""``handkse articulate`` as a user runs it, after ``handkse replay --synthetic key``.

Every piece is a real process on one router: the tracker, the kinematics service, the robot
bridge on the simulated Panda holding the demonstration's true key (``--sim-object
synthetic:key``), the replay (re-stamped to the wall clock, the default) and each
``handkse articulate``.
"""

from __future__ import annotations

import json
import math
import re
import time
from pathlib import Path

import pytest

pytest.importorskip("mujoco")

from services.common.bus import Bus
from services.common.keys import Keys
from services.common.protocol import KinematicModel
from tests.conftest import Processes, output_of, wait_until, zenoh_args

KEYS = Keys("operator")


def _model(bus: Bus) -> KinematicModel | None:
    replies = bus.get(KEYS.kinematics_model, timeout=5.0)
    return KinematicModel.from_msgpack(replies[0][1]) if replies else None


def _settled(bus: Bus, quiet_s: float = 1.5, timeout: float = 60.0) -> KinematicModel:
    """The kinematics service's model once it has stopped changing."""
    deadline = time.monotonic() + timeout
    last, since = -1, time.monotonic()
    while time.monotonic() < deadline:
        model = _model(bus)
        updates = -1 if model is None else model.updates
        if updates != last:
            last, since = updates, time.monotonic()
        elif updates > 0 and time.monotonic() - since >= quiet_s:
            assert model is not None
            return model
        time.sleep(0.2)
    pytest.fail(f"the model did not settle within {timeout} s (updates {last})")


def test_dry_run_then_articulate_the_demonstrated_key(procs: Processes, router: str,
                                                      client_bus: Bus, tmp_path: Path) -> None:
    z = [*zenoh_args(router), "--rig", KEYS.rig]
    services = {
        "tracker": procs.start("tracker", *z, name="tracker"),
        "kinematics": procs.start("kinematics", *z, "--state-file", str(tmp_path / "k.state"),
                                  name="kinematics"),
        "robot_bridge": procs.start("robot-bridge", *z, "--sim-object", "synthetic:key",
                                    name="robot_bridge"),
    }
    for name, p in services.items():
        wait_until(lambda n=name, p=p: KEYS.alive(n) in client_bus.alive(KEYS.alive_all)
                   or p.poll() is not None, 90, what=f"{name} liveliness")
        assert p.poll() is None, output_of(p)
    assert "from synthetic:key:3:0" in output_of(services["robot_bridge"])

    replay = procs.run("replay", "--synthetic", "key", *z, "--rate", "3", timeout=120)
    assert replay.returncode == 0, replay.stdout + replay.stderr
    model = _settled(client_bus)
    assert model.type == "revolute" and model.revolute is not None
    assert time.time_ns() - model.stamp_ns < 60 * 10**9  # re-stamped: minutes old at most

    dry = procs.run("articulate", *z, "--dry-run", timeout=120)
    out = dry.stdout + dry.stderr
    assert dry.returncode == 0, out
    assert out.startswith("articulate (dry run): OK (dry_run)\n"), out
    # the default task: half a turn the way the demonstration turned (the model's q)
    sign = "+" if model.revolute.q > 0 else "-"
    assert re.search(rf"^  motion     \{sign}180\.0 deg in 6\.0 s, then 0\.5 s hold; peak speed "
                     r"[0-9.]+ m/s, 0\.98 rad/s$", out, re.MULTILINE), out
    assert re.search(r"^  joint      revolute, axis \[.*\] through \[.*\] m \(robot base frame\)$",
                     out, re.MULTILINE), out
    assert re.search(r"^  limits     force 70\.0 N, wrist torque 12\.0 N m, speed 0\.25 m/s "
                     r"and 2\.00 rad/s$", out, re.MULTILINE), out

    run = procs.run("articulate", *z, "--json", timeout=180)
    assert run.returncode == 0, run.stdout + run.stderr
    answer = json.loads(run.stdout)
    result = answer["result"]
    assert result["success"] and result["reason"] == "ok", result
    assert answer["request"]["amount"] == pytest.approx(math.copysign(math.pi, model.revolute.q))
    assert abs(result["articulated"]) == pytest.approx(math.pi, rel=0.03)
    assert 0.0 < result["mean_force_n"] <= result["peak_force_n"] < 30.0
    assert result["detail"].startswith(f"articulated {sign}1"), result["detail"]
    assert result["plan"]["joint_type"] == "revolute"

    # the same model sent from a file, stamped long ago, is refused with what to do about it
    old = KinematicModel.from_json_obj({**model.to_json_obj(), "stamp_ns": 1})
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old.to_json_obj()))
    stale = procs.run("articulate", *z, "--model-file", str(path), "--dry-run", timeout=120)
    out = stale.stdout + stale.stderr
    assert stale.returncode == 1, out
    assert out.startswith("articulate (dry run): REFUSED (stale_model)\n"), out
    assert re.search(r"^  detail     model is \d+ s old \(limit 120 s, "
                     r"robot_bridge\.max_model_age_s\): replay with wall-clock stamps", out,
                     re.MULTILINE), out
    for p in services.values():
        assert p.poll() is None, output_of(p)
