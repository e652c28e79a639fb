"""Does a new contact phase move the joint of an earlier one? (docs/estimation.md#contact-phases)

A re-grasp of the same joint holds the part somewhere else, so the new phase's hand poses are
not the old phase's; but the hand's *displacement* since the new grasp, ``D_j = T_j T_1^-1``
(``T_1`` the new phase's first pose), is a motion of the joint whatever the grasp:
``D_j = Exp(dq_j xi)`` with the joint's unit screw ``xi`` in the tracking frame (revolute
``(p x u, u)``, prismatic ``(u, 0)``, rigid ``0``). :func:`screw_residual` fits ``dq_j`` to one
frame and scores what the screw leaves unexplained against the pose noise and the old model's
own uncertainty: about 5 on average (the residual has 5 degrees of freedom) when the old joint
moves, and about the whole motion's score when another joint does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import KinematicModel
from services.kinematics.filters import (
    prismatic_twist_jacobian,
    revolute_left_jacobian,
    revolute_twist_jacobian,
    tangent_basis,
)
from services.kinematics.filters.geometry import se3_inverse_fast, se3_log_fast

Array = NDArray[np.float64]

_FLOOR = 1e-6  # m^2 / rad^2 on the residual covariance's diagonal (degenerate inputs)


def unit_screw(model: KinematicModel) -> Array | None:
    """The joint's unit screw (6,) (linear first) in the model's frame; zero for rigid; None
    for a type without one (unknown, disconnected)."""
    if model.type == "rigid":
        return np.zeros(6)
    if model.type == "revolute" and model.revolute is not None:
        u = np.asarray(model.revolute.axis, dtype=float)
        p = np.asarray(model.revolute.point, dtype=float)
        return np.concatenate([np.cross(p, u), u])
    if model.type == "prismatic" and model.prismatic is not None:
        return np.concatenate([np.asarray(model.prismatic.axis, dtype=float), np.zeros(3)])
    return None


def _parameter_jacobian(model: KinematicModel, dq: float) -> tuple[Array, Array] | None:
    """``(J, C)``: the Jacobian (6 x k) of ``log Exp(dq xi)`` w.r.t. the model's axis (and
    point) parameters, and their covariance (k x k); None for rigid."""
    if model.type == "revolute" and model.revolute is not None:
        u = np.asarray(model.revolute.axis, dtype=float)
        p = np.asarray(model.revolute.point, dtype=float)
        J = revolute_left_jacobian(u, p, dq) @ revolute_twist_jacobian(u, p, tangent_basis(u), dq)
        return J[:, :5], np.asarray(model.revolute.covariance, dtype=float)[:5, :5]
    if model.type == "prismatic" and model.prismatic is not None:
        u = np.asarray(model.prismatic.axis, dtype=float)
        J = prismatic_twist_jacobian(u, tangent_basis(u), dq)
        return J[:, :2], np.asarray(model.prismatic.covariance, dtype=float)[:2, :2]
    return None


def screw_residual(model: KinematicModel, T1_inv: Array, Sigma_1: Array, T: Array,
                   Sigma: Array) -> tuple[float, float]:
    """``(residual, motion)``: the squared Mahalanobis norms of what the best 1-DOF motion along
    ``model``'s screw leaves unexplained of ``z = log(T T_1^-1)``, and of ``z`` itself (module
    docstring); ``(inf, motion)`` for a model without a screw.

    ``T1_inv``: the inverse (4x4) of the new phase's first pose; ``Sigma_1``, ``Sigma``: the 6x6
    left-perturbation covariances (frame, linear first) of that pose and of ``T`` (4x4). The
    residual's covariance is ``Sigma + Sigma_1`` plus the old model's axis (and point)
    uncertainty carried to the fitted ``dq``; the motion's is ``Sigma + Sigma_1``.
    """
    z = se3_log_fast(np.asarray(T, dtype=float) @ T1_inv)
    S0 = np.asarray(Sigma, dtype=float) + Sigma_1 + _FLOOR * np.eye(6)
    motion = float(z @ np.linalg.solve(S0, z))
    xi = unit_screw(model)
    if xi is None:
        return math.inf, motion
    if not float(xi @ xi) > 0.0:
        return motion, motion
    S = S0
    dq = 0.0
    for _ in range(2):  # fit dq, add the model uncertainty at dq, refit
        Si_xi = np.linalg.solve(S, xi)
        dq = float(Si_xi @ z) / float(Si_xi @ xi)
        jc = _parameter_jacobian(model, dq)
        if jc is not None:
            J, C = jc
            S = S0 + J @ C @ J.T
    r = z - dq * xi
    return float(r @ np.linalg.solve(S, r)), motion


def mean_screw_residual(model: KinematicModel, poses: Sequence[Array],
                        covariances: Sequence[Array]) -> float:
    """Mean of :func:`screw_residual` over frames 2.. of ``poses`` (4x4 each, in order) and
    their ``covariances`` (6x6); 0 for fewer than two poses."""
    if len(poses) < 2:
        return 0.0
    T1_inv = se3_inverse_fast(np.asarray(poses[0], dtype=float))
    S1 = np.asarray(covariances[0], dtype=float)
    return sum(screw_residual(model, T1_inv, S1, T, S)[0]
               for T, S in zip(poses[1:], covariances[1:], strict=True)) / (len(poses) - 1)


__all__ = ["mean_screw_residual", "screw_residual", "unit_screw"]
