"""Benchmark helpers: machine description, percentiles, result files under bench/results/."""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> dict[str, Any]:
    """What ran the benchmark: CPU, cores, memory, Python and key package versions."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gib = None
    try:
        pages = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        mem_gib = round(pages / 2**30, 1)
    except (ValueError, OSError):
        pass
    versions = {}
    for pkg in ("eclipse-zenoh", "numpy", "scipy", "msgpack", "onnxruntime", "mujoco"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            versions[pkg] = metadata.version(pkg)
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, check=False, cwd=RESULTS.parent).stdout.strip()
    except OSError:
        commit = ""
    load = [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None
    return {"cpu": cpu, "cores": os.cpu_count(), "memory_gib": mem_gib, "load_avg_1_5_15": load,
            "os": platform.platform(), "python": sys.version.split()[0], "packages": versions,
            "commit": commit, "date": time.strftime("%Y-%m-%d %H:%M:%S %Z")}


def percentiles_ms(seconds: Sequence[float] | np.ndarray) -> dict[str, float]:
    a = np.asarray(seconds, float) * 1e3
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
            "mean": float(a.mean()), "max": float(a.max()), "n": int(a.size)}


def write_result(name: str, result: dict[str, Any]) -> Path:
    """Write ``bench/results/<name>.json`` (with the machine) and print a summary."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    doc = {"benchmark": name, "machine": machine(), "result": result}
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    print(f"written {path}")
    return path


def update_result(name: str, key: str, value: Any) -> Path:
    """Replace ``result[key]`` of ``bench/results/<name>.json`` with ``value`` and keep the rest
    (and the machine it names, which described the rest; ``value`` should describe its own)."""
    path = RESULTS / f"{name}.json"
    doc = json.loads(path.read_text()) if path.exists() else {"benchmark": name,
                                                              "machine": machine(), "result": {}}
    doc["result"][key] = value
    path.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(value, indent=2))
    print(f"updated {key} in {path}")
    return path
