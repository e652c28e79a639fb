"""Disconnected hypothesis (docs/estimation.md#rigid-and-disconnected): no state and no prediction."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.snapshot import SnapshotReader
from services.kinematics.filters.geometry import gaussian_log_density, se3_log_fast

Array = NDArray[np.float64]

# OMIP's uninformative covariance of a disconnected "prediction": 1e6 on, 1e3 off the diagonal.
DISCONNECTED_COVARIANCE: Array = np.full((6, 6), 1e3) + np.eye(6) * (1e6 - 1e3)
DISCONNECTED_COVARIANCE.flags.writeable = False


class DisconnectedJoint:
    """Disconnected: the hand moves independently of the environment.

    Its "prediction", if ever asked for, is the identity with OMIP's uninformative covariance, which
    is also the ``S`` of its innovation ``y = log z``. Model selection scores it with a constant
    per-sample density (``KinematicsConfig.disconnected_density``).
    """

    dim = 0

    def __init__(self) -> None:
        self.z: Array = np.eye(4)
        self.S: Array = DISCONNECTED_COVARIANCE

    def predict(self, dt: float) -> None:
        """Nothing to predict."""

    def update(self, z: Array, R: Array) -> None:
        """Record the measured delta ``z`` (4x4); ``R`` is not used."""
        self.z = z

    @property
    def y(self) -> Array:
        """Innovation ``log z`` (6,)."""
        return se3_log_fast(self.z)

    def log_likelihood(self) -> float:
        """``log N(y; 0, S)`` with the uninformative ``S``."""
        return gaussian_log_density(self.y, self.S)

    def predicted_delta(self, q: float | None = None) -> tuple[Array, Array]:
        """Identity with OMIP's uninformative covariance."""
        return np.eye(4), DISCONNECTED_COVARIANCE.copy()

    def to_state(self) -> dict[str, Any]:
        """The complete filter state (arrays copied) for snapshots."""
        return {"z": np.array(self.z)}

    @classmethod
    def from_state(cls, state: dict[str, Any] | SnapshotReader) -> DisconnectedJoint:
        """Rebuild a filter from :meth:`to_state` exactly (no re-normalisation); SnapshotError
        naming the field for a value :meth:`to_state` cannot have written."""
        r = state if isinstance(state, SnapshotReader) else SnapshotReader(state, "disconnected")
        f = cls()
        f.z = r.pose("z")
        return f
