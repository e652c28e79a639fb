"""Hand-body level: EKF on SE(3) x R^6, three motion models (paper §III.B; docs/estimation.md#hand-body-ekf).

State: pose ``T = T_frame_body`` (4x4) and left (spatial) twist ``xi = [v, w]`` (linear first,
m/s and rad/s, in the tracking frame) with ``T(t + dt) = Exp(dt xi) T(t)`` under constant
velocity. Error state (12): ``[delta (v, w), epsilon (v, w)]`` with ``T = Exp(delta) T_hat`` (left
perturbation) and ``xi = xi_hat + epsilon``; ``P`` is its 12x12 covariance, in the tracking frame.
``P0`` and ``Q`` (Table I's ``P0_rb``, ``Q_rb``) are hand-centred (translation and rotation of the
hand about its own origin) and carried into this error state with ``Ad(T)`` (:func:`body_to_frame`).

Motion models, all predicted from the same posterior (docs/estimation.md#motion-models):

- ``constant_velocity``: ``T_p = Exp(dt xi) T``, ``xi_p = xi``,
  ``F = [[Ad(Exp(dt xi)), dt J_l(dt xi)], [0, I]]``, ``P_p = F P F' + Q``.
- ``static``: ``T_p = T``, ``P_p = P + Q`` (pose unchanged). It predicts nothing about the
  velocity: when it wins, the pose comes from its correction, and the twist (with its
  cross-covariance) from the constant-velocity prediction corrected with that pose
  (:meth:`HandBodyEkf.update_chosen`). Resetting the twist instead (a "brake") would deadlock:
  the constant-velocity mean would equal the static one and, with its larger covariance, never
  win; correcting the velocity with the landmarks directly would overshoot by the static lag.
- ``kinematic``: the caller's predicted pose ``T_k`` for this stamp with its 6x6 covariance
  ``Sigma_k``; ``xi_p = log(T_k T^-1) / dt``; ``P_p = blkdiag(Sigma_k + Q_pose, P_cv twist)``.
  Offered only when it is :func:`informative`: nowhere less certain than the constant-velocity
  prediction (a joint filter that has just started predicts a pose uncertain by tens of degrees;
  in a frame with gross outliers such a vague prediction is the most likely one and its wide gates
  and prior let the outliers move the pose, which then corrupts the joint filter in turn).

Model choice: the model under which the stacked landmark innovation is most likely,
``max_m log N(y_m; 0, H P_m H' + R)``, with each model's predicted pose covariance ``P_m``,
process noise included: ``P + Q`` (static), ``F P F' + Q`` (constant velocity, with its velocity
uncertainty), ``Sigma_k + Q`` (kinematic: ``services/kinematics/prediction.py`` gives the
joint's share and leaves process noise to the caller). That is each model's predictive density
of the landmarks, the likelihood the paper's "most likely prediction" names: OMIP's choice
(predicted feature positions against the measurements) made probabilistic. Leaving ``Q`` out, as
this module once did, scored each mean with a covariance that no prediction has: a kinematic
prediction that knows the joint to millimetres was judged as if the hand could not move on the
handle. The correction starts from the winner's ``P_m``. All covariances are physical (m^2,
rad^2; ``TrackerConfig.internal``), so a kinematic prediction's ``Sigma_k`` and ``R`` are on
the same scale; Table I's large velocity noise makes ``static`` win most frames of a slow hand,
``constant_velocity`` wins sustained motion, and the twist is estimated either way (see
``static``). Measured on the paper's tuning split (8 seeds), the kinematic model wins 5.2 % of
the frames (4.2 % without ``Q``) and changes the mean tangent error by less than the seeds do
(docs/estimation.md#motion-model-choice).

Measurements: the filtered landmarks ``z_i`` (tracking frame) with covariance ``R_i`` (``R_rb``,
3x3, anisotropic with the landmark filters' covariance; ``r_i I3`` accepted wherever a variance
``r_i`` is given), ``h_i(T) = T p_i`` for the landmark's body-frame coordinates
``p_i``, and ``H_i = [I3, -[T_hat p_i]x, 0]`` (3x12). All landmarks are absorbed in one stacked
update. Because ``R = blkdiag(R_i)``, the stacked quantities reduce to 6x6 information sums
(Woodbury), with ``A = sum H_i' R_i^-1 H_i``, ``b = sum H_i' R_i^-1 y_i`` and the pose block
``P`` of ``P_p``:

- ``H' S^-1 y = X b``, ``H' S^-1 H = X A``, ``H' S^-1 R S^-1 H = X A X'``, ``X = (I + A P)^-1``,
- ``y' S^-1 y = sum y_i' R_i^-1 y_i - b' P X b``,
  ``log det S = sum log det R_i + log det(I + A P)``,

so ``K = P H' S^-1`` and the Joseph form never build the 3n x 3n ``S`` (the tests compare with
the textbook stacked update; :func:`innovation_covariance` builds ``S`` for diagnostics).

Gating (``M_rb``: 7.9 sigma in physical units, ``TrackerConfig.gate_sigmas``), per landmark,
before the update:

1. against the predicted landmark (paper): ``y_i' (H_i P_p H_i' + R_i)^-1 y_i``;
2. leave-one-out: against the landmark predicted from the prior *and all other landmarks*,
   computed exactly as the standardised posterior residual (see
   :func:`~services.tracker.body_measurement.posterior_residual_passes`). With Table-I's process
   noise the prior prediction is uncertain to ~3 cm, so gate 1 only rejects jumps beyond ~23 cm;
   gate 2 carries only the uncertainty left once the other landmarks are seen, about ``R_i``,
   and rejects jumps beyond 7.9 of its sigmas (~6-10 cm).

The measurement algebra (Jacobians, information sums, likelihoods, the two gates) is in
``body_measurement.py``; this module holds the filter, its predictions and corrections and the
model choice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import (
    se3_adjoint_fast,
    se3_exp_fast,
    se3_inverse_fast,
    se3_left_jacobian_fast,
    se3_log_fast,
)
from services.tracker.body_measurement import (
    as_covariances,
    information_sums,
    information_sums_from_jacobians,
    log_likelihoods,
    measurement_jacobians,
    posterior_residual_passes_from_jacobians,
    predicted_points,
    prior_gate_passes,
)
from services.tracker.covariance import guarded_cholesky, is_psd, psd_repaired
from services.tracker.landmarks import inv_sym3

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

MOTION_MODELS = ("static", "constant_velocity", "kinematic")
_I6 = np.eye(6)
_I12 = np.eye(12)


@dataclass(frozen=True, eq=False)
class Prediction:
    """One motion model's prediction: ``T`` (4, 4), ``xi`` (6,) and the predicted error
    covariance ``P`` (12, 12), process noise included; its pose block is the covariance of the
    model's likelihood and of its gates."""

    model: str
    T: Array
    xi: Array
    P: Array


