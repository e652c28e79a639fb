"""The figures of ``handkse eval``: tangent error per object and method, and convergence over time.

Every figure names its objects and methods and says, in a caption under the plot, which data it
shows (synthetic demonstrations, split, participants, seeds), so a printed copy stands alone.
matplotlib is imported inside each function (the ``eval`` extra), with the Agg backend: files only.
"""

from __future__ import annotations

import math
import textwrap
import warnings
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from services.evaluation.runner import CONVERGED_DEG, LABELS, History, Row
from services.synthetic.splits import OBJECTS_BY_SPLIT

if TYPE_CHECKING:
    from matplotlib.figure import Figure

JOINT_TYPE_ORDER = ("prismatic", "revolute", "rigid")
# Every split's objects in their preset order (paper first).
OBJECT_NAMES = tuple(o for objects in OBJECTS_BY_SPLIT.values() for o in objects)
COLORS = {"regal": "#d97fb0", "screwmimic_faithful": "#3a9fa8", "screwmimic_fair": "#8fd3d8",
          "screwmimic_robust": "#1f6f75", "ours_no_unc": "#e08a2c",
          "ours_no_unc_gates": "#f2c14e", "ours_no_kinematic_prior": "#7aa6e0",
          "ours": "#2b59c3"}
DPI = 150
CAPTION_CHARS_PER_INCH = 15.5  # at the caption's 8.5 pt


def object_label(name: str) -> str:
    """``window_lock`` -> ``window lock``."""
    return name.replace("_", " ")


def object_order(types: dict[str, str]) -> list[str]:
    """Objects of ``types`` (object -> true joint type): prismatic, revolute, then rigid (still
    holds), each in preset order (the paper split's objects before the household's)."""
    return [o for t in JOINT_TYPE_ORDER for o in OBJECT_NAMES if o in types and types[o] == t]


def _numbers(values: Sequence[int]) -> str:
    """``[0]`` -> ``0``; ``[0, 1, 2]`` -> ``0-2``; ``[1, 3]`` -> ``1, 3``."""
    v = sorted(set(values))
    if len(v) > 2 and v == list(range(v[0], v[-1] + 1)):
        return f"{v[0]}-{v[-1]}"
    return ", ".join(str(x) for x in v)


def describe_data(rows: Sequence[Row], split: str | None = None) -> str:
    """Where the numbers come from, in one sentence: generator, split (if given), objects,
    participants, seeds and the number of demonstrations."""
    demos = {(r.object, r.participant, r.seed) for r in rows}
    objects = {r.object for r in rows}
    participants = [r.participant for r in rows]
    seeds = [r.seed for r in rows]
    p_word = "participant" if len(set(participants)) == 1 else "participants"
    s_word = "seed" if len(set(seeds)) == 1 else "seeds"
    split_text = f", {split} split" if split else ""
    return (f"Synthetic demonstrations (handkse's generator, ground truth known){split_text}: "
            f"{_count(len(objects), 'object')}, {p_word} {_numbers(participants)}, {s_word} "
            f"{_numbers(seeds)} per (object, participant); "
            f"{_count(len(demos), 'demonstration')}.")


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def _caption(fig: Any, text: str, bottom_in: float) -> None:
    """``text`` wrapped under the axes, in the bottom ``bottom_in`` inches of ``fig``."""
    lines = textwrap.fill(text, int(CAPTION_CHARS_PER_INCH * fig.get_figwidth()))
    fig.text(0.01, 0.12 / fig.get_figheight(), lines, ha="left", va="bottom", fontsize=8.5,
             color="#222222")
    fig.subplots_adjust(bottom=bottom_in / fig.get_figheight())


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _errors(rows: Sequence[Row]) -> dict[str, dict[str, list[float]]]:
    acc: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        acc[r.object][r.method].append(r.tangent_error_deg)
    return acc


