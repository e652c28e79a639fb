"""The robot-trial figures: every trial in its panel, endings explained, the limit on top."""

from __future__ import annotations

import csv
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from matplotlib.figure import Figure

from services.evaluation import robot_plots
from services.evaluation.robot_trials import LABELS, TrialRow

LIMIT_N = 70.0
Trials = tuple[list[TrialRow], dict[tuple[str, int, str], dict[str, list[float]]]]


def _row(obj: str, seed: int, method: str, success: bool, reason: str,
         peak: float = 20.0) -> TrialRow:
    return TrialRow(object=obj, seed=seed, method=method, type_est="revolute",
                    axis_angle_deg=3.0, axis_offset_cm=0.5, success=success, reason=reason,
                    articulated_deg=180.0 if success else 60.0, peak_force_n=peak,
                    mean_force_n=peak / 2, peak_torque_nm=1.0, duration_s=6.5)


def _trace(peak: float, stop_s: float | None = None) -> dict[str, list[float]]:
    t = np.linspace(0.0, 6.5, 651)
    return {"t_s": t.tolist(), "force_n": (peak * np.sin(np.pi * t / 13)).tolist(),
            "stop_s": [] if stop_s is None else [stop_s]}


@pytest.fixture
def trials() -> Trials:
    rows, traces = [], {}
    for obj in ("key", "window_lock"):
        for seed in range(3):
            for method, ok, reason in (("ours", True, "ok"), ("regal", True, "ok"),
                                       ("screwmimic", False, "torque_saturation")):
                rows.append(_row(obj, seed, method, ok, reason))
                traces[(obj, seed, method)] = _trace(20.0, None if ok else 2.5)
    # one trial refused before moving (no trace), one stopped by the force limit
    rows[rows.index(_row("key", 2, "screwmimic", False, "torque_saturation"))] = _row(
        "key", 2, "screwmimic", False, "joint_limits", peak=0.0)
    traces[("key", 2, "screwmimic")] = {"t_s": [], "force_n": [], "stop_s": []}
    i = rows.index(_row("window_lock", 1, "screwmimic", False, "torque_saturation"))
    rows[i] = replace(rows[i], reason="force_limit", peak_force_n=70.0)
    traces[("window_lock", 1, "screwmimic")] = _trace(75.0, 3.0)
    return rows, traces


def _legend(fig: Figure) -> list[str]:
    return [t.get_text() for legend in fig.legends for t in legend.get_texts()]


def test_every_trial_has_its_panel_and_the_limit_is_on_top(trials: Trials) -> None:
    rows, traces = trials
    fig = robot_plots.trials_figure(rows, traces, LIMIT_N, "robot trials (test)")
    assert len(fig.axes) == 2 * 3  # objects x seeds
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[0] == "key, demonstration 0: 2/3 ok"
    assert titles[5] == "window lock, demonstration 2: 2/3 ok"
    for ax in fig.axes:
        limit = [line for line in ax.lines if list(line.get_ydata()) == [LIMIT_N, LIMIT_N]]
        assert len(limit) == 1
        others = [line for line in ax.lines if line is not limit[0]]
        assert all(line.get_zorder() < limit[0].get_zorder() for line in others)
        assert ax.get_ylim()[1] > LIMIT_N * 1.2  # headroom: nothing sits on the limit line
    key2 = fig.axes[2]
    assert [t.get_text() for t in key2.texts] == ["ScrewMimic-style: refused (joint limits)"]
    assert len([line for line in key2.lines if len(line.get_xdata()) > 2]) == 2  # two traces
    legend = _legend(fig)
    assert legend[:3] == [LABELS[m] for m in ("ours", "regal", "screwmimic")]
    assert "force limit 70 N" in legend
    for _, text in (robot_plots.ENDINGS[k] for k in ("success", "torque_saturation",
                                                     "force_limit")):
        assert text in legend
    assert robot_plots.ENDINGS["tracking_error"][1] not in legend  # only endings drawn
    caption = " ".join(t.get_text() for t in fig.texts).replace("\n", " ")
    assert "participant 3" in caption and "18 trials" in caption and "Markers" in caption


def test_the_abort_marker_sits_at_the_abort(trials: Trials) -> None:
    rows, traces = trials
    fig = robot_plots.demonstration_figure(rows, traces, LIMIT_N, "window_lock", 1)
    ax = fig.axes[0]
    marker = robot_plots.ENDINGS["force_limit"][0]
    at = [line for line in ax.lines if line.get_marker() == marker]
    assert len(at) == 1
    assert at[0].get_xdata()[0] == pytest.approx(3.0, abs=0.01)
    assert "window lock" in ax.get_title()


def test_files_round_trip_and_the_figures_redraw_from_them(trials: Trials,
                                                          tmp_path: Path) -> None:
    rows, traces = trials
    with open(tmp_path / "results.csv", "w", newline="") as f:  # as robot_trials writes it
        w = csv.DictWriter(f, fieldnames=list(asdict(rows[0])))
        w.writeheader()
        for r in rows:
            w.writerow(asdict(r))
    robot_plots.write_traces(traces, tmp_path / "traces.json")
    (tmp_path / "table.md").write_text("# the trials of the test\n")
    assert robot_plots.read_rows(tmp_path / "results.csv") == rows
    back = robot_plots.read_traces(tmp_path / "traces.json")
    assert set(back) == set(traces)
    assert np.allclose(back[("key", 0, "ours")]["force_n"], traces[("key", 0, "ours")]["force_n"],
                       atol=0.005)
    assert back[("key", 0, "screwmimic")]["stop_s"] == [2.5]
    assert robot_plots.main([str(tmp_path), "--key-seed", "1"]) == 0
    for name in ("force_trials.png", "force_key.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (tmp_path / name).stat().st_size > 20_000
