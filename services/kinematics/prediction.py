"""Hand pose predicted from a kinematic model: the tracker's third motion model, and anyone else's.

One function, :func:`predict_hand_pose`, on the one model type
:class:`services.common.protocol.KinematicModel` (published by the kinematics service, returned by
:class:`services.kinematics.estimator.KinematicEstimator`); :func:`predicted_pose` is its pose
alone, for callers that need the covariance only now and then (the estimator's outlier gate).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import KinematicModel
from services.kinematics.filters import (
    prismatic_twist_jacobian,
    revolute_delta,
    revolute_left_jacobian,
    revolute_twist_jacobian,
    tangent_basis,
)

Array = NDArray[np.float64]


def _unit(v: Array) -> Array:
    u = np.asarray(v, dtype=float).reshape(3)
    return u / math.sqrt(float(u @ u))


def predict_hand_pose(model: KinematicModel, stamp_ns: int) -> tuple[Array, Array] | None:
    """Predicted hand pose ``T_frame_hand`` (4x4) at ``stamp_ns`` and its 6x6 covariance, or None.

    - prismatic / revolute: ``T = Exp(q_pred * screw) @ reference_pose`` with
      ``q_pred = q + dq * (stamp_ns - model.stamp_ns) * 1e-9``; the screw is ``(u, 0)`` (prismatic)
      or ``(p x u, u)`` (revolute). The covariance is that of the left perturbation of ``T`` in
      ``frame`` (linear first), propagated from the model covariance (axis in
      ``tangent_basis(axis)`` coordinates, point, q, dq) through the exact Jacobian of ``Exp``; it
      does not include the uncertainty of the reference pose itself, nor any process noise of the
      caller, which the caller adds.
    - rigid: the hand does not move relative to its reference, so the prediction is
      ``reference_pose`` with zero (parameter) covariance.
    - unknown, disconnected, or a type whose parameters are missing: None (no kinematic prediction).
    """
    model_type = model.type
    T_ref = np.asarray(model.reference_pose, dtype=float)
    if model_type == "rigid":
        return T_ref.copy(), np.zeros((6, 6))
    dt = (int(stamp_ns) - int(model.stamp_ns)) * 1e-9
    if model_type == "prismatic":
        prm = model.prismatic
        if prm is None:
            return None
        u = _unit(prm.axis)
        q = float(prm.q) + float(prm.dq) * dt
        J = prismatic_twist_jacobian(u, tangent_basis(u), q)
        J[:, 3] = dt * J[:, 2]  # q_pred = q + dq dt
        C = np.asarray(prm.covariance, dtype=float)
        cov = J @ C @ J.T  # a pure translation: the SE(3) left Jacobian is I
        D = np.eye(4)
        D[:3, 3] = q * u
    elif model_type == "revolute":
        rev = model.revolute
        if rev is None:
            return None
        u = _unit(rev.axis)
        p = np.asarray(rev.point, dtype=float).reshape(3)
        q = float(rev.q) + float(rev.dq) * dt
        J = revolute_twist_jacobian(u, p, tangent_basis(u), q)
        J[:, 6] = dt * J[:, 5]  # q_pred = q + dq dt
        J = revolute_left_jacobian(u, p, q) @ J  # SE(3) left Jacobian at q (p x u, u)
        C = np.asarray(rev.covariance, dtype=float)
        cov = J @ C @ J.T
        D = revolute_delta(u, p, q)
    else:
        return None
    return D @ T_ref, 0.5 * (cov + cov.T)


def predicted_pose(model: KinematicModel, stamp_ns: int) -> Array | None:
    """The pose of :func:`predict_hand_pose` alone (identical), without its covariance."""
    model_type = model.type
    T_ref = np.asarray(model.reference_pose, dtype=float)
    if model_type == "rigid":
        return T_ref.copy()
    dt = (int(stamp_ns) - int(model.stamp_ns)) * 1e-9
    if model_type == "prismatic" and model.prismatic is not None:
        prm = model.prismatic
        u = _unit(prm.axis)
        D = np.eye(4)
        D[:3, 3] = (float(prm.q) + float(prm.dq) * dt) * u
    elif model_type == "revolute" and model.revolute is not None:
        rev = model.revolute
        D = revolute_delta(_unit(rev.axis), np.asarray(rev.point, dtype=float).reshape(3),
                           float(rev.q) + float(rev.dq) * dt)
    else:
        return None
    return D @ T_ref


__all__ = ["predict_hand_pose", "predicted_pose"]
