"""Render every ``bench/results/*.json`` into ``bench/results/README.md``."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench.common import RESULTS


def _flatten(prefix: str, value: Any, out: list[tuple[str, str]]) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten(f"{prefix}.{k}" if prefix else str(k), v, out)
    elif isinstance(value, float):
        out.append((prefix, f"{value:.4g}"))
    elif isinstance(value, str) and value.startswith("{"):
        try:
            _flatten(prefix, json.loads(value), out)
        except json.JSONDecodeError:
            out.append((prefix, value))
    else:
        out.append((prefix, str(value)))


def render(results: Path = RESULTS) -> str:
    lines = ["# Benchmark results", "",
             "Written by `make bench` (`python -m bench.run all`); one section per benchmark, "
             "with the machine it ran on. Timings on shared 2-core VMs vary by tens of percent "
             "between runs.", ""]
    for path in sorted(results.glob("*.json")):
        doc = json.loads(path.read_text())
        m = doc.get("machine", {})
        lines += [f"## {doc.get('benchmark', path.stem)}", "",
                  f"Machine: {m.get('cpu')}, {m.get('cores')} cores, {m.get('memory_gib')} GiB, "
                  f"{m.get('os')}, Python {m.get('python')}, commit {m.get('commit')}, "
                  f"{m.get('date')}, load average {m.get('load_avg_1_5_15')} (1/5/15 min) "
                  "when the results were written.",
                  ""]
        renderer = RENDERERS.get(str(doc.get("benchmark")))
        if renderer is not None:
            lines += renderer(doc.get("result", {}))
            continue
        lines += ["| metric | value |", "| --- | --- |"]
        rows: list[tuple[str, str]] = []
        _flatten("", doc.get("result", {}), rows)
        lines += [f"| {k} | {v} |" for k, v in rows]
        lines.append("")
    return "\n".join(lines)


def _ms(p: dict[str, Any] | None) -> str:
    return "-" if not p else f"{p['p50']:.1f} / {p['p99']:.1f} / {p['max']:.0f}"


def _render_load(result: dict[str, Any]) -> list[str]:
    """Tables for ``bench/load.py``: one row per scenario (the details stay in load.json)."""
    scenarios: dict[str, Any] = result.get("scenarios", {})
    lines = ["| scenario | landmarks sent | dropped | frames without a body | camera->model [ms] "
             "p50 / p99 / max | camera->hand body [ms] | one router hop [ms] | goal met |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    for name, sc in scenarios.items():
        lat = sc.get("latency_ms", {})
        met = "yes" if all(sc.get("goal", {}).values()) else "no: " + ", ".join(
            k for k, v in sc.get("goal", {}).items() if not v)
        lines.append(f"| {name} | {sc.get('landmarks_sent')} | {sc.get('dropped')} | "
                     f"{sc.get('frames_without_body', '-')} | "
                     f"{_ms(lat.get('camera_to_model'))} | {_ms(lat.get('camera_to_hand_body'))} | "
                     f"{_ms(lat.get('camera_to_landmarks_one_hop'))} | {met} |")
    lines += ["", "CPU in percent of one core over each run, and the services' own per-stage "
              "latency (p50 / p99 ms of their last 2000 steps, from `handkse stats`):", "",
              "| scenario | CPU % | CPU ms per frame | tracker step [ms] | kinematics update [ms] | "
              "load avg before -> after |",
              "| --- | --- | --- | --- | --- | --- |"]
    for name, sc in scenarios.items():
        cpu = ", ".join(f"{k} {v:g}" for k, v in sc.get("cpu_percent_of_one_core", {}).items())
        if "cpu_total_percent" in sc:
            cpu += f" (total {sc['cpu_total_percent']:g} of {sc.get('cpu_available_percent')})"
        stages: dict[str, list[str]] = {"tracker": [], "kinematics": []}
        for rig, r in sc.get("per_rig", {}).items():
            for service, stage in (("tracker", "step"), ("kinematics", "update")):
                p = r.get("service_stats", {}).get(service, {}).get("latency_ms", {}).get(stage)
                if p:
                    stages[service].append(f"{rig}: {p['p50']:.2f} / {p['p99']:.1f}")
        load = sc.get("load_avg_1_5_15", {})
        per_frame = ", ".join(f"{k} {v:g}" for k, v in sc.get("cpu_ms_per_frame", {}).items())
        lines.append(f"| {name} | {cpu} | {per_frame or '-'} | {'; '.join(stages['tracker'])} | "
                     f"{'; '.join(stages['kinematics'])} | {load.get('before')} -> "
                     f"{load.get('after')} |")
    lines += ["", f"Goal: {result.get('goal')}. Method: {result.get('method')}."]
    if result.get("findings"):
        lines += ["", f"Findings: {result['findings']}"]
    lines.append("")
    if result.get("flood"):
        lines += _render_flood(result["flood"])
    return lines


def _render_flood(flood: dict[str, Any]) -> list[str]:
    """The flood of ``bench/flood.py``: one row per phase."""
    m = flood.get("machine", {})
    rate = flood.get("flood", {})
    lines = [f"### Flood: {rate.get('rate_per_s'):g} landmark messages/s for "
             f"{rate.get('seconds'):g} s", "",
             f"Run on {m.get('cpu')}, {m.get('cores')} cores, commit {m.get('commit')}, "
             f"{m.get('date')}, load average {flood.get('load_avg_1_5_15')} (before -> after).",
             "", "| phase | sent (flood) | tracker received / dropped / published | kinematics "
             "received / dropped / published | silent losses | stats [ms] p50 / p99 / max | "
             "tokens lost | model = clean run |",
             "| --- | ---: | ---: | ---: | ---: | ---: | --- | --- |"]
    for name, ph in flood.get("phases", {}).items():
        c = ph.get("counts", {})
        worst = max((st.get("ms", {}).get("max", 0.0) for st in ph.get("stats", {}).values()),
                    default=0.0)
        p50 = max((st.get("ms", {}).get("p50", 0.0) for st in ph.get("stats", {}).values()),
                  default=0.0)
        p99 = max((st.get("ms", {}).get("p99", 0.0) for st in ph.get("stats", {}).values()),
                  default=0.0)
        model = ph.get("model")
        same = "-" if model is None else ("yes" if model.get("equal") else
                                          f"no ({model.get('updates')} of "
                                          f"{model.get('reference_updates')} updates)")
        lines.append(f"| {name} | {c.get('landmarks_sent')} ({c.get('flood_sent')}) | "
                     f"{c.get('tracker_received')} / {c.get('tracker_dropped')} / "
                     f"{c.get('tracker_published')} | {c.get('kinematics_received')} / "
                     f"{c.get('kinematics_dropped')} / {c.get('kinematics_published')} | "
                     f"{sum(ph.get('silent_losses', {}).values())} | {p50:.1f} / {p99:.1f} / "
                     f"{worst:.0f} | {sum(ph.get('tokens_lost', {}).values())} | {same} |")
    goal = flood.get("goal", {})
    lines += ["", "Goals: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in goal.items())
              + ".", ""]
    return lines


RENDERERS: dict[str, Callable[[dict[str, Any]], list[str]]] = {"load": _render_load}


def main() -> None:
    out = RESULTS / "README.md"
    out.write_text(render())
    print(f"written {out}")


if __name__ == "__main__":
    main()
