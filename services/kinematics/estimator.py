"""Online kinematic-model estimator: hand body poses in, a :class:`KinematicModel` out.

:meth:`KinematicEstimator.update` returns an :class:`UpdateResult`: the new model (the wire type,
with ``seq`` 0: a publisher stamps its own with ``dataclasses.replace``) or why it rejected the input.

Input per frame: ``stamp_ns`` (int, ns), ``T_frame_hand`` (4x4 pose of the hand body in ``frame``,
the camera or world frame; the environment is static with pose I) and the 6x6 covariance of its left
perturbation ``T = Exp(delta) T_hat`` (delta linear first, in ``frame``) [m^2, rad^2].
``T_frame_hand`` must be rigid; it is checked where it enters handkse (the protocol decodes HandBody
with :func:`services.common.se3.check_pose`; the evaluation passes the tracker's poses), not here:
``update`` checks what protects its state (stamp type and order, shapes, finiteness, variances >= 0).

Per accepted frame (docs/estimation.md#update-loop and the sections before it):

1. Measurement (OMIP's with RRB = I): ``D = T(t) T(t0)^-1``, and for the prismatic filter the
   displacement ``t(t) - t(t0)`` of the hand origin (docs/estimation.md#prismatic-filter). ``T(t0)`` is the
   measured reference pose, the first accepted pose of the demonstration.
2. Each started joint filter predicts once with the true ``dt`` (capped at
   ``max_prediction_dt_s`` after a loss of tracking) and corrects with
   ``R = f Sigma + floor I`` (OMIP's factors ``f``, plus a floor). ``Sigma`` is the current pose's
   covariance only (``Sigma(t)``, or ``G Sigma(t) G^T`` with ``G = [I, -[t]x]`` for the
   displacement): the reference pose's error is common to all measurements, so each filter carries it
   as a state with prior ``Sigma(t0)`` instead of adding ``Ad(D) Sigma(t0) Ad(D)^T`` to every R as OMIP
   does (which biases the axis; see the filters). The rigid hypothesis' diagnostic innovation
   covariance is ``Sigma(t) + Sigma(t0) + floor I`` (OMIP's formula with its own prediction D = I).
   A joint filter starts (OMIP init from the current measurement) only once the hand moved at least
   ``prismatic_min_translation_m`` / rotated ``revolute_min_rotation_rad`` from the reference, and that
   motion is at least ``min_motion_sigmas`` standard deviations of its noise (the prismatic filter
   also provisionally at ``prismatic_min_motion_sigmas``, once the displacement has been beyond the
   rigid test for ``prismatic_min_motion_s``; it restarts at ``min_motion_sigmas``). While the
   rotation is significant but still below ``revolute_min_rotation_rad``, a started prismatic filter
   alone does not make the type known: a revolute joint cannot be ruled out before its filter runs.
3. The sample, the joint values and the rigid test (the squared Mahalanobis distances of the
   displacement and of the rotation vector against their covariances, docs/estimation.md#rigid-test)
   enter the bounded history, and model selection scores the four types
   (:mod:`services.kinematics.selection`).

Output canonicalisation (docs/estimation.md#output-canonicalisation): internally the sign of an
axis is fixed by the first motion (so
``q`` starts positive and stays continuous). The published axis is flipped, for output only, so that
its component of largest magnitude is positive (lowest index on ties); ``q`` and ``dq`` are negated
with it and the covariance is re-expressed in :func:`~services.kinematics.filters.tangent_basis` of
the published axis. ``(axis, q)`` and ``(-axis, -q)`` describe the same motion; this way a physical
axis is always published with the same direction, whichever way it was demonstrated.

``reference_pose`` is the estimated hand pose at q = 0 under the published type: the measured first
pose corrected by that joint filter's reference-error estimate (mm-level), or the measured first pose
for rigid, disconnected and unknown. ``predict_hand_pose`` reproduces the hand pose from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import (
    FRAME_IDS,
    KinematicModel,
    ProtocolError,
)
from services.common.snapshot import SnapshotError, SnapshotReader
from services.common.stamps import INT64_MAX
from services.kinematics.config import KinematicsConfig
from services.kinematics.filters import (
    JOINT_TYPES,
    DisconnectedJoint,
    PrismaticJoint,
    RevoluteJoint,
    RigidJoint,
    prismatic_noise_inflation,
    revolute_noise_inflation,
)
from services.kinematics.filters.geometry import (
    adjoint_fast,
    cross3,
    mahalanobis2_3,
    se3_exp_fast,
    se3_inverse_fast,
    se3_log_fast,
    so3_log_fast,
)
from services.kinematics.filters.whiteness import InnovationCorrelation
from services.kinematics.prediction import predict_hand_pose, predicted_pose
from services.kinematics.published import prismatic_params, revolute_params
from services.kinematics.selection import ModelSelector

Array = NDArray[np.float64]

SNAPSHOT_VERSION = 4

RejectReason = Literal["invalid_stamp", "invalid_value", "bad_shape", "non_finite",
                       "invalid_covariance", "duplicate_stamp", "out_of_order", "outlier"]
REJECT_REASONS: tuple[RejectReason, ...] = get_args(RejectReason)

_I3 = np.eye(3)
_I6 = np.eye(6)


@dataclass(frozen=True)
class UpdateResult:
    """What one :meth:`KinematicEstimator.update` did: ``model`` after an accepted pose, else None
    and ``reason`` says why it was rejected (the estimate is then unchanged). ``note``: for an
    outlier how far it was; for an accepted pose, why the outlier policy let it in (the gate
    yielded, or the demonstration restarted; docs/estimation.md#input-gates), else empty."""

    model: KinematicModel | None
    reason: RejectReason | None = None
    note: str = field(default="", compare=False)


def _mahalanobis2(e: Array, S: Array) -> float:
    """``e^T S^-1 e``; infinite when ``S`` is singular (nothing is inside a degenerate gate)."""
    try:
        return float(e @ np.linalg.solve(S, e))
    except np.linalg.LinAlgError:
        return math.inf


def chi2_quantile_of_sigmas(sigmas: float, dof: int) -> float:
    """The squared Mahalanobis distance that a ``dof``-dimensional Gaussian exceeds as rarely as a
    1-D one exceeds ``sigmas`` standard deviations: ``x`` with ``P(chi2_dof > x) = erfc(sigmas /
    sqrt 2)``. ``dof`` even, so the survival function is ``exp(-x/2) sum_{i < dof/2} (x/2)^i / i!``
    (solved by bisection on ``log``, exact to 1e-12 relative)."""
    if dof < 2 or dof % 2:
        raise ValueError(f"dof must be even and >= 2, got {dof}")
    x = sigmas / math.sqrt(2.0)
    if x < 20.0:
        log_p = math.log(math.erfc(x))
    else:  # erfc underflows: its asymptotic series (relative error below 1e-9 here)
        x2 = x * x
        log_p = (-x2 - math.log(x * math.sqrt(math.pi))
                 + math.log1p(-0.5 / x2 + 0.75 / (x2 * x2) - 1.875 / (x2 * x2 * x2)))

    def log_sf(x: float) -> float:
        h = 0.5 * x
        term, total = 1.0, 1.0
        for i in range(1, dof // 2):
            term *= h / i
            total += term
        return -h + math.log(total)

    lo, hi = 0.0, 1.0
    while log_sf(hi) > log_p:
        hi *= 2.0
    while hi - lo > 1e-12 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if log_sf(mid) > log_p else (lo, mid)
    return 0.5 * (lo + hi)


def translation_jacobian(position: Array) -> Array:
    """Jacobian (3x6) of a pose's translation w.r.t. its left perturbation: ``[I, -[t]x]``."""
    x, y, z = position.tolist()
    return np.array([[1.0, 0.0, 0.0, 0.0, z, -y],
                     [0.0, 1.0, 0.0, -z, 0.0, x],
                     [0.0, 0.0, 1.0, y, -x, 0.0]])


class KinematicEstimator:
    """Joint EKFs (rigid, prismatic, revolute, disconnected) and model selection, online.

    ``update`` never raises on bad input: it rejects malformed or non-finite poses/covariances,
    duplicate or out-of-order stamps and outliers (docs/estimation.md#input-gates), says why in its
    :class:`UpdateResult` and keeps its estimate; counting is the caller's. No I/O, no clock: time
    comes only from the stamps (how far ahead a stamp may be is the service's check,
    :mod:`services.common.stamps`).
    """

    def __init__(self, config: KinematicsConfig | None = None, frame_id: str = "camera") -> None:
        if frame_id not in FRAME_IDS:
            raise ValueError(f"frame_id must be one of {FRAME_IDS}, got {frame_id!r}")
        self.config = KinematicsConfig() if config is None else config
        self.frame_id = frame_id
        self._floor3 = self.config.measurement_noise_floor * _I3
        self._floor6 = self.config.measurement_noise_floor * _I6
        self._gate_d2 = chi2_quantile_of_sigmas(self.config.outlier_gate_sigmas, 6)
        self._restart_d2 = chi2_quantile_of_sigmas(self.config.revolute_restart_sigmas, 2)
        self._run_ns = round(self.config.outlier_run_s * 1e9)
        self.reset()

    # ---------------------------------------------------------------------------------- state

    def reset(self) -> None:
        """Forget the demonstration: the next accepted pose becomes the new reference (t0)."""
        cfg = self.config
        self._T0: Array | None = None
        self._T0_inv: Array = np.eye(4)
        self._Sigma0: Array = np.zeros((6, 6))
        self._Sigma0_floored: Array = np.zeros((6, 6))
        self._Sigma0_disp: Array = np.zeros((3, 3))
        self._stamp0 = 0
        self._last_stamp: int | None = None
        self._updates = 0
        self._rigid = RigidJoint()
        self._disconnected = DisconnectedJoint()
        self._prismatic: PrismaticJoint | None = None
        self._revolute: RevoluteJoint | None = None
        self._rotation_pending = False
        # Whether the reference pose is final: the hand moved, or a joint filter started
        # (docs/estimation.md#reference-refinement).
        self._reference_fixed = False
        self._still_whiteness = InnovationCorrelation(6)
        # Still poses (stamp, T, Sigma) not yet fused into the reference, oldest first.
        self._still_poses: list[tuple[int, Array, Array]] = []
        self._beyond_since: int | None = None  # first stamp of the current run beyond the test
        # The rotation angle [rad] at which the revolute filter's axis is next checked against
        # the delta's (docs/estimation.md#filter-start).
        self._revolute_check_rad = math.inf
        # The prismatic filter started below min_motion_sigmas, and the stamp since which the
        # displacement has been above prismatic_min_motion_sigmas (docs/estimation.md#filter-start).
        self._prismatic_provisional = False
        self._displaced_since: int | None = None
        # Outlier gate (docs/estimation.md#input-gates): the innovation (6,) of the last accepted
        # pose against the joint prediction and that pose's covariance (None unless the model was
        # prismatic or revolute), the number of consecutive outliers, the stamp of the first, and
        # whether the gate yields to them.
        self._innovation: tuple[Array, Array] | None = None
        self._outliers = 0
        self._outliers_since = 0
        self._gate_yields = False
        self._selector = ModelSelector(cfg)
        self._log_scores: Array = np.array([
            math.log(p) if p > 0.0 else -math.inf
            for p in (cfg.prior_rigid, cfg.prior_prismatic, cfg.prior_revolute,
                      cfg.prior_disconnected)])
        self._model = self._make_model()

    @property
    def model(self) -> KinematicModel:
        """The current model: the one of the last accepted update (``updates`` 0 before any)."""
        return self._model

    @property
    def prismatic(self) -> PrismaticJoint | None:
        """The prismatic filter once started (internal sign convention, not canonicalised)."""
        return self._prismatic

    @property
    def revolute(self) -> RevoluteJoint | None:
        """The revolute filter once started (internal sign convention, not canonicalised)."""
        return self._revolute

    @property
    def rigid(self) -> RigidJoint:
        return self._rigid

    @property
    def disconnected(self) -> DisconnectedJoint:
        return self._disconnected

    @property
    def selector(self) -> ModelSelector:
        return self._selector

    @property
    def log_scores(self) -> Array:
        """Unnormalised log scores (4,) of ``JOINT_TYPES`` from the last update."""
        return self._log_scores.copy()

    @property
    def measured_reference_pose(self) -> Array | None:
        """The measured reference pose ``T(t0)`` (4x4), None before the first update."""
        return None if self._T0 is None else self._T0.copy()

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the last accepted pose of this demonstration, None before one."""
        return self._last_stamp

    @property
    def gate_yields(self) -> bool:
        """Whether the joint gate currently yields to a run of outliers (a regrasp, or a model
        that no longer explains the hand; docs/estimation.md#input-gates)."""
        return self._gate_yields

    # ---------------------------------------------------------------------------------- input

    def _check(self, stamp_ns: Any, T: Any, cov: Any) -> tuple[RejectReason | None, Array, Array]:
        """The guards that keep the state sound (see the module docstring for what is not
        checked here); returns ``(reason or None, T, Sigma)`` with Sigma symmetrised."""
        empty = _I3
        if (isinstance(stamp_ns, bool) or not isinstance(stamp_ns, (int, np.integer))
                or not 0 <= int(stamp_ns) <= INT64_MAX):
            return "invalid_stamp", empty, empty
        try:
            T = np.asarray(T, dtype=float)
            cov = np.asarray(cov, dtype=float)
        except (TypeError, ValueError):
            return "invalid_value", empty, empty
        if T.shape != (4, 4) or cov.shape != (6, 6):
            return "bad_shape", empty, empty
        if not (math.isfinite(float(T.sum())) and math.isfinite(float(cov.sum()))):
            return "non_finite", empty, empty
        cov = (cov + cov.T) * 0.5
        if min(cov.diagonal().tolist()) < 0.0:
            return "invalid_covariance", empty, empty
        if self._last_stamp is not None:
            if int(stamp_ns) == self._last_stamp:
                return "duplicate_stamp", empty, empty
            if int(stamp_ns) < self._last_stamp:
                return "out_of_order", empty, empty
        return None, T, cov

    # ---------------------------------------------------------------------------------- update

    def update(self, stamp_ns: int, T_frame_hand: Array, pose_covariance: Array) -> UpdateResult:
        """Absorb one hand body pose; the result holds the new model, or why it was rejected.

        ``stamp_ns`` [ns] strictly increasing; ``T_frame_hand`` (4x4) rigid, in ``frame``;
        ``pose_covariance`` (6x6) of the left perturbation in ``frame``, linear first.
        """
        reason, T, Sigma = self._check(stamp_ns, T_frame_hand, pose_covariance)
        if reason is not None:
            return UpdateResult(model=None, reason=reason)
        stamp = int(stamp_ns)
        position = T[:3, 3]
        note = ""
        if self._T0 is not None:
            outlier, e = self._outlier(stamp, T, Sigma)
            if outlier is None:
                self._outliers = 0
                self._gate_yields = False
            else:
                far, why = outlier
                if not self._outliers:
                    self._outliers_since = stamp
                self._outliers += 1
                run = (self._outliers >= self.config.outlier_run_count
                       and stamp - self._outliers_since >= self._run_ns)
                if not run:
                    return UpdateResult(model=None, reason="outlier", note=why)
                note = (f"{self._outliers} consecutive outliers over "
                        f"{(stamp - self._outliers_since) * 1e-9:.3g} s ({why})")
                if far:
                    self.reset()  # the reference was the outlier, or the hand is elsewhere now
                    note = f"demonstration restarted after {note}"
                elif not self._gate_yields:
                    self._gate_yields = True
                    note = f"outlier gate yields after {note}"
                else:
                    note = ""
            self._innovation = None if e is None else (e, Sigma)
        if self._T0 is None:
            self._set_reference(T, Sigma, stamp)
            self._selector.add(np.zeros(3), _I3, 0.0, 0.0)
            self._updates = 1
            self._log_scores = self._selector.log_scores(None, None, position, position)
            self._model = self._make_model()
            return UpdateResult(model=self._model, note=note)

        cfg = self.config
        dt = (stamp - self._last_stamp) * 1e-9 if self._last_stamp is not None else 0.0
        dt = min(dt, cfg.max_prediction_dt_s)
        self._last_stamp = stamp
        T0 = self._T0

        # 1. Measurements: D = T T0^-1 and the hand displacement.
        D = T @ self._T0_inv
        R_D = D[:3, :3]
        disp = position - T0[:3, 3]
        disp_norm = math.sqrt(float(disp @ disp))
        # Innovation covariance of the rigid hypothesis (true delta I): Sigma + Sigma0 + floor I.
        self._rigid.update(D, Sigma + self._Sigma0_floored)
        self._disconnected.update(D, Sigma)

        # The rigid test and the filter starts (docs/estimation.md#rigid-test): squared Mahalanobis
        # distances of the displacement and of the rotation vector against their covariances,
        # the current pose's plus the reference's (rotated with the delta).
        G = translation_jacobian(position)
        Sigma_disp = G @ Sigma @ G.T
        w = so3_log_fast(R_D)
        d2_disp = mahalanobis2_3(disp, Sigma_disp + self._Sigma0_disp + self._floor3)
        d2_rot = mahalanobis2_3(
            w, Sigma[3:, 3:] + R_D @ self._Sigma0[3:, 3:] @ R_D.T + self._floor3)  # OMIP's Sigma_z

        # 2. Joint filters: predict once with the true dt, then correct (or start).
        confirmed = d2_disp >= cfg.min_motion_sigmas ** 2
        persists = self._displacement_persists(stamp, d2_disp)
        if self._prismatic is not None and not (self._prismatic_provisional and confirmed):
            f = prismatic_noise_inflation(disp_norm, cfg)
            self._prismatic.predict(dt)
            self._prismatic.update(disp, f * Sigma_disp + self._floor3)  # R = f Sigma + floor I
        elif disp_norm >= cfg.prismatic_min_translation_m and (
                confirmed or (persists and d2_disp >= cfg.prismatic_min_motion_sigmas ** 2)):
            # A start, or the restart of a provisional filter: its axis came from weaker evidence,
            # and an EKF does not recover from an axis far off (docs/estimation.md#filter-start).
            self._prismatic = PrismaticJoint.from_displacement(cfg, disp, self._Sigma0_disp)
            self._prismatic_provisional = not confirmed
            self._selector.history.backfill_prismatic(self._prismatic.u)
        angle = math.sqrt(float(w @ w))
        if self._revolute is not None:
            f = revolute_noise_inflation(angle, cfg)
            self._revolute.predict(dt)
            self._revolute.update(D, f * Sigma + self._floor6)  # R = f Sigma + floor I
            if angle >= self._revolute_check_rad:
                # The rotation grew: is the filter's axis still consistent with this delta's?
                self._revolute_check_rad = angle * cfg.revolute_recheck_growth
                if self._revolute_axis_d2(w, R_D, Sigma) > self._restart_d2:
                    self._start_revolute(D, angle)
        else:
            significant = d2_rot >= cfg.min_motion_sigmas ** 2
            if significant and angle >= cfg.revolute_min_rotation_rad:
                self._start_revolute(D, angle)
            # A significant rotation below the start threshold: a revolute joint cannot be ruled
            # out before its filter runs, so no type is published meanwhile (_type_known).
            self._rotation_pending = significant and self._revolute is None

        # 3. History and model selection.
        self._selector.add(disp, R_D,
                           0.0 if self._prismatic is None else self._prismatic.q,
                           0.0 if self._revolute is None else self._revolute.q,
                           d2_disp, d2_rot)
        self._log_scores = self._selector.log_scores(self._prismatic, self._revolute, position,
                                                     T0[:3, 3], (stamp - self._stamp0) * 1e-9)

        # 4. Reference refinement: while the hand has not moved, this pose measures the
        # reference pose too (docs/estimation.md#reference-refinement).
        if not self._reference_fixed:
            k2 = cfg.reference_still_sigmas ** 2
            beyond = d2_disp > k2 or d2_rot > k2
            if beyond:
                self._still_poses.clear()  # the slow start of a motion may be among them
                if self._beyond_since is None:
                    self._beyond_since = stamp
            else:
                self._beyond_since = None
            if (not cfg.refine_reference_while_still or self._prismatic is not None
                    or self._revolute is not None or (
                        self._beyond_since is not None
                        and (stamp - self._beyond_since) * 1e-9 >= cfg.prismatic_min_motion_s)):
                self._reference_fixed = True  # the hand moved: the displacement persists
                self._still_poses.clear()
            elif not beyond:
                # A pose is fused once it is reference_fusion_lag_s old and the hand stayed still
                # since: the start of a motion stays inside the test for a while.
                self._still_poses.append((stamp, T, Sigma))
                lag_ns = round(cfg.reference_fusion_lag_s * 1e9)
                while self._still_poses and self._still_poses[0][0] <= stamp - lag_ns:
                    _, T_still, Sigma_still = self._still_poses.pop(0)
                    self._refine_reference(T_still @ self._T0_inv, Sigma_still)
        self._updates += 1
        self._model = self._make_model()
        return UpdateResult(model=self._model, note=note)

    def _outlier(self, stamp: int, T: Array, Sigma: Array,
                 ) -> tuple[tuple[bool, str] | None, Array | None]:
        """``((far, why) or None, e)``: whether the pose is an outlier, and its innovation ``e``
        (6,) against the joint prediction (None unless the model is prismatic or revolute).

        ``far``: more than ``max_hand_displacement_m`` from the reference pose. Otherwise, once the
        joint model is confident, the pose is an outlier when its innovation ``e`` is outside the
        gate (``e^T S^-1 e``, :meth:`_innovation_covariance`) **and** jumped from the innovation
        ``e'`` of the last accepted pose by more than the gate (``(e - e')^T (S + Sigma')^-1
        (e - e')``, ``Sigma'`` that pose's covariance): a hand that drifts away from the predicted
        motion moves its innovation a little per frame and is let through (the evidence that the
        model is wrong), a pose that jumps is not (docs/estimation.md#input-gates)."""
        cfg = self.config
        assert self._T0 is not None
        d = T[:3, 3] - self._T0[:3, 3]
        dist = math.sqrt(float(d @ d))
        if dist > cfg.max_hand_displacement_m:
            return (True, f"{dist:.3g} m from the first pose of the demonstration (limit "
                          f"kinematics.max_hand_displacement_m = {cfg.max_hand_displacement_m:g})"
                    ), None
        model = self._model
        if model.type not in ("prismatic", "revolute"):
            return None, None
        dt = min((stamp - model.stamp_ns) * 1e-9, cfg.max_prediction_dt_s)
        stamp_pred = model.stamp_ns + round(dt * 1e9)
        T_pred = predicted_pose(model, stamp_pred)
        if T_pred is None:
            return None, None
        e = se3_log_fast(T @ se3_inverse_fast(T_pred))
        if model.probabilities[model.type] < cfg.outlier_gate_min_probability:
            return None, e
        # S >= Sigma + floor I, so e^T (Sigma + floor I)^-1 e bounds the distance from above: the
        # common case, a pose well inside the gate, needs no propagated covariance.
        if _mahalanobis2(e, Sigma + self._floor6) <= self._gate_d2:
            return None, e
        S = self._innovation_covariance(stamp_pred, dt, Sigma)
        d2 = _mahalanobis2(e, S)
        if d2 <= self._gate_d2:
            return None, e
        if self._innovation is not None:
            e_last, Sigma_last = self._innovation
            if _mahalanobis2(e - e_last, S + Sigma_last) <= self._gate_d2:
                return None, e
        return (False, f"Mahalanobis distance {math.sqrt(d2):.3g} from the {model.type} "
                       f"prediction (gate {math.sqrt(self._gate_d2):.3g}, "
                       f"kinematics.outlier_gate_sigmas = {cfg.outlier_gate_sigmas:g})"), e

    def _innovation_covariance(self, stamp_pred: int, dt: float, Sigma: Array) -> Array:
        """Covariance of the innovation ``e = log(T T_pred^-1)`` (left perturbation, in ``frame``)
        of a pose with covariance ``Sigma`` against the current joint model's prediction at
        ``stamp_pred``, ``dt`` after the model:

        ``S = C_pred + Sigma + Ad(D) Sigma0 Ad(D)^T + s_q dt^3/3 xi xi^T + floor I``: the model's
        propagated parameter covariance (:func:`predict_hand_pose`), the pose's own, the reference
        pose's (moved with the joint, ``D = T_pred T_ref^-1``) and the joint value's process noise
        along the screw ``xi`` over ``dt`` (capped like the filters').
        """
        model = self._model
        cfg = self.config
        if model.type == "prismatic" and model.prismatic is not None:
            u = model.prismatic.axis
            xi = np.array([u[0], u[1], u[2], 0.0, 0.0, 0.0])
            s_q = cfg.prismatic_q_noise_m2_per_s3
        else:
            assert model.revolute is not None
            u, p = model.revolute.axis, model.revolute.point
            xi = np.concatenate([cross3(p, u), u])
            s_q = cfg.revolute_q_noise_rad2_per_s3
        predicted = predict_hand_pose(model, stamp_pred)
        assert predicted is not None
        T_pred, C_pred = predicted
        A = adjoint_fast(T_pred @ se3_inverse_fast(model.reference_pose))
        return (C_pred + Sigma + A @ self._Sigma0 @ A.T
                + (s_q * dt * dt * dt / 3.0) * np.outer(xi, xi) + self._floor6)

    def _start_revolute(self, D: Array, angle: float) -> None:
        """Start (or restart) the revolute filter from the delta ``D``, whose rotation angle is
        ``angle`` [rad] (docs/estimation.md#filter-start)."""
        self._revolute = RevoluteJoint.from_twist(self.config, se3_log_fast(D), self._Sigma0)
        self._revolute_check_rad = angle * self.config.revolute_recheck_growth
        self._selector.history.backfill_revolute(self._revolute.u)

    def _revolute_axis_d2(self, w: Array, R_D: Array, Sigma: Array) -> float:
        """Squared Mahalanobis distance between the revolute filter's axis and the axis of the
        current delta's rotation vector ``w`` (3,) [rad] (sign-folded onto the filter's), in the
        filter's tangent basis ``B``: the tangent coordinates ``b = B' w / |w|`` against
        ``P_b + B' Sigma_w B / |w|^2``, ``Sigma_w`` the rotation-vector covariance of the rigid
        test (the current pose's plus the reference's, rotated with the delta;
        docs/estimation.md#filter-start)."""
        f = self._revolute
        assert f is not None
        n2 = float(w @ w)
        a = w if float(w @ f.u) >= 0.0 else -w
        Sigma_w = Sigma[3:, 3:] + R_D @ self._Sigma0[3:, 3:] @ R_D.T + self._floor3
        b = f.B.T @ a / math.sqrt(n2)
        C = f.P[:2, :2] + (f.B.T @ Sigma_w @ f.B) / n2
        return _mahalanobis2(b, C)

    def _displacement_persists(self, stamp: int, d2_disp: float) -> bool:
        """Whether the displacement has been beyond the rigid test (``rigid_test_sigmas``) for
        ``prismatic_min_motion_s`` of stamps, this frame included: a provisional start needs a
        displacement that persists, not one noisy frame (docs/estimation.md#filter-start)."""
        if d2_disp < self.config.rigid_test_sigmas ** 2:
            self._displaced_since = None
            return False
        if self._displaced_since is None:
            self._displaced_since = stamp
        return (stamp - self._displaced_since) * 1e-9 >= self.config.prismatic_min_motion_s

    def _refine_reference(self, D: Array, Sigma: Array) -> None:
        """Fuse a pose of the still hand, ``D = T T0^-1`` with covariance ``Sigma``, into the
        reference: ``T0 <- Exp(K log D) T0``, ``Sigma0 <- (I - K) Sigma0``, ``K = Sigma0
        (Sigma0 + Sigma + floor I)^-1`` (a Kalman update of a static pose; left perturbations in
        ``frame``). The stamps of the reference stay (docs/estimation.md#reference-refinement)."""
        S0 = self._Sigma0
        y = se3_log_fast(D)
        self._still_whiteness.add(y, S0 + Sigma + self._floor6)
        # Successive poses' errors are correlated: fused as independent, N still frames would
        # claim N times the information they hold. Each pose counts with its covariance
        # inflated by the integrated autocorrelation time of the innovations so far.
        rho = self._still_whiteness.rho
        R = Sigma * ((1.0 + rho) / (1.0 - rho)) + self._floor6
        K = np.linalg.solve(S0 + R, S0).T  # K = S0 (S0 + R)^-1
        T0 = se3_exp_fast(K @ y) @ self._T0
        S0 = (_I6 - K) @ S0
        stamp0, last = self._stamp0, self._last_stamp
        self._set_reference(T0, 0.5 * (S0 + S0.T), stamp0)
        self._last_stamp = last

    def _set_reference(self, T: Array, Sigma: Array, stamp: int) -> None:
        self._T0 = T.copy()
        self._T0_inv = se3_inverse_fast(T)
        self._Sigma0 = Sigma.copy()
        self._Sigma0_floored = Sigma + self.config.measurement_noise_floor * _I6
        G0 = translation_jacobian(T[:3, 3])
        self._Sigma0_disp = G0 @ Sigma @ G0.T
        self._stamp0 = stamp
        self._last_stamp = stamp

    # ---------------------------------------------------------------------------------- output

    def _type_known(self) -> bool:
        cfg = self.config
        if self._updates < cfg.min_updates_for_type or self._last_stamp is None:
            return False
        if self._revolute is not None:
            return True
        if self._prismatic is not None:
            return not self._rotation_pending
        return (self._last_stamp - self._stamp0) * 1e-9 >= cfg.min_still_duration_for_rigid_s

    def _make_model(self) -> KinematicModel:
        scores = self._log_scores.tolist()
        top = max(scores)
        weights = [math.exp(x - top) for x in scores]
        total = sum(weights)
        probs = [w / total for w in weights]
        model_type = (JOINT_TYPES[max(range(4), key=probs.__getitem__)] if self._type_known()
                      else "unknown")
        if self._T0 is None:
            reference = np.eye(4)
        elif model_type == "prismatic" and self._prismatic is not None:
            reference = self._prismatic.reference_correction() @ self._T0
        elif model_type == "revolute" and self._revolute is not None:
            reference = self._revolute.E @ self._T0
        else:
            reference = self._T0.copy()
        reference.flags.writeable = False
        return KinematicModel(
            seq=0,
            stamp_ns=0 if self._last_stamp is None else self._last_stamp,
            frame_id=self.frame_id,
            type=model_type,
            probabilities=dict(zip(JOINT_TYPES, probs, strict=True)),
            prismatic=None if self._prismatic is None else prismatic_params(self._prismatic),
            revolute=None if self._revolute is None else revolute_params(self._revolute),
            reference_pose=reference,
            updates=self._updates,
        )

    # ---------------------------------------------------------------------------------- snapshot

    def to_snapshot(self) -> dict[str, Any]:
        """The complete state as a dict of str/int/float/bool/None/list/dict/np.ndarray values."""
        return {
            "version": SNAPSHOT_VERSION,
            "frame_id": self.frame_id,
            "reference_pose": None if self._T0 is None else self._T0.copy(),
            "reference_covariance": self._Sigma0.copy(),
            "stamp0_ns": self._stamp0,
            "last_stamp_ns": self._last_stamp,
            "updates": self._updates,
            "rigid": self._rigid.to_state(),
            "disconnected": self._disconnected.to_state(),
            "prismatic": None if self._prismatic is None else self._prismatic.to_state(),
            "revolute": None if self._revolute is None else self._revolute.to_state(),
            "selector": self._selector.to_state(),
            "log_scores": self._log_scores.copy(),
            "rotation_pending": self._rotation_pending,
            "reference_fixed": self._reference_fixed,
            "still_whiteness": self._still_whiteness.to_state(),
            "beyond_since_ns": self._beyond_since,
            "still_poses": {"stamps_ns": [p[0] for p in self._still_poses],
                            "poses": np.array([p[1] for p in self._still_poses]).reshape(-1, 4, 4),
                            "covariances": np.array([p[2] for p in self._still_poses]
                                                    ).reshape(-1, 6, 6)},
            "revolute_check_rad": self._revolute_check_rad,
            "prismatic_provisional": self._prismatic_provisional,
            "displaced_since_ns": self._displaced_since,
            "innovation": None if self._innovation is None else {
                "e": self._innovation[0].copy(), "covariance": self._innovation[1].copy()},
            "outliers": self._outliers,
            "outliers_since_ns": self._outliers_since,
            "gate_yields": self._gate_yields,
        }

    @classmethod
    def from_snapshot(cls, d: dict[str, Any], config: KinematicsConfig) -> KinematicEstimator:
        """Rebuild an estimator from :meth:`to_snapshot`; continuing gives identical results.

        Every value is checked (type, shape, finite, range; ``frame_id`` camera or world; stamps
        in ``[0, 2^63)`` and ordered) and the restored model must pass the wire checks of a
        received one, so nothing :meth:`to_snapshot` cannot have written is ever served:
        :class:`~services.common.snapshot.SnapshotError` (a ValueError) names the first field that
        is wrong. Whether the last stamp is plausible *now* is the service's check
        (:meth:`services.common.stamps.StampWindow.lead_problem`).
        """
        r = SnapshotReader(d, "estimator")
        version = r.raw("version")
        if version != SNAPSHOT_VERSION:
            raise SnapshotError(f"estimator.version: unsupported snapshot version {version!r} "
                                f"(this version writes {SNAPSHOT_VERSION})")
        est = cls(config, frame_id=r.choice("frame_id", FRAME_IDS))
        updates = r.integer("updates", 0)
        last = r.optional_integer("last_stamp_ns", 0, INT64_MAX)
        if r.is_none("reference_pose"):
            if updates or last is not None:
                raise SnapshotError("estimator.reference_pose: missing although "
                                    f"{updates} updates were made")
        else:
            stamp0 = r.integer("stamp0_ns", 0, INT64_MAX)
            if last is None or last < stamp0 or updates < 1:
                raise SnapshotError(f"estimator.last_stamp_ns: {last!r} does not follow "
                                    f"stamp0_ns {stamp0} after {updates} updates")
            est._set_reference(r.pose("reference_pose"), r.covariance("reference_covariance", 6),
                               stamp0)
        est._last_stamp = last
        est._updates = updates
        est._rigid = RigidJoint.from_state(r.map("rigid"))
        est._disconnected = DisconnectedJoint.from_state(r.map("disconnected"))
        prismatic = r.optional_map("prismatic")
        est._prismatic = None if prismatic is None else PrismaticJoint.from_state(config, prismatic)
        revolute = r.optional_map("revolute")
        est._revolute = None if revolute is None else RevoluteJoint.from_state(config, revolute)
        est._selector = ModelSelector.from_state(config, r.map("selector"))
        est._log_scores = r.array("log_scores", (4,), allow_minus_inf=True)
        if not np.isfinite(est._log_scores).any():
            raise SnapshotError("estimator.log_scores: no finite score")
        est._rotation_pending = r.boolean("rotation_pending")
        est._reference_fixed = r.boolean("reference_fixed")
        est._still_whiteness = InnovationCorrelation.from_state(6, r.map("still_whiteness"))
        est._beyond_since = r.optional_integer("beyond_since_ns", 0, INT64_MAX)
        still = r.map("still_poses")
        stamps = still.raw("stamps_ns")
        if not isinstance(stamps, list) or not all(
                isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= INT64_MAX
                for x in stamps):
            raise SnapshotError("estimator.still_poses.stamps_ns: expected a list of stamps")
        poses = still.array("poses", (len(stamps), 4, 4))
        covariances = still.array("covariances", (len(stamps), 6, 6))
        est._still_poses = [(x, poses[i], covariances[i]) for i, x in enumerate(stamps)]
        check = r.raw("revolute_check_rad")
        est._revolute_check_rad = (math.inf if check == math.inf
                                   else r.number("revolute_check_rad"))
        if est._revolute_check_rad <= 0.0:
            raise SnapshotError("estimator.revolute_check_rad: must be > 0, got "
                                f"{est._revolute_check_rad!r}")
        est._prismatic_provisional = r.boolean("prismatic_provisional")
        est._displaced_since = r.optional_integer("displaced_since_ns", 0, INT64_MAX)
        if est._prismatic_provisional and est._prismatic is None:
            raise SnapshotError("estimator.prismatic_provisional: true without a prismatic filter")
        innovation = r.optional_map("innovation")
        est._innovation = (None if innovation is None
                           else (innovation.array("e", (6,)),
                                 innovation.covariance("covariance", 6)))
        est._outliers = r.integer("outliers", 0)
        est._outliers_since = r.integer("outliers_since_ns", 0, INT64_MAX)
        est._gate_yields = r.boolean("gate_yields")
        est._model = est._make_model()
        try:  # the model it serves passes the checks a received one must pass
            KinematicModel.from_msgpack(est._model.to_msgpack())
        except ProtocolError as exc:
            raise SnapshotError(f"estimator: the restored model is not valid: {exc}") from exc
        return est


__all__ = [
    "REJECT_REASONS",
    "KinematicEstimator",
    "RejectReason",
    "UpdateResult",
    "chi2_quantile_of_sigmas",
    "translation_jacobian",
]
