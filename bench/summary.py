"""Render every ``bench/results/*.json`` into ``bench/results/README.md``."""

from __future__ import annotations

import json
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
                  f"{m.get('date')}, load average {m.get('load_avg_1_5_15')} at the start.",
                  "", "| metric | value |", "| --- | --- |"]
        rows: list[tuple[str, str]] = []
        _flatten("", doc.get("result", {}), rows)
        lines += [f"| {k} | {v} |" for k, v in rows]
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    out = RESULTS / "README.md"
    out.write_text(render())
    print(f"written {out}")


if __name__ == "__main__":
    main()
