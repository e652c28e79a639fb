"""A service's state on disk: one msgpack document, replaced atomically, restored at start.

Used by the kinematics service (the estimator) and the tracker (the hand body model), so a
service that is killed and restarted continues where it was. The document is a map with a
``version``; a file that is unreadable or of another version is ignored with a warning (the
service then starts fresh), never fatal.

:meth:`StateFile.save_later` takes the write off a service's hot path: a writer thread packs and
writes the newest document handed to it (documents that were superseded before it got to them
are skipped), so a crash loses at most the updates of the last write (about 0.5 ms).

Durability: each write goes to ``<name>.tmp``, is fsync'd, renamed over the file, and the folder
is fsync'd, so a power cut leaves the old or the new document, never a torn one. At start the
folder must exist and be writable (:class:`StateFileError` otherwise: a service refuses to start
rather than run for hours without the persistence it was asked for), and a ``.tmp`` left by a
killed writer is removed. Write errors are logged at most once per ``ERROR_LOG_PERIOD_S`` with a
count. What a document *means* is validated by its owner when it restores it.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from pathlib import Path
from typing import Any

from services.common.protocol import ProtocolError, pack_document, unpack_document

log = logging.getLogger(__name__)

ERROR_LOG_PERIOD_S = 10.0


class StateFileError(RuntimeError):
    """The state file cannot be kept where it was asked for; the text names the path and why."""


def _temporary(path: Path) -> Path:
    return path.with_name(path.name + ".tmp")


def write_atomically(path: Path, data: bytes) -> None:
    """Replace ``path`` with ``data`` durably: a reader, a restart or a power cut sees the old or
    the new content, never a partial file."""
    tmp = _temporary(path)
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


def check_folder(path: Path) -> None:
    """Raise :class:`StateFileError` unless ``path``'s folder exists and a file can be written
    there; remove a stale ``.tmp`` of ``path`` (left by a writer killed mid-write)."""
    folder = path.parent
    if not folder.is_dir():
        raise StateFileError(f"state file {path}: folder {folder} does not exist (create it, or "
                             "pass another --state-file)")
    probe = folder / f".{path.name}.probe-{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise StateFileError(f"state file {path}: cannot write in {folder} ({exc.strerror}); "
                             "fix its permissions or pass another --state-file") from exc
    stale = _temporary(path)
    if stale.exists():
        log.warning("removing %s, left by a writer that was stopped mid-write", stale)
        stale.unlink()


class StateFile:
    """``save(doc)`` / ``load()`` of one versioned document at ``path`` (None: disabled)."""

    def __init__(self, path: Path | None, version: int) -> None:
        """Raises :class:`StateFileError` when ``path``'s folder is missing or not writable."""
        if path is not None:
            check_folder(path)
        self.path = path
        self.version = version
        self.write_errors = 0
        self._last_error_log = -math.inf
        self._cond = threading.Condition()
        self._pending: dict[str, Any] | None = None
        self._writing = False
        self._writer: threading.Thread | None = None

    def save(self, doc: dict[str, Any]) -> None:
        """Write ``doc`` now (after any pending :meth:`save_later` document)."""
        if self.path is not None:
            self.flush()
            write_atomically(self.path, pack_document({"version": self.version, **doc}))

    def save_later(self, doc: dict[str, Any]) -> None:
        """Hand ``doc`` (which must not be mutated afterwards) to the writer thread."""
        if self.path is None:
            return
        with self._cond:
            self._pending = doc
            if self._writer is None:
                self._writer = threading.Thread(target=self._write_loop, name="state-file",
                                                daemon=True)
                self._writer.start()
            self._cond.notify_all()

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until every document handed to :meth:`save_later` is on disk."""
        with self._cond:
            return self._cond.wait_for(lambda: self._pending is None and not self._writing,
                                       timeout)

    def _write_loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None)
                doc, self._pending, self._writing = self._pending, None, True
            try:
                assert self.path is not None and doc is not None
                write_atomically(self.path, pack_document({"version": self.version, **doc}))
            except OSError as exc:
                self._write_failed(exc)
            finally:
                with self._cond:
                    self._writing = False
                    self._cond.notify_all()

    def _write_failed(self, exc: OSError) -> None:
        self.write_errors += 1
        now = time.monotonic()
        if now - self._last_error_log >= ERROR_LOG_PERIOD_S:
            self._last_error_log = now
            log.error("cannot write the state file %s (%d failed writes so far): %s", self.path,
                      self.write_errors, exc)

    def load(self) -> dict[str, Any] | None:
        """The saved document (without ``version``), or None if absent or unreadable."""
        return None if self.path is None else read_state(self.path, self.version)


def read_state(path: Path, version: int) -> dict[str, Any] | None:
    """The document saved at ``path`` (without ``version``), or None if absent, unreadable or of
    another version. Unlike constructing a :class:`StateFile` it touches nothing in the folder,
    so an observer may read while the owner's writer runs (a ``StateFile`` removes the
    temporary file it takes for a dead writer's)."""
    if not path.exists():
        return None
    try:
        doc = unpack_document(path.read_bytes())
        if doc.get("version") != version:
            raise ValueError(f"version {doc.get('version')!r}, expected {version}")
    except (OSError, ProtocolError, ValueError, AttributeError) as exc:
        log.warning("ignoring unreadable state file %s: %s", path, exc)
        return None
    return {k: v for k, v in doc.items() if k != "version"}
