"""``handkse demo --view``: the demo with ``handkse view`` as one more client."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.conftest import Processes
from tests.view.ports import free_ports

pytest.importorskip("rerun", reason="handkse view needs the 'view' extra (rerun-sdk)")


def test_demo_view_prints_the_url_and_the_view_sees_the_models(procs: Processes) -> None:
    web, grpc = free_ports(2)
    result = procs.run("demo", "--object", "slider", "--rate", "3", "--no-robot", "--view",
                       "--web-port", str(web), "--grpc-port", str(grpc), timeout=240)
    out = result.stdout + result.stderr
    assert result.returncode == 0, out
    assert f"web viewer at http://127.0.0.1:{web}/?url=" in out
    assert "tangent error" in out
    workdir = Path(re.search(r"logs in (\S+)", out).group(1))  # type: ignore[union-attr]
    view_log = (workdir / "view.log").read_text()
    logged = re.search(r"'kinematics/model': (\d+)", view_log)
    assert logged is not None and int(logged.group(1)) > 0, view_log
