"""``handkse demo`` end to end: router, tracker and kinematics as real processes on loopback."""

from __future__ import annotations

import re

from tests.conftest import Processes


def test_demo_runs_end_to_end_and_prints_a_tangent_error(procs: Processes) -> None:
    result = procs.run("demo", "--object", "slider", "--rate", "3", timeout=240)
    out = result.stdout + result.stderr
    assert result.returncode == 0, out
    assert "ground truth" in out and "estimate" in out
    match = re.search(r"tangent error ([0-9.]+) deg", out)
    assert match is not None, out
    assert 0.0 <= float(match.group(1)) <= 180.0
    assert re.search(r"updates\s+[1-9]\d*", out), out  # the model absorbed hand-body updates
    # then the simulated Panda acts on the estimate (or refuses it with a reason)
    assert re.search(r"simulated articulation: (SUCCESS|FAILED) \(\w+\)", out), out
