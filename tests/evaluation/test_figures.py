"""The figures of ``handkse eval``: objects and methods named, the data said, the convergence
plot per object; built from a real pipeline run on two demonstrations and from hand-made rows."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from services.evaluation import figures
from services.evaluation.runner import (
    LABELS,
    METHODS,
    History,
    Row,
    Settings,
    run_demo,
)
from services.kinematics.config import KinematicsConfig
from services.tracker.config import TrackerConfig


def _row(obj: str, joint_type: str, method: str, error: float, participant: int = 3,
         seed: int = 0) -> Row:
    return Row(object=obj, participant=participant, seed=seed, method=method,
               type_true=joint_type, type_est=joint_type, tangent_error_deg=error,
               axis_angle_deg=error, line_distance_m=math.nan, converge_s=1.0, runtime_s=0.1)


def _history(obj: str, joint_type: str, method: str, seed: int, end_s: float = 3.0) -> History:
    t = np.linspace(0.0, end_s, 91)
    error = np.where(t < 0.5, math.nan, 90.0 * np.exp(-t) + seed)
    p_true = np.where(t < 0.5, math.nan, np.clip(t / end_s, 0, 1))
    return History(object=obj, participant=3, seed=seed, method=method, type_true=joint_type,
                   t_s=t, tangent_error_deg=error, p_true=p_true)


def _texts(fig: Figure) -> str:
    return "\n".join(t.get_text() for t in fig.texts)


def _legend_texts(fig: Figure) -> list[str]:
    """The entries of the figure's legends and of its axes' legends."""
    legends = [*fig.legends, *(ax.get_legend() for ax in fig.axes if ax.get_legend())]
    return [t.get_text() for legend in legends for t in legend.get_texts()]


@pytest.fixture(scope="module")
def ran() -> tuple[list[Row], list[History]]:
    """Every method on two real demonstrations (a prismatic and a revolute object)."""
    settings = Settings(TrackerConfig(), KinematicsConfig())
    rows: list[Row] = []
    histories: list[History] = []
    for obj in ("slider", "window_lock"):
        result = run_demo(obj, 3, 0, settings, METHODS)
        rows += result.rows
        histories += result.histories
    return rows, histories


def test_histories_follow_the_pipeline_frame_by_frame(ran: tuple[list[Row], list[History]]
                                                      ) -> None:
    rows, histories = ran
    assert sorted((h.object, h.method) for h in histories) == [
        (o, m) for o in ("slider", "window_lock")
        for m in ("ours", "ours_no_unc", "ours_no_unc_gates")]
    for h in histories:
        assert h.t_s[0] == 0.0 and np.all(np.diff(h.t_s) > 0)
        assert h.t_s.shape == h.tangent_error_deg.shape == h.p_true.shape
        seen = np.isfinite(h.tangent_error_deg)
        assert seen[-1] and not seen[0]  # no model at the first frame, one at the end
        assert np.array_equal(seen, np.isfinite(h.p_true))
        assert np.all((h.p_true[seen] >= 0) & (h.p_true[seen] <= 1))
        row = next(r for r in rows if r.object == h.object and r.method == h.method)
        # the last model held is the final one the row scores
        assert h.tangent_error_deg[-1] == pytest.approx(row.tangent_error_deg, abs=1e-6)
        if math.isfinite(row.converge_s):  # below 10 deg for good from converge_s on
            after = h.t_s >= row.converge_s - 1e-9
            assert np.all(h.tangent_error_deg[after] < 10.0)


def test_describe_data_names_split_participants_and_seeds() -> None:
    rows = [_row("valve", "revolute", "ours", 3.0, p, s) for p in (1, 2) for s in range(3)]
    text = figures.describe_data(rows, "tuning")
    assert "Synthetic demonstrations" in text and "tuning split" in text
    assert "participants 1, 2" in text and "seeds 0-2" in text and "6 demonstrations" in text
    one = figures.describe_data([_row("key", "revolute", "ours", 3.0)], "evaluation")
    assert "1 object, participant 3, seed 0 " in one and "; 1 demonstration." in one


def test_tangent_error_figure_names_every_object_and_method(
        ran: tuple[list[Row], list[History]], tmp_path: Path) -> None:
    rows, _ = ran
    data = figures.describe_data(rows, "evaluation")
    fig = figures.tangent_error_figure(rows, METHODS, data)
    per_object, means = fig.axes
    assert [t.get_text() for t in per_object.get_xticklabels()] == ["slider", "window lock"]
    assert {t.get_text() for t in per_object.texts} == {"prismatic", "revolute"}
    assert per_object.get_ylabel() == "tangent error [deg]"
    assert _legend_texts(fig) == [LABELS[m] for m in METHODS]
    assert [t.get_text() for t in means.get_xticklabels()] == [LABELS[m] for m in METHODS]
    assert "Mean over objects" in means.get_title()
    # the bar of each (object, method) is the row's error
    heights = sorted(round(b.get_height(), 6) for b in per_object.patches)
    assert heights == sorted(round(r.tangent_error_deg, 6) for r in rows)
    assert data in _texts(fig).replace("\n", " ")
    path = figures.save(fig, tmp_path / "tangent_error.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 20_000


def test_convergence_figure_has_a_panel_per_object_and_only_our_methods(
        ran: tuple[list[Row], list[History]], tmp_path: Path) -> None:
    rows, histories = ran
    fig = figures.convergence_figure(histories, figures.describe_data(rows, "evaluation"))
    titled = [ax for ax in fig.axes if ax.get_title()]
    assert [ax.get_title() for ax in titled] == ["slider (prismatic)", "window lock (revolute)"]
    assert len(fig.axes) == 2 * len(titled)  # tangent error over P(true type) for each
    assert all(ax.get_yscale() == "log" for ax in titled)
    assert fig.axes[0].get_ylabel().startswith("tangent error")
    assert fig.axes[1].get_ylabel() == "P(true type)"
    assert fig.axes[1].get_xlabel().startswith("time since the start")
    legend = _legend_texts(fig)
    assert legend[:3] == [LABELS["ours_no_unc"], LABELS["ours_no_unc_gates"], LABELS["ours"]]
    assert not any(LABELS[m] in legend for m in ("regal", "screwmimic_fair",
                                                 "screwmimic_robust"))
    assert "interquartile range" not in legend  # one demonstration per object: no band
    caption = _texts(fig).replace("\n", " ")
    assert "Only our methods are shown" in caption and "n = 1" in caption
    # a line per method in each panel, plus the 10 deg line
    assert len(titled[0].lines) == 3 + 1
    path = figures.save(fig, tmp_path / "convergence.png")
    assert path.stat().st_size > 20_000


def test_convergence_bands_over_several_demonstrations() -> None:
    hs = [_history("valve", "revolute", m, s, end_s=3.0 + s) for m in ("ours", "ours_no_unc")
          for s in range(4)]
    hs += [_history("slider", "prismatic", "ours", s) for s in range(4)]
    fig = figures.convergence_figure(hs, "test data.")
    titled = [ax for ax in fig.axes if ax.get_title()]
    assert [ax.get_title() for ax in titled] == ["slider (prismatic)", "valve (revolute)"]
    valve_error = titled[1]
    bands = [c for c in valve_error.collections if isinstance(c, PolyCollection)]
    assert len(bands) == 2  # one per method
    t, median = (np.asarray(v) for v in valve_error.lines[1].get_data())  # ours (table order)
    while_all_run = (t > 0.6) & (t < 3.0)
    # seeds 0-3 add 0-3 deg: the median adds 1.5 (held frame to frame, so within a step)
    assert np.allclose(median[while_all_run], 90 * np.exp(-t[while_all_run]) + 1.5, atol=3.5)
    assert np.isnan(median[t < 0.45]).all()  # no model yet
    assert "interquartile range" in _legend_texts(fig)
    assert "n = 4" in _texts(fig)
    assert valve_error.get_xlim()[1] == pytest.approx(6.0)  # the longest demonstration


def test_history_on_a_grid_holds_values_and_stops_at_its_end() -> None:
    h = _history("valve", "revolute", "ours", 0, end_s=3.0)
    grid = np.array([0.0, 0.6, 1.01, 3.0, 3.5])
    got = figures._on_grid(h, h.tangent_error_deg, grid)
    assert math.isnan(got[0]) and math.isnan(got[-1])
    k = int(np.searchsorted(h.t_s, 1.01, side="right") - 1)
    assert got[2] == h.tangent_error_deg[k] and got[3] == h.tangent_error_deg[-1]
