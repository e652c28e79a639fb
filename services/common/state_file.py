"""A service's state on disk: one msgpack document, replaced atomically, restored at start.

Used by the kinematics service (the estimator) and the tracker (the hand body model), so a
service that is killed and restarted continues where it was. The document is a map with a
``version``; a file that is unreadable or of another version is ignored with a warning (the
service then starts fresh), never fatal.
"""

from __future__ import annotations

import logging
import os
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

    def save(self, doc: dict[str, Any]) -> None:
        if self.path is not None:
            write_atomically(self.path, pack_document({"version": self.version, **doc}))

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