def innovation_covariance(prior: Prediction, points_body: Array, r: Array) -> Array:
    """Stacked ``S = H P_p H' + blkdiag(R_i)`` (3n, 3n) for body points (n, 3) (diagnostics);
    ``r`` covariances (n, 3, 3) or isotropic variances (n,)."""
    n = points_body.shape[0]
    H = np.zeros((3 * n, 12))
    H[:, :6] = measurement_jacobians(predicted_points(prior.T, points_body)).reshape(3 * n, 6)
    R = np.zeros((3 * n, 3 * n))
    for i, Ri in enumerate(as_covariances(r)):
        R[3 * i:3 * i + 3, 3 * i:3 * i + 3] = Ri
    out: Array = H @ prior.P @ H.T + R
    return out


@dataclass(frozen=True, eq=False)
class Posterior:
    """A corrected state: ``T`` (4, 4), ``xi`` (6,), ``P`` (12, 12)."""

    T: Array
    xi: Array
    P: Array


def correction(P: Array, A: Array, b: Array) -> tuple[Array, Array]:
    """``(K y, P_post)`` of the stacked EKF update of a prediction with covariance ``P`` (12, 12)
    from its information sums ``A = sum H_i' R_i^-1 H_i`` (6, 6), ``b = sum H_i' R_i^-1 y_i`` (6,)
    over the pose columns (the twist columns of H are 0); Joseph form (module docstring)."""
    # X = (I + A P)^-1:  H' S^-1 y = X b,  H' S^-1 H = X A.
    sol = np.linalg.solve(_I6 + A @ P[:6, :6], np.concatenate((b[:, None], A, _I6), axis=1))
    u, G, X = sol[:, 0], sol[:, 1:7], sol[:, 7:]
    PHt = P[:, :6]  # K = P H' S^-1 = P[:, :6] (H_pose' S^-1)
    KH = PHt @ G  # the pose columns of K H (its twist columns are 0)
    M = P - KH @ P[:6]  # (I - K H) P
    P_post = M - M[:, :6] @ KH.T + PHt @ (X @ A @ X.T) @ PHt.T  # M (I-KH)' + K R K'
    return PHt @ u, 0.5 * (P_post + P_post.T)


