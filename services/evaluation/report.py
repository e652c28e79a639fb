"""Evaluation outputs: Table II-style markdown, a CSV of every row, and a Fig. 4-style bar chart."""

from __future__ import annotations

import csv
import math
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from services.evaluation.runner import LABELS, Row
from services.synthetic.objects import PRESETS

PRISMATIC_FIRST = ("prismatic", "revolute")


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def per_object(rows: Sequence[Row], methods: Sequence[str]) -> dict[str, dict[str, float]]:
    """object -> method -> mean tangent error (deg) over participants and seeds."""
    acc: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        acc[r.object][r.method].append(r.tangent_error_deg)
    return {o: {m: _mean(acc[o][m]) for m in methods} for o in acc}


def method_means(rows: Sequence[Row], methods: Sequence[str]) -> dict[str, float]:
    """Mean over objects of the per-object means (every object weighs the same, as in Table II)."""
    table = per_object(rows, methods)
    return {m: _mean([table[o][m] for o in table]) for m in methods}


def type_accuracy(rows: Sequence[Row], method: str) -> tuple[int, int]:
    mine = [r for r in rows if r.method == method]
    return sum(r.type_est == r.type_true for r in mine), len(mine)


def table_markdown(rows: Sequence[Row], methods: Sequence[str], title: str) -> str:
    """Object rows grouped by joint type, method columns, tangent error in degrees."""
    table = per_object(rows, methods)
    types = {r.object: r.type_true for r in rows}
    order = [o for t in PRISMATIC_FIRST for o in PRESETS if o in table and types[o] == t]
    lines = [f"# {title}", "",
             "Tangent error in degrees (mean over participants and seeds), as in the paper's "
             "Table II.", "",
             "| Object | " + " | ".join(LABELS[m] for m in methods) + " |",
             "| --- | " + " | ".join("---:" for _ in methods) + " |"]
    for joint_type in PRISMATIC_FIRST:
        lines.append(f"| *{joint_type.capitalize()}* |" + " |" * len(methods))
        for o in (o for o in order if types[o] == joint_type):
            best = min(table[o][m] for m in methods)
            cells = [(f"**{table[o][m]:.1f}**" if table[o][m] == best else f"{table[o][m]:.1f}")
                     for m in methods]
            lines.append(f"| {o.replace('_', ' ')} | " + " | ".join(cells) + " |")
    means = method_means(rows, methods)
    lines.append("| **mean** | " + " | ".join(f"{means[m]:.1f}" for m in methods) + " |")
    if "ours" in methods:
        ours = means["ours"]
        lines.append("| mean / ours | " + " | ".join(f"{means[m] / ours:.2f}" for m in methods)
                     + " |")
    acc = [type_accuracy(rows, m) for m in methods]
    lines.append("| joint type right | " + " | ".join(f"{a}/{n}" for a, n in acc) + " |")
    return "\n".join(lines) + "\n"


def write_csv(rows: Sequence[Row], path: Path) -> None:
    fields = list(Row.__dataclass_fields__)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: getattr(r, k) for k in fields})


def plot_bars(rows: Sequence[Row], methods: Sequence[str], path: Path) -> None:
    """Bar chart of the mean tangent error per method with the spread over objects (Fig. 4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = per_object(rows, methods)
    values = [[table[o][m] for o in table if math.isfinite(table[o][m])] for m in methods]
    means = [float(np.mean(v)) if v else math.nan for v in values]
    stds = [float(np.std(v)) if v else 0.0 for v in values]
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=120)
    colors = ["#d97fb0", "#5bc0c8", "#8fd3d8", "#9aa7c7", "#2b59c3"][-len(methods):]
    ax.bar(range(len(methods)), means, yerr=stds, capsize=4, color=colors)
    for i, v in enumerate(values):
        ax.scatter(np.full(len(v), i) + np.linspace(-0.15, 0.15, len(v)), v, s=8, c="k",
                   alpha=0.5, zorder=3)
    ax.set_xticks(range(len(methods)), [LABELS[m] for m in methods], rotation=12, fontsize=8)
    ax.set_ylabel("tangent error [deg]")
    ax.set_title("Mean tangent error over objects (bars: ±1 std over objects; dots: objects)",
                 fontsize=9)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_report(rows: Sequence[Row], methods: Sequence[str], out_dir: Path, title: str) -> Path:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "table.md").write_text(table_markdown(rows, methods, title))
    write_csv(rows, out_dir / "results.csv")
    plot_bars(rows, methods, out_dir / "tangent_error.png")
    return out_dir
