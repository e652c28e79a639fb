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
   motion is at least ``min_motion_sigmas`` standard deviations of its noise. While the
   rotation is significant but still below ``revolute_min_rotation_rad``, a started prismatic filter
   alone does not make the type known: a revolute joint cannot be ruled out before its filter runs.
3. The sample and the joint values enter the bounded history, and model selection scores the four
   types (:mod:`services.kinematics.selection`).

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
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import KinematicModel, PrismaticParams, RevoluteParams
from services.kinematics.config import KinematicsConfig
from services.kinematics.filters import (
    JOINT_TYPES,
    DisconnectedJoint,
    PrismaticJoint,
    RevoluteJoint,
    RigidJoint,
    prismatic_noise_inflation,
    revolute_noise_inflation,
    tangent_basis,
)
from services.kinematics.filters.geometry import se3_inverse_fast, se3_log_fast
from services.kinematics.selection import ModelSelector

Array = NDArray[np.float64]

SNAPSHOT_VERSION = 1

RejectReason = Literal["invalid_stamp", "invalid_value", "bad_shape", "non_finite",
                       "invalid_covariance", "duplicate_stamp", "out_of_order"]
REJECT_REASONS: tuple[RejectReason, ...] = get_args(RejectReason)

_I3 = np.eye(3)
_I6 = np.eye(6)


@dataclass(frozen=True)
class UpdateResult:
    """What one :meth:`KinematicEstimator.update` did: ``model`` after an accepted pose, else None
    and ``reason`` says why it was rejected (the state is then unchanged)."""

    model: KinematicModel | None
    reason: RejectReason | None = None


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
    cov = (cov + cov.T) * 0.5
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
    cov = (cov + cov.T) * 0.5
    cov.flags.writeable = False
    return RevoluteParams(axis=axis, point=_frozen(f.p), q=s * f.q, dq=s * f.qdot,
                          covariance=cov)


def translation_jacobian(position: Array) -> Array:
    """Jacobian (3x6) of a pose's translation w.r.t. its left perturbation: ``[I, -[t]x]``."""
    x, y, z = position.tolist()
    return np.array([[1.0, 0.0, 0.0, 0.0, z, -y],
                     [0.0, 1.0, 0.0, -z, 0.0, x],
                     [0.0, 0.0, 1.0, y, -x, 0.0]])


