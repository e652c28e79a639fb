"""Evaluation outputs: a markdown report (Table II-style per split, variant and condition, with
types, times, calibration, segments, segmentation, conditions and the free stream), CSVs of
every row, and the figures (:mod:`services.evaluation.figures`).

File names carry what the run covered (:func:`stem`): the paper split's cut variant without a
condition writes ``table.md``, ``results.csv``, ...; the household split ``table_household.md``,
``results_household.csv``, ...; one group of a run with several writes its figures under the
group's own stem.
"""

from __future__ import annotations

import csv
import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from services.evaluation import metrics
from services.evaluation.figures import object_order
from services.evaluation.phase_metrics import PhaseScore, summarise_phases
from services.evaluation.runner import (
    ARTICULATED,
    LABELS,
    OURS,
    WHOLE_CUT,
    Evaluation,
    FreeRow,
    History,
    Row,
    SegmentRow,
)

Group = tuple[str, str, str]  # (split, variant, condition)
CALIBRATION_GOAL = (0.85, 0.95)


def _mean(values: Iterable[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def per_object(rows: Sequence[Row], methods: Sequence[str]) -> dict[str, dict[str, float]]:
    """object -> method -> mean tangent error (deg) over participants and seeds (NaN for a
    rigid truth, which has no motion to compare)."""
    acc: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in rows:
        acc[r.object][r.method].append(r.tangent_error_deg)
    return {o: {m: _mean(acc[o][m]) for m in methods} for o in acc}


def method_means(rows: Sequence[Row], methods: Sequence[str]) -> dict[str, float]:
    """Mean over objects of the per-object means (every object weighs the same, as in Table II;
    objects without a tangent error, the still holds, are left out)."""
    table = per_object(rows, methods)
    return {m: _mean([table[o][m] for o in table]) for m in methods}


def type_accuracy(rows: Sequence[Row], method: str) -> tuple[int, int]:
    """(right, all) final types of ``method``."""
    mine = [r for r in rows if r.method == method]
    return sum(r.type_est == r.type_true for r in mine), len(mine)


def no_verdict(rows: Sequence[Row], method: str) -> tuple[int, int]:
    """(no articulated verdict, articulated truths): final type unknown, disconnected or rigid
    where the truth is prismatic or revolute."""
    mine = [r for r in rows if r.method == method and r.type_true in ARTICULATED]
    return sum(r.type_est not in ARTICULATED for r in mine), len(mine)


def groups(rows: Sequence[Row]) -> list[Group]:
    """The (split, variant, condition) groups of ``rows``, in order of appearance."""
    return list(dict.fromkeys((r.split, r.variant, r.condition) for r in rows))


def group_title(group: Group) -> str:
    split, variant, condition = group
    v = ("whole demonstrations' final contact phase, cut at grasp and release"
         if variant == WHOLE_CUT else f"{variant} variant")
    c = "" if condition == "plain" else f", condition {condition}"
    return f"{split} split, {v}{c}"


def stem(split_names: Iterable[str], variants: Iterable[str], conditions: Iterable[str]) -> str:
    """File-name suffix of what a run covered: "" for the paper split's cut variant without a
    condition (the original names), else ``_<split>``, ``_<variant>``, ``_<condition>`` for
    each that is not the default (``all``, ``variants``, ``conditions`` when several)."""
    def part(values: Iterable[str], default: str, several: str) -> str:
        v = sorted(set(values) - {WHOLE_CUT})
        if not v or v == [default]:
            return ""
        return "_" + (v[0] if len(v) == 1 else several)

    return (part(split_names, "paper", "all") + part(variants, "cut", "variants")
            + part(conditions, "plain", "conditions"))


def _fmt(v: float, digits: int = 1) -> str:
    return f"{v:.{digits}f}" if math.isfinite(v) else "-"


def _error_table(rows: Sequence[Row], methods: Sequence[str]) -> list[str]:
    table = per_object(rows, methods)
    types = {r.object: r.type_true for r in rows}
    lines = ["| Object | " + " | ".join(LABELS[m] for m in methods) + " |",
             "| --- | " + " | ".join("---:" for _ in methods) + " |"]
    order = object_order(types)
    for joint_type in ("prismatic", "revolute", "rigid"):
        mine = [o for o in order if types[o] == joint_type]
        if not mine:
            continue
        lines.append(f"| *{joint_type.capitalize()}* |" + " |" * len(methods))
        for o in mine:
            if joint_type == "rigid":
                cells = []
                for m in methods:
                    right, n = type_accuracy([r for r in rows if r.object == o], m)
                    cells.append(f"{right}/{n} rigid")
            else:
                best = min((table[o][m] for m in methods if math.isfinite(table[o][m])),
                           default=math.nan)
                cells = [(f"**{table[o][m]:.1f}**" if table[o][m] == best else
                          _fmt(table[o][m])) for m in methods]
            lines.append(f"| {o.replace('_', ' ')} | " + " | ".join(cells) + " |")
    means = method_means(rows, methods)
    lines.append("| **mean** | " + " | ".join(_fmt(means[m]) for m in methods) + " |")
    if "ours" in methods and math.isfinite(means["ours"]) and means["ours"] > 0:
        ours = means["ours"]
        lines.append("| mean / ours | " + " | ".join(_fmt(means[m] / ours, 2) for m in methods)
                     + " |")
    acc = [type_accuracy(rows, m) for m in methods]
    lines.append("| joint type right | " + " | ".join(f"{a}/{n}" for a, n in acc) + " |")
    if any(r.type_true in ARTICULATED for r in rows):
        nv = [no_verdict(rows, m) for m in methods]
        lines.append("| no articulated verdict | " + " | ".join(f"{a}/{n}" for a, n in nv)
                     + " |")
    if any(r.type_true == "rigid" for r in rows):
        holds = [type_accuracy([r for r in rows if r.type_true == "rigid"], m) for m in methods]
        lines.append("| still holds rigid | " + " | ".join(f"{a}/{n}" for a, n in holds) + " |")
    for name, attr in (("time to the right type [s]", "type_s"),
                       ("time to within 10 deg [s]", "converge_s")):
        cells = []
        for m in methods:
            mine = [r for r in rows if r.method == m]
            if m not in OURS:
                cells.append("-")
                continue
            if attr == "converge_s":
                mine = [r for r in mine if r.type_true != "rigid"]
            t = metrics.summarise_times([getattr(r, attr) for r in mine])
            cells.append(f"{_fmt(t.median_s)} / {_fmt(t.p90_s)} / {t.never}")
        lines.append(f"| {name}: median / p90 / never | " + " | ".join(cells) + " |")
    return lines


def _type_table(rows: Sequence[Row], methods: Sequence[str]) -> list[str]:
    """Per object and method: final types right / demonstrations, the wrong verdicts named."""
    types = {r.object: r.type_true for r in rows}
    lines = ["| Object (true type) | " + " | ".join(LABELS[m] for m in methods) + " |",
             "| --- | " + " | ".join("---" for _ in methods) + " |"]
    for o in object_order(types):
        cells = []
        for m in methods:
            mine = [r for r in rows if r.object == o and r.method == m]
            right = sum(r.type_est == r.type_true for r in mine)
            wrong = sorted({r.type_est for r in mine if r.type_est != r.type_true})
            cells.append(f"{right}/{len(mine)}" + (f" ({', '.join(wrong)})" if wrong else ""))
        lines.append(f"| {o.replace('_', ' ')} ({types[o]}) | " + " | ".join(cells) + " |")
    return lines


def calibration_cells(rows: Sequence[Row], method: str) -> tuple[str, str]:
    """"covered/defined (percent)" of the axis direction and the revolute axis position."""
    mine = [r for r in rows if r.method == method]
    out = []
    for attr in ("axis_d2", "point_d2"):
        k, n = metrics.coverage([getattr(r, attr) for r in mine])
        out.append(f"{k}/{n} ({100.0 * k / n:.0f} %)" if n else "-")
    return out[0], out[1]


def _calibration_table(rows: Sequence[Row], methods: Sequence[str]) -> list[str]:
    ours = [m for m in methods if m in OURS]
    if not ours or not any(r.type_true in ARTICULATED for r in rows):
        return []
    lines = ["| 90 % interval covers the truth | " + " | ".join(LABELS[m] for m in ours) + " |",
             "| --- | " + " | ".join("---:" for _ in ours) + " |"]
    cells = [calibration_cells(rows, m) for m in ours]
    lines.append("| axis direction | " + " | ".join(c[0] for c in cells) + " |")
    lines.append("| revolute axis position | " + " | ".join(c[1] for c in cells) + " |")
    return lines


def _segment_table(segments: Sequence[SegmentRow]) -> list[str]:
    if not segments:
        return []
    methods = [m for m in LABELS if any(s.method == m for s in segments)]
    n_seg = max(s.segment for s in segments) + 1
    sources = sorted({s.source for s in segments})
    lines = ["| Contact phase | " + " | ".join(LABELS[m] for m in methods) + " |",
             "| --- | " + " | ".join("---:" for _ in methods) + " |"]
    for i in range(n_seg):
        cells = []
        for m in methods:
            mine = [s for s in segments if s.method == m and s.segment == i]
            right = sum(s.type_est == s.type_true for s in mine)
            cells.append(f"{_fmt(_mean(s.tangent_error_deg for s in mine))} deg, "
                         f"{right}/{len(mine)} types")
        lines.append(f"| {i + 1} | " + " | ".join(cells) + " |")
    cells = []
    for m in methods:
        demos = defaultdict(list)
        for s in segments:
            if s.method == m:
                demos[(s.object, s.participant, s.seed)].append(s.type_est == s.type_true)
        cells.append(f"{sum(all(v) for v in demos.values())}/{len(demos)}")
    lines.append("| every phase's type right | " + " | ".join(cells) + " |")
    how = ("the pipeline's model of each contact phase" if sources == ["segment"] else
           "the model held at each contact phase's last frame (the pipeline does not segment)")
    return ["Per contact phase: mean tangent error against that phase's joint over its rows, "
            f"and types right; scored by {how}.", "", *lines]


def _phase_table(evaluation: Evaluation, group: Group) -> list[str]:
    rows = [p for p in evaluation.phases if (p.split, p.variant, p.condition) == group]
    if not rows:
        return []
    lines = ["| Segmentation | onset error median / p90 [ms] | release error median / p90 [ms] "
             "| phases found | extra phases per min of free motion |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for m in (m for m in LABELS if any(p.method == m for p in rows)):
        mine = [p for p in rows if p.method == m]
        scored = [("online", [p.score for p in mine])]
        if all(p.dated is not None for p in mine):
            scored.append(("kept, dated", [p.dated for p in mine]))  # type: ignore[misc]
        for how, scores in scored:
            s = summarise_phases(scores)
            lines.append(f"| {LABELS[m]} ({how}) | {_fmt(s.onset_median_ms, 0)} / "
                         f"{_fmt(s.onset_p90_ms, 0)} | {_fmt(s.release_median_ms, 0)} / "
                         f"{_fmt(s.release_p90_ms, 0)} | {s.found}/{s.true} | "
                         f"{_fmt(s.extra_per_minute_free, 2)} |")
    return ["Online: the phase decided at each frame's own time (a tentative phase dropped later "
            "counts); kept, dated: the phases kept, dated back by at most the stated lag "
            "(docs/estimation.md#contact-phases).", "", *lines]


def _paired_means(rows: Sequence[Row], method: str, a: Group, b: Group) -> tuple[float, float,
                                                                                int]:
    """Mean tangent error of ``method`` in groups ``a`` and ``b`` over the demonstrations
    (object, participant, seed) both have, and how many those are."""
    def errors(g: Group) -> dict[tuple[str, int, int], float]:
        return {(r.object, r.participant, r.seed): r.tangent_error_deg for r in rows
                if r.method == method and (r.split, r.variant, r.condition) == g
                and math.isfinite(r.tangent_error_deg)}

    ea, eb = errors(a), errors(b)
    both = sorted(set(ea) & set(eb))
    return _mean(ea[k] for k in both), _mean(eb[k] for k in both), len(both)


def _comparison(rows: Sequence[Row], methods: Sequence[str],
                pairs: Sequence[tuple[str, Group, Group]], what: str) -> list[str]:
    """A line per ``(label, a, b)``: each method's mean error in ``a`` vs. ``b`` on the
    demonstrations both have."""
    if not pairs:
        return []
    lines = [f"| {what} | " + " | ".join(LABELS[m] for m in methods) + " |",
             "| --- | " + " | ".join("---:" for _ in methods) + " |"]
    for label, a, b in pairs:
        cells = []
        for m in methods:
            ma, mb, n = _paired_means(rows, m, a, b)
            cells.append(f"{_fmt(ma)} vs {_fmt(mb)} ({mb - ma:+.1f}, n = {n})" if n else "-")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def _per_minute(scores: Sequence[PhaseScore | None]) -> str:
    """Extra (false) phases per minute of stream, or "-" without segmentation."""
    scored = [s for s in scores if s is not None]
    if not scored:
        return "-"
    return f"{sum(s.extra for s in scored) / (sum(s.duration_s for s in scored) / 60):.2f}"


def _free_table(free: Sequence[FreeRow]) -> list[str]:
    if not free:
        return []
    lines = ["| Free hand stream | streams | minutes | frames with an articulated verdict > 0.5 "
             "| streams with one | final types | false contact phases per minute (online / kept) "
             "| kept phases with an articulated verdict > 0.5 |",
             "| --- | ---: | ---: | ---: | ---: | --- | ---: | ---: |"]
    for m in (m for m in LABELS if any(f.method == m for f in free)):
        mine = [f for f in free if f.method == m]
        minutes = sum(f.duration_s for f in mine) / 60.0
        frames = sum(f.frames for f in mine)
        art = sum(f.articulated_frames for f in mine)
        finals = ", ".join(f"{t} {sum(f.final_type == t for f in mine)}"
                           for t in sorted({f.final_type for f in mine}))
        false = " / ".join(_per_minute([getattr(f, attr) for f in mine])
                           for attr in ("phases", "dated"))
        lines.append(f"| {LABELS[m]} | {len(mine)} | {minutes:.1f} | {art}/{frames} | "
                     f"{sum(f.articulated_frames > 0 for f in mine)}/{len(mine)} | {finals} | "
                     f"{false} | {sum(f.articulated_phases for f in mine)} |")
    return lines


def report_markdown(evaluation: Evaluation, methods: Sequence[str], title: str,
                    data: str = "") -> str:
    """The whole report: a section per (split, variant, condition), then the comparisons
    (whole vs. cut, conditions vs. plain) and the free hand stream."""
    rows = evaluation.rows
    out = [f"# {title}", ""]
    if data:
        out += [data, ""]
    out += ["Tangent error in degrees (mean over participants and seeds), as in the paper's "
            "Table II; the mean is over objects (still holds have no tangent error and are "
            "counted by type). Types are the final model's (for ours: unknown and "
            "disconnected are verdicts of their own). Times from the grasp of the final joint "
            "until the type is right / the error is below 10 deg for good; never = not at "
            "the end. Definitions: docs/evaluation.md.", ""]
    for g in groups(rows):
        mine = [r for r in rows if (r.split, r.variant, r.condition) == g]
        out += [f"## {group_title(g)}", "", *_error_table(mine, methods), "",
                "Final types per object (right / demonstrations; wrong verdicts named):", "",
                *_type_table(mine, methods), ""]
        calibration = _calibration_table(mine, methods)
        if calibration:
            out += ["Calibration of the published covariance, where the final type is the "
                    "true one (docs/evaluation.md#calibration; goal: 85-95 %):", "",
                    *calibration, ""]
        seg = _segment_table([s for s in evaluation.segments
                              if (s.split, s.variant, s.condition) == g])
        if seg:
            out += [*seg, ""]
        phases = _phase_table(evaluation, g)
        if phases:
            out += [*phases, ""]
    gs = groups(rows)
    whole = [(f"{s}" + ("" if c == "plain" else f", {c}"), (s, WHOLE_CUT, c), (s, v, c))
             for s, v, c in gs if v == "whole" and (s, WHOLE_CUT, c) in gs]
    if whole:
        out += ["## Whole demonstrations vs. the same cut at grasp and release", "",
                "Mean tangent error, cut vs. whole (whole minus cut, demonstrations in both):",
                "", *_comparison(rows, methods, whole, "split: cut vs. whole"), ""]
    conditions = [(f"{s}, {v}: {c}", (s, v, "plain"), (s, v, c)) for s, v, c in gs
                  if c != "plain" and (s, v, "plain") in gs]
    if conditions:
        out += ["## Conditions vs. plain on the same demonstrations", "",
                "Mean tangent error of our methods, plain vs. the condition (condition minus "
                "plain). The baselines are given the manipulating hand's detections in every "
                "condition (docs/evaluation.md#conditions) and are not compared.", "",
                *_comparison(rows, [m for m in methods if m in OURS], conditions,
                             "split, variant: condition"), ""]
    free = _free_table(evaluation.free)
    if free:
        out += ["## Free hand stream (60 s, nothing touched)", "", *free, ""]
    return "\n".join(out).rstrip() + "\n"


def table_markdown(rows: Sequence[Row], methods: Sequence[str], title: str) -> str:
    """The report of ``rows`` alone (no segments, phases or free streams)."""
    return report_markdown(Evaluation(rows=list(rows)), methods, title)


def _write_csv(items: Sequence[Any], path: Path) -> None:
    names = [f.name for f in fields(type(items[0]))]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=names)
        w.writeheader()
        for item in items:
            w.writerow({k: getattr(item, k) for k in names})


def write_csv(rows: Sequence[Row], path: Path) -> None:
    """Every field of every row, one line each."""
    _write_csv(rows, path)


def _free_csv(free: Sequence[FreeRow], path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["participant", "seed", "method", "frames", "articulated_frames",
                    "final_type", "duration_s", "contact_phases", "kept_phases",
                    "articulated_phases"])
        for r in free:
            w.writerow([r.participant, r.seed, r.method, r.frames, r.articulated_frames,
                        r.final_type, r.duration_s, "" if r.phases is None else r.phases.extra,
                        "" if r.dated is None else r.dated.extra, r.articulated_phases])


def write_report(rows: Sequence[Row] | Evaluation, methods: Sequence[str], out_dir: Path,
                 title: str, histories: Sequence[History] = (), data: str = "") -> list[Path]:
    """Write the report, the CSVs and the figures into ``out_dir``; returns the files written.

    ``rows``: an :class:`Evaluation` (everything) or its rows; ``histories`` (of our methods,
    when ``rows`` are just rows) add the convergence figures. ``data`` (default: from the rows)
    says in each figure's caption which demonstrations it shows. Files: ``table<stem>.md``,
    ``results<stem>.csv``, ``segments<stem>.csv`` and ``free<stem>.csv`` when there are any, and
    per group ``tangent_error<group stem>.png`` and ``convergence<group stem>.png``.
    """
    from services.evaluation import figures

    ev = rows if isinstance(rows, Evaluation) else Evaluation(rows=list(rows),
                                                               histories=list(histories))
    out_dir.mkdir(parents=True, exist_ok=True)
    gs = groups(ev.rows)
    run = stem([g[0] for g in gs], [g[1] for g in gs], [g[2] for g in gs])
    data = data or figures.describe_data(ev.rows)
    written = [out_dir / f"table{run}.md", out_dir / f"results{run}.csv"]
    written[0].write_text(report_markdown(ev, methods, title, data))
    write_csv(ev.rows, written[1])
    if ev.segments:
        written.append(out_dir / f"segments{run}.csv")
        _write_csv(ev.segments, written[-1])
    if ev.free:
        written.append(out_dir / f"free{run}.csv")
        _free_csv(ev.free, written[-1])
    for g in gs:
        if g[1] == WHOLE_CUT:
            continue
        name = stem([g[0]], [g[1]], [g[2]])
        mine = [r for r in ev.rows if (r.split, r.variant, r.condition) == g]
        caption = data if len(gs) == 1 else f"{figures.describe_data(mine)} ({group_title(g)})"
        written.append(figures.save(figures.tangent_error_figure(mine, methods, caption),
                                    out_dir / f"tangent_error{name}.png"))
        hs = [h for h in ev.histories if (h.split, h.variant, h.condition) == g]
        if hs:
            written.append(figures.save(figures.convergence_figure(hs, caption),
                                        out_dir / f"convergence{name}.png"))
    return written