def corrected(prior: Prediction, A: Array, b: Array) -> Posterior:
    """The posterior of ``prior`` after the stacked update (:func:`correction`); the pose is
    updated on the group, ``T = Exp(delta) T_p``, the twist additively."""
    dx, P = correction(prior.P, A, b)
    return Posterior(T=se3_exp_fast(dx[:6]) @ prior.T, xi=prior.xi + dx[6:], P=P)


def merge_pose(P_velocity: Array, P_pose: Array) -> tuple[Array, bool]:
    """``P_velocity`` (12, 12) with its pose block replaced by ``P_pose`` (6, 6), and whether an
    input had to be repaired.

    The pose-twist cross-covariance is carried over by the congruence ``blkdiag(L_p L_v^-1, I)``
    (``L``: Cholesky factors of the two pose blocks), which keeps the result positive
    semi-definite and the correlation structure of ``P_velocity``. When round-off has left a
    pose block without a Cholesky factor, both inputs are first repaired
    (:func:`~services.tracker.covariance.psd_repaired`: the whole of ``P_velocity``, so that its
    cross-covariance stays consistent with its pose block); when even that fails (an input that
    is not finite), the cross-covariance is dropped.
    """
    P_v, P_p = P_velocity, P_pose
    repaired = False
    try:
        L_v, L_p = np.linalg.cholesky(np.array([P_v[:6, :6], P_p]))
        if not (math.isfinite(L_v[5, 5]) and math.isfinite(L_p[5, 5])):  # NaN in: no error
            raise np.linalg.LinAlgError("covariance not finite")
    except np.linalg.LinAlgError:
        repaired = True
        fixed_v, fixed_p = psd_repaired(P_velocity), psd_repaired(P_pose)
        factors = (None if fixed_v is None or fixed_p is None
                   else guarded_cholesky(np.array([fixed_v[:6, :6], fixed_p])))
        if factors is None or fixed_v is None or fixed_p is None:
            P = P_velocity.copy()
            P[:6, :6] = P_pose
            P[:6, 6:] = 0.0
            P[6:, :6] = 0.0
            return P, True
        (L_v, L_p), _ = factors
        P_v, P_p = fixed_v, fixed_p
    M = np.linalg.solve(L_v.T, L_p.T).T  # L_p L_v^-1
    P = P_v.copy()
    P[:6, :6] = P_p
    P[:6, 6:] = M @ P_v[:6, 6:]
    P[6:, :6] = P[:6, 6:].T
    return P, repaired


def pose_fused(prior: Prediction, T_z: Array, R_z: Array) -> tuple[Array, Array]:
    """``(K y, P_post)`` of the EKF update of ``prior`` with a pose measurement ``T_z`` (4, 4) of
    covariance ``R_z`` (6, 6): ``y = log(T_z T_p^-1)`` (left), ``H = [I6, 0]``, Joseph form."""
    P = prior.P
    y = se3_log_fast(T_z @ se3_inverse_fast(prior.T))
    S = P[:6, :6] + R_z  # S = H P H' + R
    K = np.linalg.solve(S, P[:6, :]).T  # K = P H' S^-1
    M = P - K @ P[:6]  # (I - K H) P
    P_post = M - M[:, :6] @ K.T + K @ R_z @ K.T  # M (I - K H)' + K R K'
    return K @ y, 0.5 * (P_post + P_post.T)


