"""Evaluation outputs: Table II-style markdown, a CSV of every row, and the figures
(:mod:`services.evaluation.figures`)."""

from __future__ import annotations

import csv
import math
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from services.evaluation.runner import LABELS, History, Row
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


def write_report(rows: Sequence[Row], methods: Sequence[str], out_dir: Path, title: str,
                 histories: Sequence[History] = (), data: str = "") -> list[Path]:
    """Write ``table.md``, ``results.csv``, ``tangent_error.png`` and, given the histories of
    our methods, ``convergence.png`` into ``out_dir``; returns the files written. ``data``
    (default: from the rows) says in each figure's caption which demonstrations it shows."""
    from services.evaluation import figures

    out_dir.mkdir(parents=True, exist_ok=True)
    data = data or figures.describe_data(rows)
    written = [out_dir / "table.md", out_dir / "results.csv"]
    written[0].write_text(table_markdown(rows, methods, title))
    write_csv(rows, written[1])
    written.append(figures.save(figures.tangent_error_figure(rows, methods, data),
                                out_dir / "tangent_error.png"))
    if histories:
        written.append(figures.save(figures.convergence_figure(histories, data),
                                    out_dir / "convergence.png"))
    return written
