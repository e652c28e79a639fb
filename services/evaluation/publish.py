"""Copying a run's report files to the published results (``--publish``: bench/results/...)."""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[2] / "bench" / "results"


def publish(paths: Iterable[Path], folder: Path) -> Path:
    """Copy every existing file of ``paths`` into ``folder`` (created), print where, and return
    it. A published result replaces the older one of the same name."""
    folder.mkdir(parents=True, exist_ok=True)
    for path in paths:
        if path.exists():
            shutil.copy(path, folder / path.name)
    print(f"copied to {folder}")
    return folder


__all__ = ["RESULTS", "publish"]
