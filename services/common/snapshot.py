"""Checked reading of a restored state document: every value's type, shape and range.

A state file (:mod:`services.common.state_file`) holds what its owner wrote, unless it was
truncated by a bug, edited by hand, written by another version or forged. Its owner restores it
through a :class:`SnapshotReader`, which raises :class:`SnapshotError` naming the field path and
what is wrong (``estimator.revolute.P: expected shape (12, 12), got (3,)``) for anything that is
not exactly what the owner writes: a value of another type, an array of another shape, NaN or
infinity, an integer out of range, a string outside its choices. The owner then starts fresh.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import check_pose

Array = NDArray[np.float64]


class SnapshotError(ValueError):
    """A restored document does not hold what its owner writes; the text names the field."""


def _describe(value: Any) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text[:60]}{'...' if len(text) > 60 else ''}"


class SnapshotReader:
    """Typed access to one map of a document; ``path`` names it in errors (``"estimator"``)."""

    def __init__(self, doc: Any, path: str) -> None:
        if not isinstance(doc, dict):
            raise SnapshotError(f"{path}: expected a map, got {_describe(doc)}")
        self._doc = doc
        self.path = path

    def _where(self, key: str) -> str:
        return f"{self.path}.{key}"

    def exactly(self, *keys: str) -> SnapshotReader:
        """This reader, if the map holds exactly ``keys`` (SnapshotError naming the missing and
        the unknown ones otherwise: a document of another layout is not partly restored)."""
        expected = set(keys)
        if set(self._doc) != expected:
            missing = sorted(expected - set(self._doc))
            unknown = sorted(map(str, set(self._doc) - expected))
            raise SnapshotError(f"{self.path}: expected the keys {sorted(expected)} (missing "
                                f"{missing}, unknown {unknown})")
        return self

    def raw(self, key: str) -> Any:
        """The value at ``key`` as stored (SnapshotError if absent)."""
        if key not in self._doc:
            raise SnapshotError(f"{self._where(key)}: missing")
        return self._doc[key]

    def is_none(self, key: str) -> bool:
        return self.raw(key) is None

    def map(self, key: str) -> SnapshotReader:
        return SnapshotReader(self.raw(key), self._where(key))

    def optional_map(self, key: str) -> SnapshotReader | None:
        return None if self.is_none(key) else self.map(key)

    def integer(self, key: str, lo: int | None = None, hi: int | None = None) -> int:
        """An int (not a bool) in ``[lo, hi]``."""
        value = self.raw(key)
        if isinstance(value, bool) or not isinstance(value, int):
            raise SnapshotError(f"{self._where(key)}: expected an integer, got {_describe(value)}")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise SnapshotError(f"{self._where(key)}: {value} is outside [{lo}, {hi}]")
        return value

    def optional_integer(self, key: str, lo: int | None = None,
                         hi: int | None = None) -> int | None:
        return None if self.is_none(key) else self.integer(key, lo, hi)

    def number(self, key: str) -> float:
        """A finite int or float (not a bool), as float."""
        value = self.raw(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SnapshotError(f"{self._where(key)}: expected a number, got {_describe(value)}")
        if not math.isfinite(value):
            raise SnapshotError(f"{self._where(key)}: {value!r} is not finite")
        return float(value)

    def boolean(self, key: str) -> bool:
        value = self.raw(key)
        if not isinstance(value, bool):
            raise SnapshotError(f"{self._where(key)}: expected true/false, got {_describe(value)}")
        return value

    def choice(self, key: str, choices: Sequence[str]) -> str:
        value = self.raw(key)
        if not isinstance(value, str) or value not in choices:
            raise SnapshotError(f"{self._where(key)}: expected one of {list(choices)}, got "
                                f"{_describe(value)}")
        return value

    def array(self, key: str, shape: tuple[int, ...], *, allow_minus_inf: bool = False,
              allow_nan_rows: bool = False) -> Array:
        """A float64 copy of a numeric array (or nested list) of exactly ``shape`` (any empty one
        for an empty ``shape``), finite (``-inf`` allowed where ``allow_minus_inf``, for log
        scores; a row along the last axis that is NaN throughout where ``allow_nan_rows``, for
        an entry that is absent, but never a row only partly NaN)."""
        value = self.raw(key)
        where = self._where(key)
        if isinstance(value, np.ndarray):
            if value.dtype.kind not in "fiu":
                raise SnapshotError(f"{where}: expected a numeric array, got dtype {value.dtype}")
        elif not isinstance(value, list):
            raise SnapshotError(f"{where}: expected an array, got {_describe(value)}")
        try:
            a = np.array(value, dtype=np.float64)
        except (TypeError, ValueError, OverflowError) as exc:
            raise SnapshotError(f"{where}: not a numeric array ({exc})") from exc
        if a.size == 0 and math.prod(shape) == 0:
            return np.zeros(shape)  # an empty array loses its shape in a list round trip
        if a.shape != shape:
            raise SnapshotError(f"{where}: expected shape {shape}, got {a.shape}")
        bad = ~np.isfinite(a)
        if allow_minus_inf:
            bad &= a != -np.inf
        if allow_nan_rows:
            if a.ndim != 2:
                raise ValueError(f"allow_nan_rows needs a 2-d shape, got {shape}")
            nan = np.isnan(a)
            partial = np.flatnonzero(nan.any(axis=1) & ~nan.all(axis=1))
            if partial.size:
                raise SnapshotError(f"{where}: rows {partial.tolist()} are partly NaN (an entry "
                                    "is there in full, or NaN throughout)")
            bad &= ~nan
        if bad.any():
            raise SnapshotError(f"{where}: contains NaN or infinity")
        return a

    def covariance(self, key: str, n: int) -> Array:
        """An ``n x n`` array, symmetric (1e-9 relative) with a non-negative diagonal."""
        C = self.array(key, (n, n))
        scale = max(1.0, float(np.abs(C).max(initial=0.0)))
        if float(np.abs(C - C.T).max(initial=0.0)) > 1e-9 * scale:
            raise SnapshotError(f"{self._where(key)}: not symmetric")
        if n and float(C.diagonal().min()) < 0.0:
            raise SnapshotError(f"{self._where(key)}: negative variance on the diagonal")
        return C

    def unit_vector(self, key: str, n: int = 3) -> Array:
        """A finite ``(n,)`` array of unit length (1e-6)."""
        v = self.array(key, (n,))
        norm = float(np.linalg.norm(v))
        if abs(norm - 1.0) > 1e-6:
            raise SnapshotError(f"{self._where(key)}: not a unit vector (norm {norm:.9g})")
        return v

    def pose(self, key: str) -> Array:
        """A rigid 4x4 transform (:func:`services.common.se3.check_pose`)."""
        T = self.array(key, (4, 4))
        problem = check_pose(T)
        if problem is not None:
            raise SnapshotError(f"{self._where(key)}: not a rigid transform ({problem})")
        return T


__all__ = ["SnapshotError", "SnapshotReader"]