def body_to_frame(T: Array, M: Array) -> Array:
    """A (12, 12) error covariance over [pose, twist] in body coordinates (perturbations about
    the body origin) as the left-perturbation covariance in the tracking frame:
    ``G M G'`` with ``G = blkdiag(Ad(T), Ad(T))``."""
    Ad = se3_adjoint_fast(T)
    G = np.zeros((12, 12))
    G[:6, :6] = Ad
    G[6:, 6:] = Ad
    return G @ M @ G.T


def informative(C_k: Array, P_cv_pose: Array) -> bool:
    """Whether a kinematic prediction's pose covariance ``C_k`` (6, 6) is nowhere larger than
    the constant-velocity prediction's (with its process noise) ``P_cv_pose`` (6, 6), i.e.
    ``P_cv_pose - C_k`` is positive semi-definite.

    A vaguer prediction (a joint filter that has just started, whose axis and point are still
    uncertain by tens of degrees and centimetres) adds nothing the constant-velocity model does
    not already say, but it would win the model choice in exactly the wrong frames: when gross
    outliers fit no precise prediction, the vaguest model is the most likely one, and its wide
    gates and prior would let the outliers move the pose.
    """
    D = P_cv_pose - 0.5 * (C_k + C_k.T)
    scale = max(float(np.abs(P_cv_pose).max()), 1e-300)
    return bool(np.linalg.eigvalsh(0.5 * (D + D.T))[0] >= -1e-12 * scale)


