"""The report of ``handkse eval`` from hand-made rows: failures counted as failures, still
holds by type, times, calibration, per-segment rows, comparisons, the free stream, file names."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

from services.evaluation.phase_metrics import PhaseScore
from services.evaluation.report import (
    calibration_cells,
    method_means,
    no_verdict,
    report_markdown,
    stem,
    type_accuracy,
    write_report,
)
from services.evaluation.runner import (
    WHOLE_CUT,
    Evaluation,
    FreeRow,
    PhaseRow,
    Row,
    SegmentRow,
)

METHODS = ("regal", "ours_no_unc", "ours")


def _row(obj: str, type_true: str, method: str, type_est: str, error: float, *,
         variant: str = "cut", condition: str = "plain", seed: int = 0, type_s: float = 1.0,
         axis_d2: float = math.nan, point_d2: float = math.nan) -> Row:
    return Row(object=obj, participant=6, seed=seed, method=method, type_true=type_true,
               type_est=type_est, tangent_error_deg=error, axis_angle_deg=error,
               line_distance_m=math.nan, converge_s=type_s, runtime_s=0.1, split="household",
               variant=variant, condition=condition, type_s=type_s, axis_d2=axis_d2,
               point_d2=point_d2)


def _rows(variant: str = "cut", condition: str = "plain", shift: float = 0.0) -> list[Row]:
    return [
        _row("kitchen_drawer", "prismatic", "regal", "prismatic", 3.0, variant=variant,
             condition=condition),
        _row("kitchen_drawer", "prismatic", "ours_no_unc", "disconnected", 90.0,
             variant=variant, condition=condition, type_s=math.nan),
        _row("kitchen_drawer", "prismatic", "ours", "prismatic", 1.0 + shift, variant=variant,
             condition=condition, axis_d2=1.0),
        _row("cabinet_door", "revolute", "regal", "revolute", 5.0, variant=variant,
             condition=condition),
        _row("cabinet_door", "revolute", "ours_no_unc", "unknown", 90.0, variant=variant,
             condition=condition, type_s=math.nan),
        _row("cabinet_door", "revolute", "ours", "revolute", 3.0 + shift, variant=variant,
             condition=condition, type_s=3.0, axis_d2=10.0, point_d2=0.5),
        _row("hold_handle", "rigid", "regal", "prismatic", math.nan, variant=variant,
             condition=condition),
        _row("hold_handle", "rigid", "ours_no_unc", "disconnected", math.nan, variant=variant,
             condition=condition, type_s=math.nan),
        _row("hold_handle", "rigid", "ours", "rigid", math.nan, variant=variant,
             condition=condition, type_s=2.0),
    ]


def test_failures_are_counted_as_failures() -> None:
    rows = _rows()
    assert type_accuracy(rows, "ours_no_unc") == (0, 3)
    assert no_verdict(rows, "ours_no_unc") == (2, 2)
    assert no_verdict(rows, "regal") == (0, 2)  # a wrong joint is a verdict
    assert method_means(rows, METHODS) == {"regal": 4.0, "ours_no_unc": 90.0, "ours": 2.0}
    text = report_markdown(Evaluation(rows=rows), METHODS, "test")
    assert "| **mean** | 4.0 | 90.0 | 2.0 |" in text
    assert "| joint type right | 2/3 | 0/3 | 3/3 |" in text
    assert "| no articulated verdict | 0/2 | 2/2 | 0/2 |" in text
    assert "| still holds rigid | 0/1 | 0/1 | 1/1 |" in text
    assert "| hold handle | 0/1 rigid | 0/1 rigid | 1/1 rigid |" in text
    assert "| kitchen drawer (prismatic) | 1/1 | 0/1 (disconnected) | 1/1 |" in text
    # times: ours got there in 1, 3 and 2 s; the ablation never did
    assert "| time to the right type [s]: median / p90 / never | - | - / - / 3 | " \
           "2.0 / 2.8 / 0 |" in text
    assert "| time to within 10 deg [s]: median / p90 / never | - | - / - / 2 | " \
           "2.0 / 2.8 / 0 |" in text


def test_calibration_is_reported_where_the_type_is_right() -> None:
    rows = _rows()
    assert calibration_cells(rows, "ours") == ("1/2 (50 %)", "1/1 (100 %)")
    assert calibration_cells(rows, "ours_no_unc") == ("-", "-")
    text = report_markdown(Evaluation(rows=rows), METHODS, "test")
    assert "| axis direction | - | 1/2 (50 %) |" in text
    assert "| revolute axis position | - | 1/1 (100 %) |" in text


def test_comparisons_whole_vs_cut_and_conditions_vs_plain() -> None:
    rows = (_rows("whole", shift=10.0) + _rows(WHOLE_CUT) + _rows("whole", "idle_same", 11.0))
    text = report_markdown(Evaluation(rows=rows), METHODS, "test")
    assert "## household split, whole variant" in text
    assert "final contact phase, cut at grasp and release" in text
    assert "## Whole demonstrations vs. the same cut at grasp and release" in text
    assert "| household | 4.0 vs 4.0 (+0.0, n = 2) | 90.0 vs 90.0 (+0.0, n = 2) | " \
           "2.0 vs 12.0 (+10.0, n = 2) |" in text
    assert "## Conditions vs. plain on the same demonstrations" in text
    # the baselines are given the manipulating hand in every condition: not compared
    assert "| household, whole: idle_same | 90.0 vs 90.0 (+0.0, n = 2) | " \
           "12.0 vs 13.0 (+1.0, n = 2) |" in text


def test_segments_phases_and_the_free_stream() -> None:
    ids = {"object": "cabinet_door", "participant": 6, "seed": 0, "split": "household",
           "variant": "sequence", "condition": "plain"}
    segments = [SegmentRow(**ids, method="ours", segment=i, joint=j, type_true=t,
                           type_est=e, tangent_error_deg=err, source="at_release")
                for i, j, t, e, err in ((0, "latch", "prismatic", "prismatic", 4.0),
                                        (1, "door", "revolute", "disconnected", 90.0))]
    phases = [PhaseRow(**ids, method="ours", score=PhaseScore(
        onset_errors_ms=(100.0, -50.0), release_errors_ms=(30.0, 60.0), missed=0, extra=1,
        duration_s=8.0, free_s=3.0), dated=PhaseScore(
        onset_errors_ms=(10.0, -20.0), release_errors_ms=(5.0, 41.0), missed=0, extra=0,
        duration_s=8.0, free_s=3.0))]
    free = [FreeRow(participant=6, seed=0, method="ours", frames=1800, articulated_frames=12,
                    final_type="disconnected", duration_s=60.0, phases=None),
            FreeRow(participant=7, seed=0, method="ours", frames=1800, articulated_frames=0,
                    final_type="rigid", duration_s=60.0,
                    phases=PhaseScore((), (), 0, 3, 60.0, 60.0),
                    dated=PhaseScore((), (), 0, 1, 60.0, 60.0), articulated_phases=1)]
    rows = [_row("cabinet_door", "revolute", "ours", "disconnected", 90.0, variant="sequence")]
    text = report_markdown(Evaluation(rows=rows, segments=segments, phases=phases, free=free),
                           ("ours",), "test")
    assert "the model held at each contact phase's last frame" in text
    assert "| 1 | 4.0 deg, 1/1 types |" in text and "| 2 | 90.0 deg, 0/1 types |" in text
    assert "| every phase's type right | 0/1 |" in text
    assert "| Ours (online) | 75 / 95 | 45 / 57 | 2/2 | 20.00 |" in text
    assert "| Ours (kept, dated) | 15 / 19 | 23 / 37 | 2/2 | 0.00 |" in text
    # the stream without segmentation counts in neither rate; one kept articulated phase
    assert ("| Ours | 2 | 2.0 | 12/3600 | 1/2 | disconnected 1, rigid 1 | 3.00 / 1.00 | 1 |"
            in text)


def test_file_names_say_what_the_run_covered(tmp_path: Path) -> None:
    assert stem(["paper"], ["cut"], ["plain"]) == ""
    assert stem(["household"], ["cut"], ["plain"]) == "_household"
    assert stem(["paper", "household"], ["whole", WHOLE_CUT], ["plain", "idle_same"]) == \
        "_all_whole_conditions"
    assert stem(["paper"], ["cut", "regrasp"], ["dropout"]) == "_variants_dropout"
    pytest.importorskip("matplotlib")
    ev = Evaluation(rows=_rows() + _rows(condition="idle_same"))
    written = write_report(ev, METHODS, tmp_path, "test")
    assert [p.name for p in written] == [
        "table_household_conditions.md",
        "results_household_conditions.csv", "tangent_error_household.png",
        "tangent_error_household_idle_same.png"]
    with open(written[1]) as f:
        got = list(csv.DictReader(f))
    assert len(got) == 18 and got[0]["condition"] == "plain" and got[0]["split"] == "household"