def _finite_mean(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def save(fig: Figure, path: Path) -> Path:
    """Write ``fig`` to ``path`` (PNG by its suffix) and free it."""
    fig.savefig(path)
    _pyplot().close(fig)
    return path


def tangent_error_figure(rows: Sequence[Row], methods: Sequence[str], data: str) -> Figure:
    """Left: tangent error of every method on every object (grouped bars, objects named and
    grouped by joint type). Right: the mean over objects per method with the spread (Fig. 4)."""
    plt = _pyplot()
    acc = _errors(rows)
    types = {r.object: r.type_true for r in rows}
    order = object_order(types)
    table = {o: {m: _finite_mean(acc[o][m]) for m in methods} for o in order}
    n_per_object = max((len(acc[o][m]) for o in order for m in methods), default=1)

    # Long method names, rotated under the mean panel, need room above the caption.
    extra_in = 0.035 * max(0, max(len(LABELS[m]) for m in methods) - 21)
    fig, (ax, ax_mean) = plt.subplots(1, 2, figsize=(max(13.0, 5.0 + 0.55 * len(order)),
                                                     5.2 + extra_in),
                                      dpi=DPI, gridspec_kw={"width_ratios": [3.3, 1]})
    width = 0.8 / len(methods)
    x = np.arange(len(order))
    for k, m in enumerate(methods):
        ax.bar(x + (k - (len(methods) - 1) / 2) * width, [table[o][m] for o in order], width,
               color=COLORS.get(m), label=LABELS[m], edgecolor="white", linewidth=0.4)
    ax.set_xticks(x, [object_label(o) for o in order], rotation=25, ha="right")
    lo = -0.5
    for joint_type in JOINT_TYPE_ORDER:
        n = sum(types[o] == joint_type for o in order)
        if not n:
            continue
        hi = lo + n
        if hi < len(order) - 0.5:
            ax.axvline(hi, color="k", linewidth=0.8)
        label = "rigid (no motion)" if joint_type == "rigid" else joint_type
        if joint_type == "rigid":
            ax.text((lo + hi) / 2, 45, "no tangent error:\nthe report counts\ntheir types",
                    ha="center", va="center", fontsize=8, color="#555555")
        ax.text((lo + hi) / 2, 1.01, label, transform=ax.get_xaxis_transform(),
                ha="center", va="bottom", fontsize=9, style="italic")
        lo = hi
    ax.set_xlim(-0.5, len(order) - 0.5)
    ax.set_ylim(0, 95)
    ax.set_ylabel("tangent error [deg]")
    each = "mean over its demonstrations" if n_per_object > 1 else "one demonstration each"
    ax.set_title(f"Tangent error per object ({each})", fontsize=10, pad=16)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, ncols=min(len(methods), 4), loc="upper left",
              bbox_to_anchor=(0, -0.2), frameon=False)

    values = [[table[o][m] for o in order if math.isfinite(table[o][m])] for m in methods]
    means = [float(np.mean(v)) if v else math.nan for v in values]
    stds = [float(np.std(v)) if v else 0.0 for v in values]
    ax_mean.bar(range(len(methods)), means, yerr=stds, capsize=3,
                color=[COLORS.get(m) for m in methods])
    for i, v in enumerate(values):
        ax_mean.scatter(np.full(len(v), i) + np.linspace(-0.2, 0.2, len(v)), v, s=7, c="k",
                        alpha=0.5, zorder=3, linewidths=0)
    for i, (mean, std) in enumerate(zip(means, stds, strict=True)):
        ax_mean.text(i, mean + std + 1.5, f"{mean:.1f}", ha="center", va="bottom", fontsize=8,
                     fontweight="bold")
    ax_mean.set_xticks(range(len(methods)), [LABELS[m] for m in methods], rotation=35,
                       ha="right", fontsize=8)
    ax_mean.set_ylim(0, 95)
    ax_mean.set_title("Mean over objects", fontsize=10, pad=16)
    ax_mean.grid(axis="y", alpha=0.3)
    fig.suptitle("Joint axis accuracy on synthetic demonstrations: every method, every object",
                 fontsize=12, fontweight="bold")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    _caption(fig, f"{data} Tangent error: the mean angle between the true and the estimated "
             "direction of motion over the demonstrated range (docs/evaluation.md#tangent-error); "
             "90 deg for a rigid or missing estimate. Right: bars and numbers are the means over "
             "the objects, whiskers one standard deviation, dots the objects.",
             bottom_in=1.45 + extra_in)
    return fig


