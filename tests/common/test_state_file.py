"""State files: atomic, versioned, written off the hot path, never fatal when unreadable."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from services.common.state_file import StateFile, StateFileError


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


def test_a_folder_that_cannot_hold_the_file_is_refused_at_start(tmp_path: Path) -> None:
    with pytest.raises(StateFileError, match="does not exist"):
        StateFile(tmp_path / "missing" / "s.state", 1)
    (tmp_path / "plain").write_text("a file, not a folder")
    with pytest.raises(StateFileError, match="does not exist"):
        StateFile(tmp_path / "plain" / "s.state", 1)
    with pytest.raises(StateFileError, match="cannot write"):
        StateFile(Path("/proc/handkse-test.state"), 1)  # not writable, even for root


def test_a_stale_temporary_file_is_removed_at_start(tmp_path: Path) -> None:
    path = tmp_path / "s.state"
    StateFile(path, 1).save({"a": 1})
    (tmp_path / "s.state.tmp").write_bytes(b"half a docu")  # a writer killed mid-write
    state = StateFile(path, 1)
    assert not (tmp_path / "s.state.tmp").exists()
    assert state.load() == {"a": 1}


def test_write_failures_are_counted_and_logged_rarely(tmp_path: Path,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "s.state"
    state = StateFile(path, 1)
    path.mkdir()  # the rename onto a folder fails from now on
    with caplog.at_level(logging.ERROR, logger="services.common.state_file"):
        for i in range(20):
            state.save_later({"i": i})
            assert state.flush()
    assert state.write_errors == 20
    assert len([r for r in caplog.records if "cannot write" in r.getMessage()]) == 1
