"""Figures of ``handkse robot-trials``: the force of every simulated trial, and the traces' file.

``force_trials.png``: small multiples, one panel per demonstration (rows: objects, columns:
seeds), a line per method with the measured force magnitude over time; a marker at the end of
each line says how the trial ended (legend), a trial refused before it moved is named in the
panel, and the force limit is drawn on top of everything, above the legend-free plot area.
``force_key.png``: the same for one key demonstration, larger (the paper's Fig. 6).
``traces.json`` keeps the force traces beside ``results.csv``, so the figures can be redrawn
without rerunning the trials: ``python -m services.evaluation.robot_plots DIR``.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from services.evaluation.robot_trial_rows import LABELS, METHODS, OBJECTS, PARTICIPANT, TrialRow

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

Trace = Mapping[str, Sequence[float]]  # "t_s" (s), "force_n" (N), "stop_s" (0 or 1 abort time)
TraceKey = tuple[str, int, str]        # (object, seed, method)

COLORS = {"ours": "#2b59c3", "regal": "#d9509b", "screwmimic": "#1f9e89"}
LIMIT_COLOR = "#c0392b"
DPI = 150
# How a trial ended -> (marker, legend text). A trial that ran and did not succeed ended with
# the safety check's reason (services/robot_bridge/safety.py).
ENDINGS = {
    "success": ("o", "reached 180 deg (success)"),
    "short": ("s", "stopped short of 180 deg"),
    "force_limit": ("v", "aborted: force over the limit"),
    "torque_limit": ("D", "aborted: wrist torque over its limit"),
    "torque_saturation": ("X", "aborted: joint torques at the arm's limits"),
    "tracking_error": ("P", "aborted: tracking error"),
}
OTHER_ABORT = ("*", "aborted: other reason")


def ending(row: TrialRow) -> str:
    """The key of :data:`ENDINGS` for a trial that moved."""
    if row.success:
        return "success"
    if row.reason == "ok":
        return "short"
    return row.reason if row.reason in ENDINGS else "other"


def _marker(key: str) -> tuple[str, str]:
    return ENDINGS.get(key, OTHER_ABORT)


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _draw_trials(ax: Axes, rows: Sequence[TrialRow], traces: Mapping[TraceKey, Trace],
                 force_limit_n: float, used: set[str], note_size: float) -> None:
    """One demonstration's trials in ``ax``; adds the ending keys drawn to ``used``."""
    refused = []
    for r in rows:
        tr = traces.get((r.object, r.seed, r.method))
        color = COLORS.get(r.method, "#444444")
        if tr is None or len(tr["t_s"]) == 0:
            refused.append(r)
            continue
        t, f = list(tr["t_s"]), list(tr["force_n"])
        ax.plot(t, f, color=color, linewidth=1.4, zorder=3)
        key = ending(r)
        stop = list(tr.get("stop_s", []))
        if stop:  # mark the force at the moment of the abort, not at the end of the trace
            k = min(range(len(t)), key=lambda i: abs(t[i] - stop[0]))
            at = (t[k], f[k])
        else:
            at = (t[-1], f[-1])
        marker, _ = _marker(key)
        ax.plot(*at, marker=marker, color=color, markersize=7, markeredgecolor="black",
                markeredgewidth=0.6, linestyle="none", zorder=4)
        used.add(key)
    # The limit goes over the lines and markers; the plot leaves headroom above it for the notes.
    ax.axhline(force_limit_n, color=LIMIT_COLOR, linestyle="--", linewidth=1.3, zorder=10)
    ax.set_ylim(0, force_limit_n * 1.3)
    for i, r in enumerate(refused):
        ax.text(0.02, 0.97 - 0.085 * i, f"{LABELS.get(r.method, r.method)}: refused "
                f"({r.reason.replace('_', ' ')})", transform=ax.transAxes, ha="left",
                va="top", fontsize=note_size, color=COLORS.get(r.method, "#444444"))


def _legend(fig: Figure, methods: Sequence[str], used: set[str], force_limit_n: float,
            ncols: int) -> None:
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=COLORS.get(m, "#444444"), linewidth=2,
                      label=LABELS.get(m, m)) for m in methods]
    handles.append(Line2D([], [], color=LIMIT_COLOR, linestyle="--", linewidth=1.3,
                          label=f"force limit {force_limit_n:.0f} N"))
    order = [*ENDINGS, "other"]
    for key in (k for k in order if k in used):
        marker, text = _marker(key)
        handles.append(Line2D([], [], marker=marker, color="#999999", markeredgecolor="black",
                              markeredgewidth=0.6, linestyle="none", markersize=7, label=text))
    fig.legend(handles=handles, loc="lower center", ncols=ncols, fontsize=8.5, frameon=False,
               bbox_to_anchor=(0.5, 0.0))


def _seeds(rows: Sequence[TrialRow]) -> list[int]:
    return sorted({r.seed for r in rows})


def _caption_data(rows: Sequence[TrialRow]) -> str:
    seeds = _seeds(rows)
    return (f"Simulated Franka Panda (MuJoCo) turning each object 180 deg in 6 s along each "
            f"method's estimate from a synthetic demonstration by participant {PARTICIPANT} "
            f"(seeds {seeds[0]}-{seeds[-1]}); {len(rows)} trials. Force: the magnitude of the "
            "measured end-effector force; the trial aborts when it exceeds the limit.")


