"""Guards for the tracker's covariance algebra: symmetrise, test, repair and factor.

Every covariance the tracker factors, inverts or publishes passes through here. In exact
arithmetic the filters keep their covariances positive semi-definite (Joseph forms, congruences),
but round-off can break that when the numbers are extreme (a flood of frames microseconds apart
gives a process noise ~1e-9 of the pose covariance; landmarks near the 1 km limit give
information sums ~1e12 times those of a hand at arm's length), and a Cholesky factor of a matrix
that is not positive definite does not exist. So:

- :func:`psd_repaired` returns the nearest symmetric matrix whose eigenvalues are at least a small
  floor relative to the largest (eigenvalue clipping); None when the matrix is not finite;
- :func:`is_psd` is the cheap test, one Cholesky factorisation of the matrix plus a relative
  jitter (a success proves every eigenvalue is above minus that jitter);
- :func:`guarded_cholesky` factors, repairing first when it must.

Callers count every repair (``HandTracker.covariance_repairs``): a repair is a symptom, never
silent. The floors are relative (to the largest eigenvalue, or the trace), so they do not depend
on the units.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# Relative eigenvalue floor of a repaired covariance, and the jitter under which a covariance still
# counts as positive semi-definite: far below any variance the filters hold (round-off of the
# largest entry is ~1e-16 of it), far above the round-off of a 12x12 congruence.
EIGENVALUE_FLOOR = 1e-12
PSD_TOLERANCE = 1e-9


@lru_cache(maxsize=4)
def _eye(n: int) -> Array:
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


def symmetrised(M: Array) -> Array:
    """``(M + M') / 2`` over the last two axes."""
    out: Array = 0.5 * (M + np.swapaxes(M, -1, -2))
    return out


def is_psd(M: Array, tolerance: float = PSD_TOLERANCE) -> bool:
    """Whether the symmetric matrix ``M`` (n, n) is finite and has no eigenvalue below
    ``-tolerance`` times its trace: one Cholesky factorisation of ``M + tolerance trace(M) I``
    (a NaN or inf anywhere in the lower triangle, which is all it reads, reaches the last
    diagonal entry of the factor; callers pass symmetrised matrices)."""
    n = M.shape[-1]
    try:
        L = np.linalg.cholesky(M + (tolerance * float(np.trace(M))) * _eye(n))
    except np.linalg.LinAlgError:
        return False
    return bool(np.isfinite(L[-1, -1]))


def psd_repaired(M: Array, floor: float = EIGENVALUE_FLOOR) -> Array | None:
    """The symmetrised ``M`` (..., n, n) with every eigenvalue raised to at least ``floor`` times
    the largest eigenvalue (of each matrix; absolute ``floor`` for a matrix that is all zero),
    or None when ``M`` is not finite. Positive definite, and unchanged up to round-off where
    ``M`` already was comfortably so."""
    if not np.isfinite(M).all():
        return None
    w, V = np.linalg.eigh(symmetrised(M))
    top = np.maximum(w[..., -1:], 0.0)
    w = np.maximum(w, np.where(top > 0.0, floor * top, floor))
    out: Array = (V * w[..., None, :]) @ np.swapaxes(V, -1, -2)
    return symmetrised(out)


def guarded_cholesky(M: Array) -> tuple[Array, bool] | None:
    """Lower Cholesky factors of the symmetrised ``M`` (..., n, n) and whether ``M`` had to be
    repaired first (:func:`psd_repaired`); None when ``M`` is not finite."""
    if not np.isfinite(M).all():
        return None
    try:
        return np.linalg.cholesky(symmetrised(M)), False
    except np.linalg.LinAlgError:
        pass
    fixed = psd_repaired(M)
    if fixed is None:
        return None
    try:
        return np.linalg.cholesky(fixed), True
    except np.linalg.LinAlgError:  # a floor lost to round-off at extreme condition numbers
        return None


__all__ = ["EIGENVALUE_FLOOR", "PSD_TOLERANCE", "guarded_cholesky", "is_psd", "psd_repaired",
           "symmetrised"]