def _on_grid(h: History, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``values`` of ``h`` held from frame to frame, sampled at ``grid`` (s); NaN past its end."""
    idx = np.searchsorted(h.t_s, grid, side="right") - 1
    out = np.full(len(grid), math.nan)
    inside = (idx >= 0) & (grid <= h.t_s[-1])
    out[inside] = values[idx[inside]]
    return out


def _median_band(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Median and interquartile range over the rows of ``stack`` (demos x times), ignoring NaN."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: before any model
        lo, med, hi = np.nanpercentile(stack, [25, 50, 75], axis=0)
    return med, lo, hi


def convergence_methods(histories: Sequence[History]) -> list[str]:
    """Methods with a history, in the order of the table."""
    have = {h.method for h in histories}
    return [m for m in LABELS if m in have]


def convergence_figure(histories: Sequence[History], data: str, columns: int = 5) -> Figure:
    """One panel per object: tangent error (top, log scale) and the probability of the true
    joint type (bottom) against time since the demonstration's start, a line per method (the
    median over demonstrations) with the interquartile band where there are several."""
    plt = _pyplot()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    by_object: dict[str, list[History]] = defaultdict(list)
    for h in histories:
        by_object[h.object].append(h)
    order = object_order({o: hs[0].type_true for o, hs in by_object.items()})
    methods = convergence_methods(histories)
    columns = max(1, min(columns, len(order)))
    rows = math.ceil(len(order) / columns)
    ratios = []
    for r in range(rows):
        ratios += [1.5, 1.0] + ([0.55] if r < rows - 1 else [])
    fig = plt.figure(figsize=(3.0 * columns + 0.6, 3.6 * rows + 2.4), dpi=DPI)
    grid = fig.add_gridspec(len(ratios), columns, height_ratios=ratios, hspace=0.12,
                            wspace=0.12, left=0.05, right=0.99, top=1 - 1.05 / (3.6 * rows + 2.4))
    counts = set()
    for k, obj in enumerate(order):
        r, c = divmod(k, columns)
        ax_err = fig.add_subplot(grid[3 * r, c])
        ax_p = fig.add_subplot(grid[3 * r + 1, c], sharex=ax_err)
        t_end = max(float(h.t_s[-1]) for h in by_object[obj])
        t = np.linspace(0.0, t_end, 400)
        for m in methods:
            mine = [h for h in by_object[obj] if h.method == m]
            if not mine:
                continue
            counts.add(len(mine))
            for ax, field in ((ax_err, "tangent_error_deg"), (ax_p, "p_true")):
                stack = np.array([_on_grid(h, getattr(h, field), t) for h in mine])
                med, lo, hi = _median_band(stack)
                ax.plot(t, med, color=COLORS.get(m), linewidth=1.6)
                if len(mine) > 1:
                    ax.fill_between(t, lo, hi, color=COLORS.get(m), alpha=0.2, linewidth=0)
        ax_err.axhline(CONVERGED_DEG, color="#555555", linestyle="--", linewidth=0.9)
        ax_err.set_yscale("log")
        ax_err.set_ylim(0.2, 100)
        ax_err.set_yticks([1, 10, 90], ["1", "10", "90"])
        ax_p.set_ylim(-0.04, 1.04)
        ax_p.set_yticks([0, 0.5, 1])
        ax_err.set_xlim(0, t_end)
        ax_err.set_title(f"{object_label(obj)} ({by_object[obj][0].type_true})", fontsize=10)
        ax_err.tick_params(labelbottom=False)
        for ax in (ax_err, ax_p):
            ax.grid(alpha=0.3, which="major")
            if c > 0:
                ax.tick_params(labelleft=False)
        if c == 0:
            ax_err.set_ylabel("tangent error\n[deg]", fontsize=9)
            ax_p.set_ylabel("P(true type)", fontsize=9)
        if k + columns >= len(order):
            ax_p.set_xlabel("time since the start [s]", fontsize=9)
    handles = [Line2D([], [], color=COLORS.get(m), linewidth=2, label=LABELS[m])
               for m in methods]
    handles.append(Line2D([], [], color="#555555", linestyle="--", linewidth=1,
                          label=f"{CONVERGED_DEG:.0f} deg: converged below"))
    several = max(counts, default=1) > 1
    if several:
        handles.append(Patch(color="#888888", alpha=0.3, label="interquartile range"))
    height = fig.get_figheight()
    fig.suptitle("Convergence: tangent error and probability of the true joint type over time",
                 x=0.05, y=1 - 0.12 / height, ha="left", va="top", fontsize=12,
                 fontweight="bold")
    fig.legend(handles=handles, loc="upper left", ncols=len(handles), fontsize=9,
               frameon=False, bbox_to_anchor=(0.045, 1 - 0.42 / height))
    n = "/".join(str(x) for x in sorted(counts)) or "0"
    line = ("Lines: the median over the demonstrations of each object "
            f"(n = {n} per object and method; past the end of a shorter one, over those still "
            "running), bands: their interquartile range. "
            if several else
            f"Lines: the one demonstration of each object (n = {n}). ")
    _caption(fig, f"{data} {line}Each line starts at the first model and shows the model held "
             "after each frame; 90 deg means no motion model (rigid, disconnected); a still hold "
             "has no error, only the probability of rigid. Only our methods are "
             "shown: the baselines (Regal-style, ScrewMimic-style) fit once, at the end of the "
             "demonstration, and have no estimate over time.", bottom_in=1.0)
    fig.subplots_adjust(bottom=1.25 / fig.get_figheight())
    return fig