class HandBodyEkf:
    """EKF for the hand body: ``T`` (4, 4), ``xi`` (6,), ``P`` (12, 12); see module docstring.

    ``P0_body`` and ``Q_body`` (12, 12; ``Q`` per ``nominal_dt_s``) are given in body
    coordinates, i.e. translation and rotation noise of the hand about its own origin (Table I's
    ``P0_rb``, ``Q_rb``), and carried into the frame-coordinate error state with ``Ad(T)``
    (:func:`body_to_frame`); added directly in frame coordinates, a rotation noise would turn
    the hand about the camera origin and add ~|t|^2 q_rot of translation noise.
    """

    def __init__(self, T: Array, xi: Array, P0_body: Array, Q_body: Array,
                 nominal_dt_s: float) -> None:
        self.T: Array = np.array(T, dtype=float)
        self.xi: Array = np.array(xi, dtype=float)
        self.P: Array = body_to_frame(self.T, np.asarray(P0_body, dtype=float))
        self.Q_body = np.array(Q_body, dtype=float)
        self.nominal_dt_s = float(nominal_dt_s)

    def process_noise(self, dt_s: float) -> Array:
        """``Q`` (frame coordinates, at the current pose) for an interval of ``dt_s`` seconds."""
        return body_to_frame(self.T, self.Q_body * (dt_s / self.nominal_dt_s))

    def transition(self, dt_s: float) -> tuple[Array, Array]:
        """``(Exp(dt xi), F)`` of the constant-velocity model,
        ``F = [[Ad(Exp(dt xi)), dt J_l(dt xi)], [0, I]]``."""
        step = dt_s * self.xi
        E = se3_exp_fast(step)
        F = _I12.copy()
        F[:6, :6] = se3_adjoint_fast(E)
        F[:6, 6:] = dt_s * se3_left_jacobian_fast(step)
        return E, F

    def predict(self, dt_s: float, kinematic: tuple[Array, Array] | None = None
                ) -> list[Prediction]:
        """The motion models' predictions for ``dt_s`` ahead (the state is not changed).

        ``kinematic``: (``T_k`` (4, 4), ``Sigma_k`` (6, 6)) for this stamp, or None.
        Order: static, constant_velocity, [kinematic] (ties go to the first).
        """
        Q = self.process_noise(dt_s)
        E, F = self.transition(dt_s)
        FPFt = F @ self.P @ F.T
        P_cv = FPFt + Q  # P = F P F' + Q
        P_cv = 0.5 * (P_cv + P_cv.T)
        out = [Prediction("static", self.T.copy(), self.xi.copy(), self.P + Q),
               Prediction("constant_velocity", E @ self.T, self.xi.copy(), P_cv)]
        if kinematic is not None and informative(kinematic[1], P_cv[:6, :6]):
            T_k, Sigma_k = kinematic
            P_k = np.zeros((12, 12))
            P_k[:6, :6] = 0.5 * (Sigma_k + Sigma_k.T) + Q[:6, :6]
            P_k[6:, 6:] = P_cv[6:, 6:]
            xi_k = se3_log_fast(T_k @ se3_inverse_fast(self.T)) / dt_s
            out.append(Prediction("kinematic", np.array(T_k, dtype=float), xi_k, P_k))
        return out

    def update(self, prior: Prediction, z: Array, points_body: Array, r: Array) -> None:
        """Correct ``prior`` with landmarks ``z`` (n, 3) of body points ``points_body`` (n, 3)
        and noise ``R_i`` (``r``: covariances (n, 3, 3) or isotropic variances (n,)): one
        stacked EKF update (module docstring)."""
        q = predicted_points(prior.T[None], points_body)
        W, _ = inv_sym3(as_covariances(r))
        A, b, _ = information_sums(q, z[None] - q, W)  # y = z - h(x_p)
        self._set(corrected(prior, A[0], b[0]))

    def update_chosen(self, predictions: list[Prediction], step: BodyStep) -> tuple[str, ...]:
        """Apply the correction :func:`select_and_gate` chose: the winner's posterior. When the
        pose-only static model won, the twist comes from the constant-velocity prediction
        corrected with the static posterior pose (a pose measurement), so that it tracks the
        poses we report: in steady motion its fixed point is their finite difference.

        Returns the covariances that had to be repaired on the way (``"merge_pose"``, and
        ``"posterior"`` when the new ``P`` was not positive semi-definite; :meth:`_set`), so that
        the caller can count them. Raises ``numpy.linalg.LinAlgError`` only for a singular
        innovation covariance, which positive semi-definite inputs rule out."""
        repairs: list[str] = []
        chosen = predictions[step.model]
        post = corrected(chosen, step.A[step.model], step.b[step.model])
        if chosen.model == "static":
            cv = predictions[1]
            dx, P_cv = pose_fused(cv, post.T, post.P[:6, :6])
            P, repaired = merge_pose(P_cv, post.P[:6, :6])
            if repaired:
                repairs.append("merge_pose")
            post = Posterior(T=post.T, xi=cv.xi + dx[6:], P=P)
        if not self._set(post):
            repairs.append("posterior")
        return tuple(repairs)

    def _set(self, post: Posterior) -> bool:
        """Adopt ``post`` (True). A posterior whose covariance is not positive semi-definite is
        adopted with the covariance repaired (:func:`~services.tracker.covariance.psd_repaired`);
        one that is not finite is not adopted at all (False either way)."""
        if is_psd(post.P):
            self.T, self.xi, self.P = post.T, post.xi, post.P
            return True
        fixed = psd_repaired(post.P)
        if fixed is not None and np.isfinite(post.T).all() and np.isfinite(post.xi).all():
            self.T, self.xi, self.P = post.T, post.xi, fixed
        return False


