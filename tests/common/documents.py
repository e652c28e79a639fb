"""Editing nested documents (state files, snapshots) for the tests of their readers."""

from __future__ import annotations

import copy
from typing import Any


def with_field(doc: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    """A deep copy of ``doc`` with the field at the dotted ``path`` set to ``value``
    (``...``: deleted)."""
    doc = copy.deepcopy(doc)
    *parents, key = path.split(".")
    node = doc
    for p in parents:
        node = node[p]
    if value is ...:
        del node[key]
    else:
        node[key] = value
    return doc
