"""``python -m bench.run NAME|all`` (``make bench``, ``handkse bench NAME``): run benchmarks."""

from __future__ import annotations

import importlib
import sys

BENCHMARKS = ("protocol", "tracker", "kinematics", "detector", "robot", "load", "faults",
              "multihost", "view")


def run(name: str) -> None:
    names = BENCHMARKS if name == "all" else (name,)
    for n in names:
        if n not in BENCHMARKS:
            raise SystemExit(f"unknown benchmark {n!r}; choose from {list(BENCHMARKS)} or all")
        try:
            module = importlib.import_module(f"bench.{n}")
        except ModuleNotFoundError as exc:
            print(f"skipping {n}: {exc}")
            continue
        print(f"== {n}", flush=True)
        module.main()
    from bench.summary import main as summarise

    summarise()


if __name__ == "__main__":
    run(sys.argv[1] if len(sys.argv) > 1 else "all")
