"""A service's state on disk: one msgpack document, replaced atomically, restored at start.

Used by the kinematics service (the estimator) and the tracker (the hand body model), so a
service that is killed and restarted continues where it was. The document is a map with a
``version``; a file that is unreadable or of another version is ignored with a warning (the
service then starts fresh), never fatal.

:meth:`StateFile.save_later` takes the write off a service's hot path: a writer thread packs and
writes the newest document handed to it (documents that were superseded before it got to them
are skipped), so a crash loses at most the updates of the last write (about 0.5 ms).
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path
from typing import Any

from services.common.protocol import ProtocolError, pack_document, unpack_document

log = logging.getLogger(__name__)


def write_atomically(path: Path, data: bytes) -> None:
    """Replace ``path`` with ``data`` so a reader (or a restart) never sees a partial file."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


class StateFile:
    """``save(doc)`` / ``load()`` of one versioned document at ``path`` (None: disabled)."""

    def __init__(self, path: Path | None, version: int) -> None:
        self.path = path
        self.version = version
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
                log.error("cannot write the state file %s: %s", self.path, exc)
            finally:
                with self._cond:
                    self._writing = False
                    self._cond.notify_all()

    def load(self) -> dict[str, Any] | None:
        """The saved document (without ``version``), or None if absent or unreadable."""
        if self.path is None or not self.path.exists():
            return None
        try:
            doc = unpack_document(self.path.read_bytes())
            if doc.get("version") != self.version:
                raise ValueError(f"version {doc.get('version')!r}, expected {self.version}")
        except (OSError, ProtocolError, ValueError, AttributeError) as exc:
            log.warning("ignoring unreadable state file %s: %s", self.path, exc)
            return None
        return {k: v for k, v in doc.items() if k != "version"}
