"""The published parameters of a joint filter (docs/estimation.md#output-canonicalisation).

Internally a filter's axis sign is fixed by the first motion (so ``q`` starts positive and stays
continuous); the published axis is flipped, for output only, so that its largest-magnitude
component is positive (:func:`canonical_axis_sign`), with ``q``, ``qdot`` and the covariance
mapped along. The published covariance is the filter's own times its whiteness inflation
(docs/estimation.md#published-covariance). Frames and units are the filter's (the tracking
frame; m, rad).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import PrismaticParams, RevoluteParams
from services.kinematics.filters import PrismaticJoint, RevoluteJoint, tangent_basis

Array = NDArray[np.float64]


def canonical_axis_sign(u: Array) -> float:
    """+1 or -1 so that ``sign * u`` has its largest-magnitude component positive.

    Components within 1e-6 of the largest magnitude count as tied and the lowest index wins, so
    rounding cannot flip axes such as (0, 1, -1)/sqrt(2) between runs.
    """
    mags = [abs(c) for c in u.tolist()]
    top = max(mags)
    big = next(c for c, m in zip(u.tolist(), mags, strict=True) if m >= top - 1e-6)
    return 1.0 if big >= 0.0 else -1.0


def _frozen(a: Array) -> Array:
    a = np.array(a, dtype=float)
    a.flags.writeable = False
    return a


def _axis_output(u: Array, B: Array) -> tuple[float, Array, list[list[float]]]:
    """``(s, axis, T)``: the output sign, the published axis ``s u`` and the 2x2 map ``T`` of the
    axis tangent coordinates from the filter's basis ``B`` to ``tangent_basis(axis)``
    (:func:`~services.kinematics.filters.axis_basis_change`)."""
    s = canonical_axis_sign(u)
    axis = u * s
    axis.flags.writeable = False
    (e0, f0), (e1, f1), (e2, f2) = tangent_basis(axis).tolist()
    (a0, c0), (a1, c1), (a2, c2) = B.tolist()
    T = [[s * (e0 * a0 + e1 * a1 + e2 * a2), s * (e0 * c0 + e1 * c1 + e2 * c2)],
         [s * (f0 * a0 + f1 * a1 + f2 * a2), s * (f0 * c0 + f1 * c1 + f2 * c2)]]
    return s, axis, T


def prismatic_params(f: PrismaticJoint) -> PrismaticParams:
    """Canonicalised published parameters of a prismatic filter (see the module docstring)."""
    s, axis, ((t00, t01), (t10, t11)) = _axis_output(f.u, f.B)
    G = np.array([[t00, t01, 0.0, 0.0], [t10, t11, 0.0, 0.0], [0.0, 0.0, s, 0.0],
                  [0.0, 0.0, 0.0, s]])
    cov = G @ f.P[:4, :4] @ G.T
    cov = (cov + cov.T) * (0.5 * f.covariance_inflation())
    cov.flags.writeable = False
    return PrismaticParams(axis=axis, q=s * f.q, dq=s * f.qdot, covariance=cov)


def revolute_params(f: RevoluteJoint) -> RevoluteParams:
    """Canonicalised published parameters of a revolute filter (see the module docstring)."""
    s, axis, ((t00, t01), (t10, t11)) = _axis_output(f.u, f.B)
    (a0, c0), (a1, c1), (a2, c2) = f.B.tolist()
    # (b, c, q, qdot) -> (b_out, p = p_hat + B c, s q, s qdot)
    G = np.array([[t00, t01, 0.0, 0.0, 0.0, 0.0], [t10, t11, 0.0, 0.0, 0.0, 0.0],
                  [0.0, 0.0, a0, c0, 0.0, 0.0], [0.0, 0.0, a1, c1, 0.0, 0.0],
                  [0.0, 0.0, a2, c2, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, s, 0.0],
                  [0.0, 0.0, 0.0, 0.0, 0.0, s]])
    cov = G @ f.P[:6, :6] @ G.T
    cov = (cov + cov.T) * (0.5 * f.covariance_inflation())
    cov.flags.writeable = False
    return RevoluteParams(axis=axis, point=_frozen(f.p), q=s * f.q, dq=s * f.qdot,
                          covariance=cov)


__all__ = ["canonical_axis_sign", "prismatic_params", "revolute_params"]
