"""Read an ``.rrd`` file back with Rerun's own reader (``rerun.chunk.RrdReader``), as plain rows."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import pyarrow as pa
import rerun.chunk as rrc

TIMELINE = "stamp_ns"


def read_entities(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Entity path -> rows ``{"stamp_ns": int | None, "Archetype:component": value, ...}`` of
    every chunk of the first recording in the file, sorted by stamp (static rows first)."""
    entities: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in rrc.RrdReader(path).stream():
        batch = chunk.to_record_batch()
        columns: dict[str, list[Any]] = {}
        for name in batch.schema.names:
            if name.startswith("rerun.") or name == "log_time":
                continue
            column = batch.column(name)
            if pa.types.is_timestamp(column.type):
                column = column.cast(pa.int64())
            columns[name] = column.to_pylist()
        for i in range(batch.num_rows):
            row = {name: values[i] for name, values in columns.items()}
            row.setdefault(TIMELINE, None)
            entities[chunk.entity_path].append(row)
    for rows in entities.values():
        rows.sort(key=lambda r: -1 if r[TIMELINE] is None else r[TIMELINE])
    return dict(entities)


def at(rows: list[dict[str, Any]], stamp_ns: int, component: str) -> Any:
    """The value of ``component`` logged at exactly ``stamp_ns`` (the last such row)."""
    values = [r[component] for r in rows if r[TIMELINE] == stamp_ns and r.get(component) is not None]
    if not values:
        raise KeyError(f"no {component} at {stamp_ns}")
    return values[-1]
