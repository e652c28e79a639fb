"""Whiteness of a joint filter's innovations, and the covariance inflation it implies.

The joint EKFs treat every frame's hand pose as an independent measurement. The tracker's pose
errors are not independent: detector errors and grip adjustments persist over many frames (the
lag-one correlation of the pose error is 0.7-0.9 on the synthetic demonstrations). A filter that
counts N correlated frames as N independent ones ends with a posterior covariance that is too
small, and its innovations, white when the model is right, are correlated
(docs/estimation.md#published-covariance).

:class:`InnovationCorrelation` keeps the lag-one autocorrelation ``rho`` of the whitened
innovations ``w_k = L_k^-1 y_k`` (``S_k = L_k L_k'``) over a filter's life:
``rho = sum_k w_k . w_{k-1} / sum_k |w_k|^2``, clipped to ``[0, 1)``. For AR(1) errors,
``(1 + rho) / (1 - rho)`` is the integrated autocorrelation time: the variance inflation under
which an estimator that assumes independence gets the right posterior.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dpotrf, dtrtrs

from services.common.snapshot import SnapshotError, SnapshotReader

Array = NDArray[np.float64]


class InnovationCorrelation:
    """Running lag-one autocorrelation of a filter's whitened innovations (module docstring)."""

    def __init__(self, dim: int) -> None:
        self.dim = dim
        self.sum_squares = 0.0  # sum_k |w_k|^2
        self.sum_lag_products = 0.0  # sum_k w_k . w_{k-1}
        self.last: Array | None = None  # w_{k-1}

    def add(self, y: Array, S: Array) -> None:
        """Absorb one innovation ``y`` (dim,) with its covariance ``S`` (dim x dim); an ``S``
        without a Cholesky factor (never, in exact arithmetic) is skipped."""
        L, info = dpotrf(S, lower=1, clean=1)  # S = L L' (LAPACK: no numpy overhead per frame)
        if info:
            return
        w, info = dtrtrs(L, y, lower=1)  # w = L^-1 y
        if info:
            return
        self.sum_squares += float(w @ w)
        if self.last is not None:
            self.sum_lag_products += float(w @ self.last)
        self.last = w

    @property
    def rho(self) -> float:
        """Lag-one autocorrelation in ``[0, 1)`` (0 before two innovations; a negative one, which
        would claim the errors cancel, counts as 0)."""
        if self.sum_squares <= 0.0:
            return 0.0
        return min(max(self.sum_lag_products / self.sum_squares, 0.0), 1.0 - 1e-9)

    def inflation(self, scale: float, cap: float) -> float:
        """The variance factor of the published covariance: ``scale (1 + rho) / (1 - rho)``,
        at least 1 (the filter's own covariance is never shrunk) and at most ``cap``."""
        rho = self.rho
        return min(max(scale * (1.0 + rho) / (1.0 - rho), 1.0), cap)

    def to_state(self) -> dict[str, Any]:
        return {"sum_squares": self.sum_squares, "sum_lag_products": self.sum_lag_products,
                "last": None if self.last is None else self.last.copy()}

    @classmethod
    def from_state(cls, dim: int, r: SnapshotReader) -> InnovationCorrelation:
        """Rebuild from :meth:`to_state`; SnapshotError naming the field that is wrong."""
        c = cls(dim)
        c.sum_squares = r.number("sum_squares")
        c.sum_lag_products = r.number("sum_lag_products")
        if c.sum_squares < 0.0 or not math.isfinite(c.sum_squares):
            raise SnapshotError(f"{r.path}.sum_squares: must be >= 0, got {c.sum_squares!r}")
        c.last = None if r.is_none("last") else r.array("last", (dim,))
        return c
