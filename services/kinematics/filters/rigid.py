"""Rigid joint (OMIP's): no state; the hand does not move relative to the reference."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.snapshot import SnapshotReader
from services.kinematics.filters.geometry import (
    excess_sigmas,
    gaussian_log_density,
    se3_log_fast,
)

Array = NDArray[np.float64]


class RigidJoint:
    """Rigid joint: the predicted delta is I.

    ``update(z, R)`` takes the measured delta ``z = D`` (4x4) with its left-perturbation covariance
    ``R`` (6x6) and keeps them; the innovation ``y = log D`` (6,) is computed when asked for, with
    ``S = R``.
    """

    dim = 0

    def __init__(self) -> None:
        self.z: Array = np.eye(4)
        self.S: Array = np.eye(6)

    def predict(self, dt: float) -> None:
        """Nothing to predict: the joint has no state."""

    def update(self, z: Array, R: Array) -> None:
        """Record the measured delta ``z`` (4x4) and ``S = R`` (6x6)."""
        self.z = z
        self.S = R

    @property
    def y(self) -> Array:
        """Innovation ``log(z Exp(0)^-1) = log z`` (6,)."""
        return se3_log_fast(self.z)

    def log_likelihood(self) -> float:
        """``log N(y; 0, S)`` of the last innovation."""
        return gaussian_log_density(self.y, self.S)

    def predicted_delta(self, q: float | None = None) -> tuple[Array, Array]:
        """Identity delta with zero covariance (a rigid joint has no parameters)."""
        return np.eye(4), np.zeros((6, 6))

    @staticmethod
    def history_errors(d2_translation: Array, d2_rotation: Array,
                       sigmas: float) -> tuple[Array, Array]:
        """Model-selection errors of samples against "no motion" (the rigid test,
        docs/estimation.md#rigid-test): by how many sigmas the hand displacement and the rotation
        of each delta exceed ``sigmas`` sigmas of their published covariance,
        ``max(0, sqrt(d2) - sigmas)`` (:func:`~services.kinematics.filters.excess_sigmas`).

        ``d2_translation``, ``d2_rotation`` (m,): the squared Mahalanobis distances of the
        displacement and of the rotation vector. Rigid predicts the measurement exactly, so its
        error is the measurement noise, measured in the published covariance's own units.
        """
        return excess_sigmas(d2_translation, sigmas), excess_sigmas(d2_rotation, sigmas)

    def to_state(self) -> dict[str, Any]:
        """The complete filter state (arrays copied) for snapshots."""
        return {"z": np.array(self.z), "S": np.array(self.S)}

    @classmethod
    def from_state(cls, state: dict[str, Any] | SnapshotReader) -> RigidJoint:
        """Rebuild a filter from :meth:`to_state` exactly (no re-normalisation); SnapshotError
        naming the field for a value :meth:`to_state` cannot have written."""
        r = state if isinstance(state, SnapshotReader) else SnapshotReader(state, "rigid")
        f = cls()
        f.z = r.pose("z")
        f.S = r.covariance("S", 6)
        return f