class KinematicEstimator:
    """Joint EKFs (rigid, prismatic, revolute, disconnected) and model selection, online.

    ``update`` never raises on bad input: it rejects malformed or non-finite poses/covariances and
    duplicate or out-of-order stamps, says why in its :class:`UpdateResult` and keeps its state;
    counting is the caller's. No I/O, no clock: time comes only from the stamps.
    """

    def __init__(self, config: KinematicsConfig | None = None, frame_id: str = "camera") -> None:
        self.config = KinematicsConfig() if config is None else config
        self.frame_id = frame_id
        self._floor3 = self.config.measurement_noise_floor * _I3
        self._floor6 = self.config.measurement_noise_floor * _I6
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

    # ---------------------------------------------------------------------------------- input

    def _check(self, stamp_ns: Any, T: Any, cov: Any) -> tuple[RejectReason | None, Array, Array]:
        """The guards that keep the state sound (see the module docstring for what is not
        checked here); returns ``(reason or None, T, Sigma)`` with Sigma symmetrised."""
        empty = _I3
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, (int, np.integer)):
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
        if self._T0 is None:
            self._set_reference(T, Sigma, stamp)
            self._selector.add(np.zeros(3), _I3, 0.0, 0.0)
            self._updates = 1
            self._log_scores = self._selector.log_scores(None, None, position, position)
            self._model = self._make_model()
            return UpdateResult(model=self._model)

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

        # 2. Joint filters: predict once with the true dt, then correct (or start).
        if self._prismatic is not None or disp_norm >= cfg.prismatic_min_translation_m:
            G = translation_jacobian(position)
            Sigma_disp = G @ Sigma @ G.T
            if self._prismatic is not None:
                f = prismatic_noise_inflation(disp_norm, cfg)
                self._prismatic.predict(dt)
                self._prismatic.update(disp, f * Sigma_disp + self._floor3)  # R = f Sigma + floor I
            elif self._significant(disp, Sigma_disp + self._Sigma0_disp):
                self._prismatic = PrismaticJoint.from_displacement(cfg, disp, self._Sigma0_disp)
                self._selector.history.backfill_prismatic(self._prismatic.u)
        if self._revolute is not None:
            (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R_D.tolist()
            s0, s1, s2 = r21 - r12, r02 - r20, r10 - r01
            angle = math.atan2(0.5 * math.sqrt(s0 * s0 + s1 * s1 + s2 * s2),
                               0.5 * (r00 + r11 + r22 - 1.0))
            f = revolute_noise_inflation(angle, cfg)
            self._revolute.predict(dt)
            self._revolute.update(D, f * Sigma + self._floor6)  # R = f Sigma + floor I
        else:
            z = se3_log_fast(D)
            w = z[3:]
            significant = self._significant(
                w, Sigma[3:, 3:] + R_D @ self._Sigma0[3:, 3:] @ R_D.T)  # OMIP's Sigma_z, rotation block
            if significant and float(w @ w) >= cfg.revolute_min_rotation_rad ** 2:
                self._revolute = RevoluteJoint.from_twist(cfg, z, self._Sigma0)
                self._selector.history.backfill_revolute(self._revolute.u)
            # A significant rotation below the start threshold: a revolute joint cannot be ruled
            # out before its filter runs, so no type is published meanwhile (_type_known).
            self._rotation_pending = significant and self._revolute is None

        # 3. History and model selection.
        self._selector.add(disp, R_D,
                           0.0 if self._prismatic is None else self._prismatic.q,
                           0.0 if self._revolute is None else self._revolute.q)
        self._log_scores = self._selector.log_scores(self._prismatic, self._revolute, position,
                                                     T0[:3, 3])
        self._updates += 1
        self._model = self._make_model()
        return UpdateResult(model=self._model)

    def _significant(self, v: Array, Sigma_v: Array) -> bool:
        """Whether ``v^T Sigma_v^-1 v >= min_motion_sigmas^2`` (``Sigma_v`` floored)."""
        S = Sigma_v + self.config.measurement_noise_floor * np.eye(len(v))
        return float(v @ np.linalg.solve(S, v)) >= self.config.min_motion_sigmas ** 2

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
        }

    @classmethod
    def from_snapshot(cls, d: dict[str, Any], config: KinematicsConfig) -> KinematicEstimator:
        """Rebuild an estimator from :meth:`to_snapshot`; continuing gives identical results."""
        if d.get("version") != SNAPSHOT_VERSION:
            raise ValueError(f"unsupported kinematics snapshot version {d.get('version')!r}")
        est = cls(config, frame_id=str(d["frame_id"]))
        if d["reference_pose"] is not None:
            est._set_reference(np.array(d["reference_pose"], dtype=float),
                               np.array(d["reference_covariance"], dtype=float),
                               int(d["stamp0_ns"]))
        est._last_stamp = None if d["last_stamp_ns"] is None else int(d["last_stamp_ns"])
        est._updates = int(d["updates"])
        est._rigid = RigidJoint.from_state(d["rigid"])
        est._disconnected = DisconnectedJoint.from_state(d["disconnected"])
        est._prismatic = (None if d["prismatic"] is None
                          else PrismaticJoint.from_state(config, d["prismatic"]))
        est._revolute = (None if d["revolute"] is None
                         else RevoluteJoint.from_state(config, d["revolute"]))
        est._selector = ModelSelector.from_state(config, d["selector"])
        est._log_scores = np.array(d["log_scores"], dtype=float)
        est._rotation_pending = bool(d.get("rotation_pending", False))
        est._model = est._make_model()
        return est


__all__ = [
    "REJECT_REASONS",
    "KinematicEstimator",
    "RejectReason",
    "UpdateResult",
    "canonical_axis_sign",
    "prismatic_params",
    "revolute_params",
    "translation_jacobian",
]