@dataclass(frozen=True, eq=False)
class BodyStep:
    """Outcome of :func:`select_and_gate` over n candidate landmarks.

    ``model``: index of the winning prediction; ``log_likelihood`` (m,) of every prediction;
    ``accepted``/``rejected`` (n,) landmarks to use / rejected as outliers; ``y`` (n, 3) the
    innovations against the winner; ``A`` (m, 6, 6), ``b`` (m, 6) every prediction's information
    sums over the accepted landmarks (input of :meth:`HandBodyEkf.update_chosen`); ``W``
    (n, 3, 3) the inverse measurement covariances ``R_i^-1`` of all n landmarks.
    """

    model: int
    log_likelihood: Array
    accepted: BoolArray
    rejected: BoolArray
    y: Array
    A: Array
    b: Array
    W: Array


def select_and_gate(predictions: list[Prediction], z: Array, points_body: Array, r: Array,
                    threshold: float, gate: bool) -> BodyStep:
    """Pick the most likely motion model and gate the n landmarks (n >= 1) against it.

    The likelihoods and the gates use each prediction's predicted pose covariance (module
    docstring).
    Selection uses the landmarks that pass the prior gate under at least one model (a landmark
    that fits no model is an outlier and would only add noise to the comparison); the update set
    is those passing both the prior and the leave-one-out gate of the winner. ``gate=False``
    (ablation) uses and accepts every landmark. z, points_body (n, 3), r the measurement
    covariances (n, 3, 3) or isotropic variances (n,).
    """
    m, n = len(predictions), z.shape[0]
    T = np.array([p.T for p in predictions])
    P_pose = np.array([p.P[:6, :6] for p in predictions])
    q = predicted_points(T, points_body)  # (m, n, 3)
    y = z[None] - q
    H = measurement_jacobians(q)  # (m, n, 3, 6)
    R = as_covariances(r)
    W_all, det_R = inv_sym3(R)
    if gate:
        prior_ok = prior_gate_passes(q, y, P_pose, R, threshold, W=W_all)  # (m, n)
        select = prior_ok.any(axis=0)
    else:
        prior_ok = np.ones((m, n), dtype=bool)
        select = prior_ok[0]
    all_selected = bool(select.all())
    W_select = W_all if all_selected else np.where(select[:, None, None], W_all, 0.0)
    A, b, c = information_sums_from_jacobians(H, y, W_select)
    logdet_R = float(np.log(det_R if all_selected else det_R[select]).sum())
    ll = log_likelihoods(P_pose, A, b, c, logdet_R, int(select.sum()))
    best = int(ll.argmax())  # the first of equals wins: static before constant_velocity
    accepted = prior_ok[best].copy()
    same = accepted.all() if all_selected else np.array_equal(accepted, select)
    if gate and accepted.sum() >= 2:
        if same:
            A_best, b_best = A[best], b[best]
        else:
            A_w, b_w, _ = information_sums_from_jacobians(
                H[best:best + 1], y[best:best + 1], np.where(accepted[:, None, None], W_all, 0.0))
            A_best, b_best = A_w[0], b_w[0]
        passes = posterior_residual_passes_from_jacobians(H[best], y[best], R, P_pose[best],
                                                          A_best, b_best, threshold)
        if not passes[accepted].all():
            accepted &= passes
            same = False
    if not same:
        A, b, _ = information_sums_from_jacobians(H, y, np.where(accepted[:, None, None], W_all, 0.0))
    return BodyStep(model=best, log_likelihood=ll, accepted=accepted, rejected=~accepted,
                    y=y[best], A=A, b=b, W=W_all)


def body_noise_matrices(p0: tuple[float, float, float, float],
                        q: tuple[float, float, float, float]) -> tuple[Array, Array]:
    """12x12 diagonal ``P0`` and ``Q`` from per-block scalars (position, rotation, linear
    velocity, angular velocity)."""
    P0 = np.diag(np.repeat(np.asarray(p0, dtype=float), 3))
    Q = np.diag(np.repeat(np.asarray(q, dtype=float), 3))
    return P0, Q


__all__ = [
    "MOTION_MODELS",
    "BodyStep",
    "HandBodyEkf",
    "Posterior",
    "Prediction",
    "body_noise_matrices",
    "body_to_frame",
    "corrected",
    "correction",
    "informative",
    "innovation_covariance",
    "merge_pose",
    "pose_fused",
    "select_and_gate",
]
