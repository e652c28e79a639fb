"""``python -m bench.run NAME|all`` (``make bench``, ``handkse bench NAME``): run benchmarks."""

from __future__ import annotations

import importlib
import sys

from services.common.progress import Progress

BENCHMARKS = ("protocol", "tracker", "kinematics", "detector", "robot", "load", "faults",
              "multihost", "view")


def run(name: str) -> None:
    """Run one benchmark or all of them, showing which runs and how many are left, then
    rewrite ``bench/results/README.md``."""
    names = BENCHMARKS if name == "all" else (name,)
    for n in names:
        if n not in BENCHMARKS:
            raise SystemExit(f"unknown benchmark {n!r}; choose from {list(BENCHMARKS)} or all")
    ran = []
    with Progress(len(names)) as progress:
        for n in names:
            progress.step(f"benchmark {n}")
            try:
                module = importlib.import_module(f"bench.{n}")
            except ModuleNotFoundError as exc:
                progress.note(f"skipping {n}: {exc}")
                continue
            with progress.redirect_stdout():  # the benchmark's own output goes above the bar
                module.main()
            ran.append(n)
        progress.done(f"ran {len(ran)} of {len(names)} benchmarks: {', '.join(ran) or 'none'}")
    from bench.summary import main as summarise

    summarise()


if __name__ == "__main__":
    run(sys.argv[1] if len(sys.argv) > 1 else "all")
