"""Revolute joint EKF (OMIP's, with the changes in docs/estimation.md#revolute-filter)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import skew
from services.common.snapshot import SnapshotReader
from services.kinematics.config import KinematicsConfig
from services.kinematics.filters.geometry import (
    axis_basis,
    cross3,
    ekf_correct,
    gaussian_log_density,
    revolute_delta,
    revolute_measurement_jacobian,
    revolute_twist,
    rotate_axis,
    rotation_angles_from_trace,
    se3_exp_fast,
    se3_inverse_fast,
    se3_log_fast,
    tangent_basis,
)
from services.kinematics.filters.whiteness import InnovationCorrelation

Array = NDArray[np.float64]

# Index ranges of the error state (b1, b2, c1, c2, q, qdot, e1..e6).
_AXIS = slice(0, 2)
_POINT = slice(2, 4)
_Q = 4
_QDOT = 5
_REF = slice(6, 12)


class RevoluteJoint:
    """Revolute joint EKF: the hand rotates about a fixed line.

    Nominal state: unit axis ``u`` (3,) with its right-handed tangent basis ``B = [t1 t2]`` (3x2,
    ``t2 = u x t1``), point ``p`` (3,) [m] on the axis with ``p . u = 0`` (the point closest to the
    frame origin), joint value ``q`` [rad] (unbounded, right-handed about ``u``), ``qdot``
    [rad/s], and the reference correction ``E`` (4x4): the estimated true hand pose at q = 0 is
    ``E @ T_ref_measured``.

    Error state and covariance ``P`` (12x12), order ``(b1, b2, c1, c2, q, qdot, e1..e6)``:
    ``u(b) = Exp(u x (B b)) u``; ``p(c) = p + B c``, a 2-D point error in the plane
    orthogonal to the axis (instead of projecting a 3-D one; after an axis update
    ``p`` is re-projected onto the new plane, a change along ``u`` that ``h`` does not see);
    ``E = Exp(e) E_hat`` (left perturbation, linear first). The published 7x7 covariance of
    ``(b1, b2, px, py, pz, q, qdot)`` is mapped from the leading 6x6 block (``p = B c``).

    Measurement ``z``: the delta ``D = T(t) T_ref_measured^-1`` (4x4) with the current pose's
    covariance ``R`` (6x6, left perturbation in ``frame``). Model ``D = Exp(h) E`` with
    ``h = q (p x u, u)``. Innovation on the group: ``y = log(D (Exp(h) E)^-1)``, so ``q``
    passes pi and 2 pi continuously and ``qdot`` keeps its sign. ``H`` (6x12): see
    :func:`~services.kinematics.filters.geometry.revolute_measurement_jacobian`.

    Why ``E``: the reference pose's error is common to every measurement (see
    :class:`~services.kinematics.filters.prismatic.PrismaticJoint`); OMIP folds it into each
    frame's R as independent noise instead.
    """

    dim = 12

    def __init__(self, config: KinematicsConfig, axis: Array, point: Array, q: float, *,
                 qdot: float = 0.0, reference_correction: Array | None = None,
                 reference_covariance: Array | None = None, P: Array | None = None,
                 basis: Array | None = None) -> None:
        u = np.array(axis, dtype=float).reshape(3)
        self.u: Array = u / math.sqrt(float(u @ u))
        self.B: Array = tangent_basis(self.u) if basis is None else np.array(basis, dtype=float)
        p = np.array(point, dtype=float).reshape(3)
        self.p: Array = p - float(p @ self.u) * self.u
        self.q = float(q)
        self.qdot = float(qdot)
        self.E: Array = (np.eye(4) if reference_correction is None
                         else np.array(reference_correction, dtype=float))
        if P is None:
            self.P: Array = np.zeros((12, 12))
            self.P[:6, :6] = config.revolute_initial_variance * np.eye(6)
            if reference_covariance is not None:
                self.P[_REF, _REF] = reference_covariance
        else:
            self.P = np.array(P, dtype=float)
        self._sa = config.revolute_axis_noise_rad2_per_s3
        self._sp = config.revolute_point_noise_m2_per_s3
        self._sq = config.revolute_q_noise_rad2_per_s3
        self._sqd = config.revolute_qdot_noise_rad2_per_s3
        self.y: Array = np.zeros(6)
        self.S: Array = np.eye(6)
        self.K: Array = np.zeros((12, 6))
        # Innovation whiteness and the published covariance's inflation from it
        # (docs/estimation.md#published-covariance).
        self.whiteness = InnovationCorrelation(6)
        self._inflation_scale = config.covariance_correlation_scale
        self._inflation_cap = config.max_covariance_inflation

    @classmethod
    def from_twist(cls, config: KinematicsConfig, z: Array,
                   reference_covariance: Array | None = None) -> RevoluteJoint:
        """OMIP init from ``z = log D = (v, w)``, ``|w| > 0``: ``u = w/|w|``, ``q0 = |w|``,
        ``p0 = w x v / |w|^2`` (the screw axis point closest to the origin), ``qdot0 = 0``,
        ``P0 = s I`` (axis, point, q, qdot), ``E = I`` with prior ``reference_covariance`` (6x6)."""
        v, w = z[:3], z[3:]
        n2 = float(w @ w)
        return cls(config, w / math.sqrt(n2), cross3(w, v) / n2, math.sqrt(n2),
                   reference_covariance=reference_covariance)

    # ---------------------------------------------------------------------------- process

    def transition_matrix(self, dt: float) -> Array:
        """F (12x12): ``q <- q + dt qdot``; axis, point, ``qdot`` random walks, ``E`` constant."""
        F = np.eye(12)
        F[_Q, _QDOT] = dt
        return F

    def process_noise(self, dt: float) -> Array:
        """Q (12x12): axis ``sa``, point ``sp``, q ``sq`` (all times ``dt^3/3``), qdot ``sqd dt``,
        0 for ``E`` (OMIP's dt scaling; the point noise lies in the plane orthogonal to the axis)."""
        c = dt * dt * dt / 3.0
        Q = np.zeros((12, 12))
        Q[0, 0] = Q[1, 1] = self._sa * c
        Q[2, 2] = Q[3, 3] = self._sp * c
        Q[_Q, _Q] = self._sq * c
        Q[_QDOT, _QDOT] = self._sqd * dt
        return Q

    def predict(self, dt: float) -> None:
        """Propagate ``dt`` seconds: ``x- = f(x)``, ``P- = F P F^T + Q``."""
        self.q += dt * self.qdot  # q- = q + dt qdot
        P = self.P
        P[_Q, :] += dt * P[_QDOT, :]  # F P      (F = I + dt e_q e_qdot^T)
        P[:, _Q] += dt * P[:, _QDOT]  # (F P) F^T
        c = dt * dt * dt / 3.0
        P[0, 0] += self._sa * c  # + Q
        P[1, 1] += self._sa * c
        P[2, 2] += self._sp * c
        P[3, 3] += self._sp * c
        P[_Q, _Q] += self._sq * c
        P[_QDOT, _QDOT] += self._sqd * dt

    # ---------------------------------------------------------------------------- correction

    def twist(self, q: float | None = None) -> Array:
        """Joint twist ``q (p x u, u)`` (6,) at joint value ``q`` (default: the state's)."""
        return revolute_twist(self.u, self.p, self.q if q is None else float(q))

    def measurement(self) -> Array:
        """Predicted delta ``Exp(h(x)) E`` (4x4)."""
        return revolute_delta(self.u, self.p, self.q) @ self.E

    def measurement_jacobian(self) -> Array:
        """H (6x12) of the group residual at the prediction."""
        return revolute_measurement_jacobian(self.u, self.p, self.B, self.q)[0]

    def residual(self, z: Array) -> Array:
        """Group innovation ``y = log(z (Exp(h) E)^-1)`` (6,) for the measured delta ``z`` (4x4)."""
        return se3_log_fast(z @ se3_inverse_fast(self.measurement()))

    def update(self, z: Array, R: Array) -> None:
        """Correct with the measured delta ``z`` (4x4) and its left-perturbation covariance ``R``."""
        H, Ex = revolute_measurement_jacobian(self.u, self.p, self.B, self.q)
        y = se3_log_fast(z @ se3_inverse_fast(Ex @ self.E))  # y = log(z (Exp(h) E)^-1)
        dx, self.P, self.S, self.K = ekf_correct(self.P, H, R, y)
        self.y = y
        self.whiteness.add(y, self.S)
        self.inject(dx)

    def inject(self, dx: Array) -> None:
        """Fold ``dx = (b1, b2, c1, c2, dq, dqdot, de)`` into the nominal state.

        ``p + B c`` is re-projected onto the plane orthogonal to the new axis.
        """
        p = self.p + self.B @ dx[_POINT]
        self.u, self.B = rotate_axis(self.u, self.B, dx[_AXIS])
        self.p = p - float(p @ self.u) * self.u
        self.q += float(dx[_Q])
        self.qdot += float(dx[_QDOT])
        self.E = se3_exp_fast(dx[_REF]) @ self.E

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

    def reference_correction(self) -> Array:
        """Pose ``E`` (4x4): the estimated hand pose at q = 0 is ``E @ T_ref_measured``."""
        return self.E.copy()

    def parameter_covariance(self) -> Array:
        """Covariance (7x7) of ``(b1, b2, px, py, pz, q, qdot)`` in this filter's basis ``B``."""
        G = np.zeros((7, 6))
        G[0, 0] = G[1, 1] = 1.0
        G[2:5, 2:4] = self.B  # p = p_hat + B c
        G[5, 4] = G[6, 5] = 1.0
        C = G @ self.P[:6, :6] @ G.T
        return 0.5 * (C + C.T)

    def predicted_delta(self, q: float | None = None) -> tuple[Array, Array]:
        """Delta ``Exp(q (p x u, u)) E`` (4x4) from the measured reference pose at joint value ``q``,
        and its 6x6 left-perturbation covariance in ``frame``.

        With ``q=None`` the state's q is used and the covariance includes its variance; with an
        explicit ``q`` only the axis, point and reference uncertainty contribute.
        """
        qv = self.q if q is None else float(q)
        J, Ex = revolute_measurement_jacobian(self.u, self.p, self.B, qv)
        if q is not None:
            J[:, _Q] = 0.0
        cov = J @ self.P @ J.T
        return Ex @ self.E, 0.5 * (cov + cov.T)

    def history_errors(self, d: Array, R_flat: Array, trace: Array, q: Array,
                       reference_position: Array) -> tuple[Array, Array]:
        """OMIP's model-selection errors of samples against this joint at the joint values ``q`` (m,).

        ``d`` (m,3) hand displacements from ``reference_position`` ``c0`` (3,) [m]; ``R_flat`` (m,9)
        row-major delta rotations (``trace`` unused here). The hypothesis puts the hand at
        ``Exp(h_j) E c0``: with ``K = [u]x``, ``R_q = I + sin(q) K + (1 - cos q) K^2``, ``c0' = E c0``
        and ``a = c0' - p``, its displacement is ``(c0' - c0) + sin(q) K a + (1 - cos q) K^2 a``;
        ``e_t = |d_j - that|``. Its rotation is ``R_q R_E``, so
        ``cos e_r = (<R_j, R_E> + sin(q) <R_j, K R_E> + (1 - cos q) <R_j, K^2 R_E> - 1) / 2``.
        """
        K = skew(self.u)
        K2 = K @ K
        RE = self.E[:3, :3]
        c0t = RE @ reference_position + self.E[:3, 3]
        a = c0t - self.p
        s = np.sin(q)
        c = 1.0 - np.cos(q)
        r = d - (c0t - reference_position) - np.outer(s, K @ a) - np.outer(c, K2 @ a)
        V = np.empty((9, 3))
        V[:, 0] = RE.ravel()
        V[:, 1] = (K @ RE).ravel()
        V[:, 2] = (K2 @ RE).ravel()
        G = R_flat @ V  # (m, 3) Frobenius products
        tr = G[:, 0] + s * G[:, 1] + c * G[:, 2]
        return np.sqrt(np.einsum("ij,ij->i", r, r)), rotation_angles_from_trace(tr)

    # ---------------------------------------------------------------------------- snapshot

    def to_state(self) -> dict[str, Any]:
        """The complete filter state (arrays copied) for snapshots."""
        return {"axis": self.u.copy(), "basis": self.B.copy(), "point": self.p.copy(),
                "q": self.q, "qdot": self.qdot, "reference_correction": self.E.copy(),
                "P": self.P.copy(), "y": self.y.copy(), "S": self.S.copy(), "K": self.K.copy(),
                "innovation_correlation": self.whiteness.to_state()}

    @classmethod
    def from_state(cls, config: KinematicsConfig,
                   state: dict[str, Any] | SnapshotReader) -> RevoluteJoint:
        """Rebuild a filter from :meth:`to_state` exactly (no re-normalisation); SnapshotError
        naming the field for a value :meth:`to_state` cannot have written."""
        r = state if isinstance(state, SnapshotReader) else SnapshotReader(state, "revolute")
        u = r.unit_vector("axis")
        p = r.array("point", (3,))
        f = cls(config, u, p, r.number("q"), qdot=r.number("qdot"),
                reference_correction=r.pose("reference_correction"), P=r.covariance("P", 12),
                basis=axis_basis(r, u))
        f.u = u  # exact, not re-normalised or re-projected
        f.p = p
        f.y = r.array("y", (6,))
        f.S = r.covariance("S", 6)
        f.K = r.array("K", (12, 6))
        f.whiteness = InnovationCorrelation.from_state(6, r.map("innovation_correlation"))
        return f
