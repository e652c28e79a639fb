"""The tracker's state document: the hand body model it writes, and the checked reading of it.

The document (``services.common.state_file``, version ``SNAPSHOT_VERSION`` of the tracker
service) is ``{"body": None, "body_epoch": E}`` before any initialisation and after a ``reset``,
else ``{"body": {"frame_id": F, "points": P}, "body_epoch": E}``: the tracking frame ``F``
("camera" or "world") and the (21, 3) body-frame landmark coordinates ``P`` [m] of the last body
model, in landmark order, a row of NaN for a landmark that is not in the model, and ``E`` the
tracker's body epoch (``HandBody.body_epoch``: the epoch of that body frame, or the last one
used). Without ``E`` a restarted tracker that re-acquires its body frame would publish it under
epoch 0, and the kinematics service would take the same body frame for a new one and start its
estimate again; files written before it existed (no ``body_epoch``) are read as epoch unknown. It
holds no stamp: a restarted tracker starts its stream at the first landmarks it gets, so no
"latest stamp" can come back from a file.

:func:`body_from_document` accepts exactly what :func:`body_document` writes. Anything else (a
missing or unknown key, a value of another type, another shape, infinity, a row only partly NaN,
coordinates that no hand has) raises :class:`~services.common.snapshot.SnapshotError` naming the
field and the fault, and the tracker starts fresh.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.snapshot import SnapshotError, SnapshotReader
from services.tracker.landmarks import NUM_LANDMARKS

Array = NDArray[np.float64]

TRACKING_FRAMES = ("camera", "world")
# A hand is about 0.2 m long and its body frame sits at the centroid of its landmarks (or, once
# re-acquired, at an earlier centroid of the same hand): a coordinate beyond this is no hand.
MAX_BODY_COORDINATE_M = 1.0


@dataclass(frozen=True)
class RememberedBody:
    """A body model read back from the state file (see the module docstring)."""

    frame_id: str
    points: Array  # (21, 3) body-frame coordinates [m], NaN rows: not in the model
    body_epoch: int | None = None  # None: a file written before the epoch was kept


def body_document(remembered: tuple[str, Array] | None, body_epoch: int) -> dict[str, Any]:
    """The document that remembers ``(frame_id, points)`` (from
    :meth:`~services.tracker.tracker.HandTracker.remembered_body`; None: no body) and the
    tracker's ``body_epoch``."""
    if remembered is None:
        return {"body": None, "body_epoch": int(body_epoch)}
    frame_id, points = remembered
    return {"body": {"frame_id": frame_id, "points": np.asarray(points, dtype=np.float64)},
            "body_epoch": int(body_epoch)}


def epoch_from_document(doc: Any) -> int | None:
    """The body epoch of a restored document (None: written before it was kept); SnapshotError
    naming the field if it is not a whole number >= 0."""
    tracker = SnapshotReader(doc, "tracker")
    if not isinstance(doc, dict) or "body_epoch" not in doc:
        return None
    epoch = tracker.raw("body_epoch")
    if isinstance(epoch, bool) or not isinstance(epoch, int) or epoch < 0:
        raise SnapshotError(f"tracker.body_epoch: {epoch!r} is not a whole number >= 0")
    return epoch


def body_from_document(doc: Any) -> RememberedBody | None:
    """The body model of a restored document (None: it remembers none); SnapshotError naming the
    field if ``doc`` is not exactly what :func:`body_document` writes (or wrote before
    ``body_epoch`` was kept)."""
    tracker = SnapshotReader(doc, "tracker")
    if isinstance(doc, dict) and "body_epoch" in doc:
        tracker.exactly("body", "body_epoch")
    else:
        tracker.exactly("body")
    epoch = epoch_from_document(doc)
    body = tracker.optional_map("body")
    if body is None:
        return None
    body.exactly("frame_id", "points")
    frame_id = body.choice("frame_id", TRACKING_FRAMES)
    points = body.array("points", (NUM_LANDMARKS, 3), allow_nan_rows=True)
    present = np.isfinite(points).all(axis=1)
    largest = float(np.abs(points[present]).max(initial=0.0))
    if largest > MAX_BODY_COORDINATE_M:
        raise SnapshotError(f"tracker.body.points: a coordinate of {largest:.3g} m, no hand is "
                            f"that large (limit {MAX_BODY_COORDINATE_M:g} m)")
    return RememberedBody(frame_id, points, epoch)


__all__ = ["MAX_BODY_COORDINATE_M", "RememberedBody", "body_document", "body_from_document",
           "epoch_from_document"]
