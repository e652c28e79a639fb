"""Prismatic joint EKF (OMIP's, with the changes in docs/estimation.md#prismatic-filter)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.snapshot import SnapshotReader
from services.kinematics.config import KinematicsConfig
from services.kinematics.filters.geometry import (
    axis_basis,
    ekf_correct,
    excess_sigmas,
    gaussian_log_density,
    prismatic_twist_jacobian,
    rotate_axis,
    tangent_basis,
)
from services.kinematics.filters.whiteness import InnovationCorrelation

Array = NDArray[np.float64]

_I3 = np.eye(3)


class PrismaticJoint:
    """Prismatic joint EKF: the hand origin moves along a line, its orientation stays fixed.

    Nominal state: unit axis ``u`` (3,), its tangent basis ``B`` (3x2), joint value ``q`` [m], joint
    velocity ``qdot`` [m/s], and the offset ``o`` (3,) [m] of the hand position at q = 0 from the
    measured reference position. Error state and covariance ``P`` (7x7), in the order
    ``(b1, b2, q, qdot, o1, o2, o3)``, ``u(b) = Exp(u x (B b)) u`` (docs/estimation.md#axis-error-state).

    Measurement ``z`` (3,): displacement of the hand origin from the reference pose, in ``frame``
    [m] (OMIP strips the rotation of the delta instead, which is exact only for a camera-aligned
    hand frame; docs/estimation.md#prismatic-filter). Model ``h(x) = q u + o``,
    ``H = [q B, u, 0, I3]`` (3x7).

    Why ``o``: every measurement is relative to the same measured reference pose, so that pose's
    error is common to all of them. OMIP adds it to each frame's R as if it were independent, which
    biases the axis (the fitted line is forced through the noisy reference point). Here it is a
    constant state with the reference position's covariance as prior, and R holds only the current
    frame's noise. The published 4-D covariance is the ``(b1, b2, q, qdot)`` block.
    """

    dim = 7

    def __init__(self, config: KinematicsConfig, axis: Array, q: float, *, qdot: float = 0.0,
                 offset: Array | None = None, reference_covariance: Array | None = None,
                 P: Array | None = None, basis: Array | None = None) -> None:
        u = np.array(axis, dtype=float).reshape(3)
        self.u: Array = u / math.sqrt(float(u @ u))
        self.B: Array = tangent_basis(self.u) if basis is None else np.array(basis, dtype=float)
        self.q = float(q)
        self.qdot = float(qdot)
        self.o: Array = np.zeros(3) if offset is None else np.array(offset, dtype=float)
        if P is None:
            self.P: Array = np.zeros((7, 7))
            self.P[:4, :4] = config.prismatic_initial_variance * np.eye(4)
            if reference_covariance is not None:
                self.P[4:, 4:] = reference_covariance
        else:
            self.P = np.array(P, dtype=float)
        self._sa = config.prismatic_axis_noise_rad2_per_s3
        self._sq = config.prismatic_q_noise_m2_per_s3
        self._sqd = config.prismatic_qdot_noise_m2_per_s3
        self.y: Array = np.zeros(3)
        self.S: Array = np.eye(3)
        self.K: Array = np.zeros((7, 3))
        # Innovation whiteness and the published covariance's inflation from it
        # (docs/estimation.md#published-covariance).
        self.whiteness = InnovationCorrelation(3)
        self._inflation_scale = config.covariance_correlation_scale
        self._inflation_cap = config.max_covariance_inflation

    @classmethod
    def from_displacement(cls, config: KinematicsConfig, z: Array,
                          reference_covariance: Array | None = None) -> PrismaticJoint:
        """OMIP init from the displacement ``z`` (3,), ``|z| > 0``: ``u = z/|z|``, ``q0 = |z|``,
        ``qdot0 = 0``, ``P0 = s I4``; ``o = 0`` with prior ``reference_covariance`` (3x3)."""
        n = math.sqrt(float(z @ z))
        return cls(config, z / n, n, reference_covariance=reference_covariance)

    # ---------------------------------------------------------------------------- process

    def transition_matrix(self, dt: float) -> Array:
        """F (7x7): ``q <- q + dt qdot``; axis and ``qdot`` random walks, ``o`` constant."""
        F = np.eye(7)
        F[2, 3] = dt
        return F

    def process_noise(self, dt: float) -> Array:
        """Q (7x7): ``diag(sa, sa, sq) dt^3 / 3``, ``sqd dt``, 0 for ``o`` (OMIP's dt scaling)."""
        c = dt * dt * dt / 3.0
        Q = np.zeros((7, 7))
        Q[0, 0] = Q[1, 1] = self._sa * c
        Q[2, 2] = self._sq * c
        Q[3, 3] = self._sqd * dt
        return Q

    def predict(self, dt: float) -> None:
        """Propagate ``dt`` seconds: ``x- = f(x)``, ``P- = F P F^T + Q``."""
        self.q += dt * self.qdot  # q- = q + dt qdot
        P = self.P
        P[2, :] += dt * P[3, :]  # F P      (F = I + dt e_q e_qdot^T)
        P[:, 2] += dt * P[:, 3]  # (F P) F^T
        c = dt * dt * dt / 3.0
        P[0, 0] += self._sa * c  # + Q
        P[1, 1] += self._sa * c
        P[2, 2] += self._sq * c
        P[3, 3] += self._sqd * dt

    # ---------------------------------------------------------------------------- correction

    def measurement(self) -> Array:
        """Predicted displacement ``h(x) = q u + o`` (3,)."""
        return self.q * self.u + self.o

    def measurement_jacobian(self) -> Array:
        """H (3x7) = dh/d(b1, b2, q, qdot, o) = ``[q B, u, 0, I3]``."""
        q = self.q
        u0, u1, u2 = self.u.tolist()
        (b00, b01), (b10, b11), (b20, b21) = self.B.tolist()
        return np.array([[q * b00, q * b01, u0, 0.0, 1.0, 0.0, 0.0],
                         [q * b10, q * b11, u1, 0.0, 0.0, 1.0, 0.0],
                         [q * b20, q * b21, u2, 0.0, 0.0, 0.0, 1.0]])

    def update(self, z: Array, R: Array) -> None:
        """Correct with the displacement ``z`` (3,) [m] and its covariance ``R`` (3x3) [m^2]."""
        H = self.measurement_jacobian()
        y = z - self.measurement()  # y = z - h(x-)
        dx, self.P, self.S, self.K = ekf_correct(self.P, H, R, y)
        self.y = y
        self.whiteness.add(y, self.S)
        self.inject(dx)

    def inject(self, dx: Array) -> None:
        """Fold an error-state estimate ``dx = (b1, b2, dq, dqdot, do)`` into the nominal state."""
        self.u, self.B = rotate_axis(self.u, self.B, dx[:2])
        self.q += float(dx[2])
        self.qdot += float(dx[3])
        self.o = self.o + dx[4:]

    def covariance_inflation(self) -> float:
        """Variance factor of the published covariance: ``covariance_correlation_scale (1 + rho)
        / (1 - rho)`` for the lag-one autocorrelation ``rho`` of this filter's whitened
        innovations, in ``[1, max_covariance_inflation]``
        (docs/estimation.md#published-covariance)."""
        return self.whiteness.inflation(self._inflation_scale, self._inflation_cap)

    def log_likelihood(self) -> float:
        """``log N(y; 0, S)`` of the last innovation."""
        return gaussian_log_density(self.y, self.S)

    # ---------------------------------------------------------------------------- model

    def twist(self, q: float | None = None) -> Array:
        """Joint twist ``(q u, 0)`` (6,) at joint value ``q`` (default: the state's)."""
        h = np.zeros(6)
        h[:3] = (self.q if q is None else q) * self.u
        return h

    def reference_correction(self) -> Array:
        """Pose (4x4) taking the measured reference to the estimated one: translation by ``o``."""
        C = np.eye(4)
        C[:3, 3] = self.o
        return C

    def predicted_delta(self, q: float | None = None) -> tuple[Array, Array]:
        """Delta ``Exp((q u + o, 0))`` (4x4) from the measured reference pose at joint value ``q``,
        and its 6x6 left-perturbation covariance in ``frame``.

        With ``q=None`` the state's q is used and the covariance includes its variance; with an
        explicit ``q`` only the axis and offset uncertainty contribute. (A pure translation: the
        SE(3) left Jacobian is I.)
        """
        qv = self.q if q is None else float(q)
        J = np.zeros((6, 7))
        J[:, :4] = prismatic_twist_jacobian(self.u, self.B, qv)
        J[:3, 4:] = _I3
        if q is not None:
            J[:, 2] = 0.0
        cov = J @ self.P @ J.T
        T = np.eye(4)
        T[:3, 3] = qv * self.u + self.o
        return T, 0.5 * (cov + cov.T)

    def history_errors(self, d: Array, q: Array, d2_rotation: Array,
                       sigmas: float) -> tuple[Array, Array]:
        """Model-selection errors of samples against this joint at the joint values ``q`` (m,).

        ``d`` (m,3) hand displacements [m]; ``d2_rotation`` (m,) the squared Mahalanobis
        distances of the delta rotations' rotation vectors. The hypothesis displaces the hand by
        ``o + q_j u`` without rotating it: ``e_t = |d_j - o - q_j u|`` [m] (a fitted prediction:
        the whole residual counts) and, for the rotation, the same prediction as rigid's, so the
        same error: by how many sigmas it exceeds the rigid test (docs/estimation.md#rigid-test).
        """
        r = d - self.o - q[:, None] * self.u
        return np.sqrt(np.einsum("ij,ij->i", r, r)), excess_sigmas(d2_rotation, sigmas)

    # ---------------------------------------------------------------------------- snapshot

    def to_state(self) -> dict[str, Any]:
        """The complete filter state (arrays copied) for snapshots."""
        return {"axis": self.u.copy(), "basis": self.B.copy(), "q": self.q, "qdot": self.qdot,
                "offset": self.o.copy(), "P": self.P.copy(), "y": self.y.copy(),
                "S": self.S.copy(), "K": self.K.copy(),
                "innovation_correlation": self.whiteness.to_state()}

    @classmethod
    def from_state(cls, config: KinematicsConfig,
                   state: dict[str, Any] | SnapshotReader) -> PrismaticJoint:
        """Rebuild a filter from :meth:`to_state` exactly (no re-normalisation); SnapshotError
        naming the field for a value :meth:`to_state` cannot have written."""
        r = state if isinstance(state, SnapshotReader) else SnapshotReader(state, "prismatic")
        u = r.unit_vector("axis")
        f = cls(config, u, r.number("q"), qdot=r.number("qdot"), offset=r.array("offset", (3,)),
                P=r.covariance("P", 7), basis=axis_basis(r, u))
        f.u = u  # exact, not re-normalised
        f.y = r.array("y", (3,))
        f.S = r.covariance("S", 3)
        f.K = r.array("K", (7, 3))
        f.whiteness = InnovationCorrelation.from_state(3, r.map("innovation_correlation"))
        return f
