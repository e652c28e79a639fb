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
    # not a terminal: one plain line per finished demonstration, counting up, nothing redrawn
    progress = [line for line in result.stdout.splitlines() if line.startswith("[")]
    assert [line.split("]")[0] for line in progress] == [f"[{i}/8" for i in range(1, 9)]
    assert all(" p1 s0: " in line or " p2 s0: " in line for line in progress)
    assert all("regal" in line and "ours" in line and " deg (" in line for line in progress)
    assert "s left)" in progress[0] and "left" not in progress[-1]
    assert "\r" not in result.stdout
    table = (out / "table.md").read_text()
    for name in ("valve", "tension belt", "window lock", "flap latch", "**mean**",
                 "mean / ours", "joint type right"):
        assert name in table
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 8 * 2
    assert {r["method"] for r in rows} == {"regal", "ours"}
    assert all(0.0 <= float(r["tangent_error_deg"]) <= 180.0 for r in rows)
    for name in ("tangent_error.png", "convergence.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (out / name).stat().st_size > 20_000
    assert "convergence.png" in result.stdout  # listed among the files written


def test_eval_household_conditions_writes_named_files(procs: Processes, tmp_path: Path) -> None:
    out = tmp_path / "eval"
    result = procs.run("eval", "--split", "household", "--partition", "tuning", "--condition",
                       "plain,idle_same", "--methods", "ours_no_kinematic_prior,ours", "--jobs", "2",
                       "--out", str(out), timeout=900)
    assert result.returncode == 0, result.stdout + result.stderr
    progress = [line for line in result.stdout.splitlines() if line.startswith("[")]
    assert len(progress) == 2 * 14  # 7 objects by participants 4 and 5, two conditions
    assert sum(" idle_same: " in line for line in progress) == 14
    table = (out / "table_household_conditions.md").read_text()
    for text in ("## household split, cut variant", "condition idle_same", "still holds rigid",
                 "no articulated verdict", "time to the right type", "90 % interval covers",
                 "axis direction", "Conditions vs. plain", "cabinet door", "hold handle",
                 "Ours w/o kin. prior"):  # an optional method, run when named
        assert text in table, text
    with open(out / "results_household_conditions.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * 14 * 2
    assert {r["condition"] for r in rows} == {"plain", "idle_same"}
    assert {r["split"] for r in rows} == {"household"}
    for name in ("tangent_error_household.png", "tangent_error_household_idle_same.png",
                 "convergence_household.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_eval_refuses_bad_choices_in_one_line(procs: Processes, tmp_path: Path) -> None:
    for args, says in ((("--variant", "cut,long"), "unknown variant 'long'"),
                       (("--methods", "ours,magic"), "unknown method 'magic'"),
                       (("--variant", "sequence", "--condition", "dropout"),
                        "no demonstrations to run")):
        result = procs.run("eval", *args, "--out", str(tmp_path / "x"), timeout=120)
        assert result.returncode == 2, result.stdout + result.stderr
        assert says in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "x").exists()


def test_tune_writes_a_loadable_config(procs: Processes, tmp_path: Path) -> None:
    out = tmp_path / "tuned.toml"
    result = procs.run("tune", "--trials", "2", "--jobs", "2", "--out", str(out), timeout=900)
    assert result.returncode == 0, result.stdout + result.stderr
    assert [line.split(" (")[0].split(":")[0] for line in result.stdout.splitlines()
            if line.startswith("[")] == [
        "[1/2] trial 0", "[2/2] trial 1",  # the trials as they finish
        "[1/4] tuning split with the default parameters",
        "[2/4] tuning split with the tuned parameters",
        "[3/4] evaluation split with the default parameters",
        "[4/4] evaluation split with the tuned parameters"]
    assert "| tuning |" in result.stdout and "| evaluation |" in result.stdout
    config = load_section("tracker", out)  # what `handkse --config tuned.toml ...` does
    assert config.mahalanobis_rb > 0