def trials_figure(rows: Sequence[TrialRow], traces: Mapping[TraceKey, Trace],
                  force_limit_n: float, title: str) -> Figure:
    """Every trial: a panel per (object, seed), a line per method."""
    plt = _pyplot()
    objects = [o for o in OBJECTS if any(r.object == o for r in rows)]
    objects += sorted({r.object for r in rows} - set(objects))
    seeds = _seeds(rows)
    methods = [m for m in METHODS if any(r.method == m for r in rows)]
    fig, axes = plt.subplots(len(objects), len(seeds), squeeze=False, sharex=True, sharey=True,
                             figsize=(2.9 * len(seeds) + 0.8, 2.5 * len(objects) + 1.9), dpi=DPI)
    used: set[str] = set()
    for i, obj in enumerate(objects):
        for j, seed in enumerate(seeds):
            ax = axes[i][j]
            mine = [r for r in rows if r.object == obj and r.seed == seed]
            _draw_trials(ax, mine, traces, force_limit_n, used, note_size=7)
            ok = sum(r.success for r in mine)
            ax.set_title(f"{obj.replace('_', ' ')}, demonstration {seed}: {ok}/{len(mine)} ok",
                         fontsize=9)
            ax.grid(alpha=0.3)
            if j == 0:
                ax.set_ylabel("|F| [N]")
            if i == len(objects) - 1:
                ax.set_xlabel("time [s]")
    fig.suptitle(title, fontsize=11, fontweight="bold")
    _legend(fig, methods, used, force_limit_n, ncols=min(len(methods) + 1 + len(used), 5))
    caption = textwrap.fill(_caption_data(rows) + " Markers: how each trial ended; "
                            "\"refused\": stopped by a check before moving.",
                            int(15.5 * fig.get_figwidth()))
    height = fig.get_figheight()
    fig.text(0.01, 1.0 - 0.42 / height, caption, ha="left", va="top", fontsize=8.5)
    fig.tight_layout(rect=(0, 0.6 / height, 1, 1 - 0.5 / height), h_pad=0.8)
    return fig


def demonstration_figure(rows: Sequence[TrialRow], traces: Mapping[TraceKey, Trace],
                         force_limit_n: float, obj: str, seed: int) -> Figure:
    """One demonstration's trials, large (the paper's Fig. 6)."""
    plt = _pyplot()
    mine = [r for r in rows if r.object == obj and r.seed == seed]
    fig, ax = plt.subplots(figsize=(8, 4.6), dpi=DPI)
    used: set[str] = set()
    _draw_trials(ax, mine, traces, force_limit_n, used, note_size=8.5)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("|F| [N]")
    ax.grid(alpha=0.3)
    ax.set_title(f"{obj.replace('_', ' ')}, participant {PARTICIPANT} demonstration {seed}: "
                 "force during articulation", fontsize=11)
    _legend(fig, [r.method for r in mine], used, force_limit_n, ncols=3)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    return fig


def save(fig: Figure, path: Path) -> Path:
    fig.savefig(path)
    _pyplot().close(fig)
    return path


def write_traces(traces: Mapping[TraceKey, Trace], path: Path) -> Path:
    """``traces.json``: ``{"object/seed/method": {"t_s": [...], "force_n": [...],
    "stop_s": [...]}}``, times to 1 ms and forces to 0.01 N."""
    doc = {f"{o}/{s}/{m}": {"t_s": [round(float(x), 3) for x in tr["t_s"]],
                            "force_n": [round(float(x), 2) for x in tr["force_n"]],
                            "stop_s": [round(float(x), 3) for x in tr.get("stop_s", [])]}
           for (o, s, m), tr in traces.items()}
    path.write_text(json.dumps(doc, separators=(",", ":")) + "\n")
    return path


def read_traces(path: Path) -> dict[TraceKey, Trace]:
    """The traces of :func:`write_traces`."""
    out: dict[TraceKey, Trace] = {}
    for key, tr in json.loads(path.read_text()).items():
        o, s, m = key.split("/")
        out[(o, int(s), m)] = tr
    return out


def read_rows(path: Path) -> list[TrialRow]:
    """The rows of ``results.csv``, typed as :class:`TrialRow`."""
    types = {f.name: f.type for f in dataclasses.fields(TrialRow)}
    rows = []
    with open(path, newline="") as f:
        for raw in csv.DictReader(f):
            values: dict[str, Any] = {}
            for name, kind in types.items():
                text = raw[name]
                values[name] = (text == "True" if kind in (bool, "bool") else
                                int(text) if kind in (int, "int") else
                                float(text) if kind in (float, "float") else text)
            rows.append(TrialRow(**values))
    return rows


def write_figures(rows: Sequence[TrialRow], traces: Mapping[TraceKey, Trace], out: Path,
                  force_limit_n: float, title: str, key_seed: int) -> list[Path]:
    """``force_trials.png`` and ``force_key.png`` (key, ``key_seed``) in ``out``; returns the
    files written."""
    written = [save(trials_figure(rows, traces, force_limit_n, title), out / "force_trials.png")]
    if any(r.object == "key" and r.seed == key_seed for r in rows):
        written.append(save(demonstration_figure(rows, traces, force_limit_n, "key", key_seed),
                            out / "force_key.png"))
    return written


def main(argv: list[str] | None = None) -> int:
    """Redraw the figures of a report folder from its ``results.csv`` and ``traces.json``."""
    parser = argparse.ArgumentParser(prog="python -m services.evaluation.robot_plots",
                                     description=main.__doc__)
    parser.add_argument("folder", type=Path)
    parser.add_argument("--force-limit", type=float, default=70.0, help="N (default 70)")
    parser.add_argument("--key-seed", type=int, default=0)
    args = parser.parse_args(argv)
    rows = read_rows(args.folder / "results.csv")
    traces = read_traces(args.folder / "traces.json")
    table = args.folder / "table.md"
    title = (table.read_text().splitlines()[0].lstrip("# ") if table.is_file()
             else f"Robot trials in simulation, force limit {args.force_limit:.0f} N")
    for path in write_figures(rows, traces, args.folder, args.force_limit, title, args.key_seed):
        print(f"written {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
