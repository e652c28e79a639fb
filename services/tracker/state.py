"""The tracker's state document: the hand body model it writes, and the checked reading of it.

The document (``services.common.state_file``, version ``SNAPSHOT_VERSION`` of the tracker
service) is ``{"body": None}`` before any initialisation and after a ``reset``, else
``{"body": {"frame_id": F, "points": P}}``: the tracking frame ``F`` ("camera" or "world") and the
(21, 3) body-frame landmark coordinates ``P`` [m] of the last body model, in landmark order, a row
of NaN for a landmark that is not in the model. It holds no stamp: a restarted tracker starts its
stream at the first landmarks it gets, so no "latest stamp" can come back from a file.

:func:`body_from_document` accepts exactly what :func:`body_document` writes. Anything else (a
missing or unknown key, a value of another type, another shape, infinity, a row only partly NaN,
coordinates that no hand has) raises :class:`BodyDocumentError` naming the field and the fault,
and the tracker starts fresh.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.tracker.landmarks import NUM_LANDMARKS

Array = NDArray[np.float64]

TRACKING_FRAMES = ("camera", "world")
# A hand is about 0.2 m long and its body frame sits at the centroid of its landmarks (or, once
# re-acquired, at an earlier centroid of the same hand): a coordinate beyond this is no hand.
MAX_BODY_COORDINATE_M = 1.0


class BodyDocumentError(ValueError):
    """A restored tracker document does not hold a body model; the text names the field."""


@dataclass(frozen=True)
class RememberedBody:
    """A body model read back from the state file (see the module docstring)."""

    frame_id: str
    points: Array  # (21, 3) body-frame coordinates [m], NaN rows: not in the model


def body_document(remembered: tuple[str, Array] | None) -> dict[str, Any]:
    """The document that remembers ``(frame_id, points)`` (from
    :meth:`~services.tracker.tracker.HandTracker.remembered_body`; None: no body)."""
    if remembered is None:
        return {"body": None}
    frame_id, points = remembered
    return {"body": {"frame_id": frame_id, "points": np.asarray(points, dtype=np.float64)}}


def _describe(value: Any) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text[:60]}{'...' if len(text) > 60 else ''}"


def _expect_keys(value: Any, where: str, keys: set[str]) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise BodyDocumentError(f"{where}: expected a map, got {_describe(value)}")
    if set(value) != keys:
        missing, unknown = sorted(keys - set(value)), sorted(map(str, set(value) - keys))
        raise BodyDocumentError(f"{where}: expected the keys {sorted(keys)} (missing {missing}, "
                                f"unknown {unknown})")
    return value


def _points(value: Any) -> Array:
    where = "body.points"
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "fiu":
            raise BodyDocumentError(f"{where}: expected a numeric array, got dtype {value.dtype}")
    elif not isinstance(value, list):
        raise BodyDocumentError(f"{where}: expected an array, got {_describe(value)}")
    try:
        points = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise BodyDocumentError(f"{where}: not a numeric array ({exc})") from exc
    if points.shape != (NUM_LANDMARKS, 3):
        raise BodyDocumentError(f"{where}: expected shape ({NUM_LANDMARKS}, 3), got "
                                f"{points.shape}")
    if np.isinf(points).any():
        raise BodyDocumentError(f"{where}: contains infinity")
    nan = np.isnan(points)
    partial = np.flatnonzero(nan.any(axis=1) & ~nan.all(axis=1))
    if partial.size:
        raise BodyDocumentError(f"{where}: landmarks {partial.tolist()} are partly NaN (a "
                                "landmark is in the model with three coordinates, or not at all)")
    largest = float(np.abs(points[~nan]).max(initial=0.0))
    if largest > MAX_BODY_COORDINATE_M:
        raise BodyDocumentError(f"{where}: a coordinate of {largest:.3g} m, no hand is that "
                                f"large (limit {MAX_BODY_COORDINATE_M:g} m)")
    return points


def body_from_document(doc: Any) -> RememberedBody | None:
    """The body model of a restored document (None: it remembers none); BodyDocumentError if
    ``doc`` is not exactly what :func:`body_document` writes."""
    body = _expect_keys(doc, "document", {"body"})["body"]
    if body is None:
        return None
    body = _expect_keys(body, "body", {"frame_id", "points"})
    frame_id = body["frame_id"]
    if not isinstance(frame_id, str) or frame_id not in TRACKING_FRAMES:
        raise BodyDocumentError(f"body.frame_id: expected one of {list(TRACKING_FRAMES)}, got "
                                f"{_describe(frame_id)}")
    return RememberedBody(frame_id, _points(body["points"]))


__all__ = ["MAX_BODY_COORDINATE_M", "BodyDocumentError", "RememberedBody", "body_document",
           "body_from_document"]
