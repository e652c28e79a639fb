"""``handkse eval`` and ``handkse tune`` through the real CLI, on small runs."""

from __future__ import annotations

import csv
from pathlib import Path

from services.common.config import load_section
from tests.conftest import Processes


def test_eval_writes_table_csv_and_plot(procs: Processes, tmp_path: Path) -> None:
    out = tmp_path / "eval"
    result = procs.run("eval", "--split", "tuning", "--methods", "regal,ours", "--jobs", "2",
                       "--out", str(out), timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "[  8/8" in result.stdout  # progress per demonstration
    table = (out / "table.md").read_text()
    for name in ("valve", "tension belt", "window lock", "flap latch", "**mean**",
                 "mean / ours", "joint type right"):
        assert name in table
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 8 * 2
    assert {r["method"] for r in rows} == {"regal", "ours"}
    assert all(0.0 <= float(r["tangent_error_deg"]) <= 180.0 for r in rows)
    assert (out / "tangent_error.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_tune_writes_a_loadable_config(procs: Processes, tmp_path: Path) -> None:
    out = tmp_path / "tuned.toml"
    result = procs.run("tune", "--trials", "2", "--jobs", "2", "--out", str(out), timeout=900)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "trial   1" in result.stdout
    assert "| tuning |" in result.stdout and "| evaluation |" in result.stdout
    config = load_section("tracker", out)  # what `handkse --config tuned.toml ...` does
    assert config.mahalanobis_rb > 0
