"""State files: atomic, versioned, written off the hot path, never fatal when unreadable."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.common.state_file import StateFile


def test_the_newest_document_reaches_the_disk(tmp_path: Path) -> None:
    state = StateFile(tmp_path / "s.state", version=3)
    for i in range(200):
        state.save_later({"i": i, "x": np.full(4, float(i))})
    assert state.flush()
    doc = StateFile(tmp_path / "s.state", version=3).load()
    assert doc is not None and doc["i"] == 199
    np.testing.assert_array_equal(doc["x"], np.full(4, 199.0))
    assert not (tmp_path / "s.state.tmp").exists()
    state.save({"i": -1})  # a direct save is ordered after the pending ones
    assert state.load() == {"i": -1}


def test_unreadable_or_foreign_files_are_ignored(tmp_path: Path) -> None:
    path = tmp_path / "s.state"
    assert StateFile(path, 1).load() is None  # absent
    path.write_bytes(b"\x00garbage")
    assert StateFile(path, 1).load() is None
    StateFile(path, 2).save({"a": 1})
    assert StateFile(path, 1).load() is None  # another version
    assert StateFile(path, 2).load() == {"a": 1}
    StateFile(None, 1).save_later({"a": 1})  # disabled: nothing happens
    assert StateFile(None, 1).flush()
