"""Configuration of the hand tracker: landmark KFs, weighted RANSAC and the hand-body EKF.

The Table-I fields keep the ICRA-25 paper's values (Pfisterer et al., Table I); the
physical terms below them are ours (what the paper leaves open), each with its reason.

Units and dt-scaling of Table I
-------------------------------
Positions in m, rotations in rad, velocities in m/s and rad/s. Initial covariances ``P0`` and
the measurement noise ``R_lm`` are absolute. Process noises ``Q`` are the variance added **per
nominal frame** of ``nominal_dt_s`` = 1/30 s (the Azure Kinect's 30 Hz), and are scaled linearly
with the elapsed time, ``Q_k = Q * dt / nominal_dt_s``, so a dropped frame adds the noise of two.

Why per frame: the paper's filters ran at a fixed 30 Hz, where a per-step ``Q`` is the simplest
implementation, and it is the one reading under which *every* Table-I threshold acts at a
physically meaningful distance (numbers in Table-I units, ``u``):

- landmark gate ``M_lm = 0.19``: the steady-state innovation covariance is S ~ 0.22 u per axis,
  so measurements that jump by more than ~0.09 sqrt(u) from the landmark prediction are outliers;
- loss threshold ``trace(P_lm) >= 0.3``: the steady-state posterior trace is 0.12 and one frame
  of process noise adds 0.39, so a landmark whose correction is skipped once (missing or outlier)
  is dropped; it restarts at its next measurement, gated against the lost filter's prediction
  when that filter was confirmed (``lm_confirm_corrections``; ``landmarks.py``); ``3 * P0`` =
  0.27 stays just below the threshold;
- body gate ``M_rb = 0.25``: S ~ 0.8 u (dominated by ``Q_rb``) against the predicted landmark,
  and the same threshold on the leave-one-out residual (``body.py``);
- the landmark KF gain is ~0.78, so the filtered landmark lags the measurement by ~0.3 frame.

Gates in sigma
--------------
Every gate compares a Mahalanobis distance ``d = sqrt(y' S^-1 y)`` of a 3-D residual ``y`` with
its own covariance ``S``; "N sigma" below means ``d >= N`` rejects. Table I's thresholds are in
Table-I units; in the filters' physical units (:meth:`TrackerConfig.internal`, the variance unit
1e-3 m^2) each is divided by ``sqrt(1e-3)`` (:meth:`TrackerConfig.gate_sigmas` computes them):

- landmark gate ``M_lm``: 6.0 sigma of ``S = P_lm + R_lm`` (~9 cm at 30 Hz), and the same on a
  confirmed landmark's restart, against the lost filter's growing prediction;
- body prior gate ``M_rb``: 7.9 sigma of ``S = H P_p H' + R_rb`` (``P_p`` with ``Q_rb``: ~23 cm);
- body leave-one-out gate ``M_rb``: 7.9 sigma of the leave-one-out residual's covariance
  ``R_rb - H Sigma H'`` (~6-10 cm; ``R_rb`` is ~(9 mm)^2 per axis);
- RANSAC inliers ``ransac_inlier_mahalanobis``: 7.9 sigma of ``(r_start + r_end) I3`` (~10 cm);
- body-model refinement (``template.py``): 3.4 sigma of ``R_rb`` (the 99 % point of chi-square
  with 3 degrees of freedom, ~3 cm; the long-term model takes no borderline landmark);
- hand identity (``hands.py``): ``hand_association_gate_sigma`` = 4 sigma of the hand centre's
  predicted spread ``sqrt(hand_centre_std_m^2 + (hand_speed_std_mps dt)^2)`` (~18 cm at 30 Hz).

Table I's gates are wide (a Gaussian innovation exceeds 6 sigma once in ~10^7 frames): they only
reject gross outliers; the uncertainty models, not the gates, weigh the rest. They are kept at
the paper's values: on the tuning split a 4-sigma landmark gate (``mahalanobis_lm`` 0.126) gave
4.7 deg instead of 5.2 deg mean tangent error, and the body gates at 4-5 sigma 5.4-5.7 deg
(docs/estimation.md#tuning-record); ``handkse tune`` optimises both.

The variance unit (``variance_unit_m2``)
-----------------------------------------
Read literally in m^2, Table I's covariances are ~(20 cm)^2, far above any landmark detector's
noise: Table I is a consistent filter only up to one global covariance scale, for which its tiny
Mahalanobis thresholds compensate. We fix that scale by physics: one Table-I unit is
``variance_unit_m2`` = 1e-3 m^2, chosen so that ``R_lm`` = 0.05 u is the detector's lateral
noise, (7.1 mm)^2 per axis (MediaPipe Hands, arXiv:2006.10214, Table 2: mean 2-D error 10 % of
the palm size, ~8.5 mm for an 8.5 cm palm, i.e. 6.8 mm per axis). :meth:`TrackerConfig.internal`
multiplies every Table-I covariance by the unit and divides every Table-I Mahalanobis threshold
by its square root: every Kalman gain and gate decision is exactly Table I's, but innovations,
likelihoods and covariances are now physical, so they can be combined with physical quantities
(the articulation variance, the kinematic level's predicted pose) and the motion-model choice
compares likelihoods in consistent units. ``variance_unit_m2 = 1`` is the literal SI reading.

Physical terms (beyond Table I)
-------------------------------
- ``articulation_std_rad``: the body model holds the hand rigid, but only the palm is; fingers
  flex by a few degrees while holding an object. ``R_rb = s_k P_lm + a_k I`` adds each
  landmark's variance from an independent flexion of this std at every joint between it and the
  palm (``landmarks.articulation_variances``). 0.15 rad (~9 deg) of grip adjustment per joint.
- ``depth_variance_factor``: anisotropic ``R_lm`` about the viewing ray (``landmarks.
  ray_measurement_covariances``). The depth read at a correctly detected fingertip is precise
  (mm-level skin surface), but a detection a few pixels off a thin finger reads the background
  or a mixed pixel, cm behind: a mixture whose spread along the ray exceeds the lateral one,
  though not by much once the gates remove the gross outliers: 2 (along-ray variance twice the
  lateral).
- ``template_memory_frames``, ``template_candidate_frames``: the body model (landmark
  coordinates in the body frame) is refined from every accepted frame and completed with the
  landmarks that were not RANSAC inliers at initialisation (``template.BodyTemplate.refine``);
  a model from a 5-frame window carries that window's (slowly varying) detector error forever.
- ``max_correlation_factor``: the published covariance is inflated by the measured
  frame-to-frame correlation of the fit residuals (``HandTracker.correlation_factor``, typically
  2.5-4.5 on the synthetic data): the kinematic filters treat successive poses as independent.

Tuning-split evidence for each physical term: docs/estimation.md#tuning-record.

Body-EKF blocks are ordered (translation, rotation, linear velocity, angular velocity), our
reading of Table I's ``P0_rb``/``Q_rb`` (docs/estimation.md#hand-body-ekf), and are hand-centred:
noise of the hand about its own origin, carried into the tracking frame with ``Ad(T)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

HAND_SELECTIONS = ("manipulating", "left", "right")
_TABLE_ONE_COVARIANCES = frozenset({
    "p0_lm_position_m2", "p0_lm_velocity_m2ps2", "q_lm_position_m2", "q_lm_velocity_m2ps2",
    "r_lm_m2", "lm_loss_trace_m2", "p0_rb_position_m2", "p0_rb_rotation_rad2",
    "p0_rb_linear_velocity_m2ps2", "p0_rb_angular_velocity_rad2ps2", "q_rb_position_m2",
    "q_rb_rotation_rad2", "q_rb_linear_velocity_m2ps2", "q_rb_angular_velocity_rad2ps2"})
_TABLE_ONE_GATES = frozenset({"mahalanobis_lm", "mahalanobis_rb", "ransac_inlier_mahalanobis"})


@dataclass(frozen=True)
class TrackerConfig:
    """Parameters of :class:`services.tracker.tracker.HandTracker` (Table I defaults)."""

    # Time base: Q values are variances added per `nominal_dt_s` (see module docstring).
    nominal_dt_s: float = 1.0 / 30.0

    # Landmark constant-velocity KF, one per landmark, state [position (m), velocity (m/s)].
    p0_lm_position_m2: float = 0.09
    p0_lm_velocity_m2ps2: float = 0.06
    q_lm_position_m2: float = 0.13
    q_lm_velocity_m2ps2: float = 0.05
    r_lm_m2: float = 0.05  # detector noise per axis, in the camera frame
    lm_loss_trace_m2: float = 0.3  # landmark dropped once trace(P_position) >= this
    visibility_threshold: float = 0.006  # landmarks with B_vis below this are missing
    # Landmark gate (Table-I units; 6.0 sigma in physical units): outlier if sqrt(y' S^-1 y) >= this.
    mahalanobis_lm: float = 0.19
    # A lost landmark whose filter had this many corrections restarts only within M_lm of the
    # lost filter's prediction (landmarks.py, "restart gate"); 0 gates every restart.
    lm_confirm_corrections: int = 3

    # Hand-body EKF on SE(3), error state [pose (v, w), twist (v, w)].
    p0_rb_position_m2: float = 0.05
    p0_rb_rotation_rad2: float = 0.2
    p0_rb_linear_velocity_m2ps2: float = 0.1
    p0_rb_angular_velocity_rad2ps2: float = 0.2
    q_rb_position_m2: float = 0.75
    q_rb_rotation_rad2: float = 3.0
    q_rb_linear_velocity_m2ps2: float = 2.4
    q_rb_angular_velocity_rad2ps2: float = 4.8
    # Body gates (Table-I units; 7.9 sigma in physical units): outlier if sqrt(y_i' S_i^-1 y_i)
    # >= this, against the predicted landmark and leave-one-out (body.py).
    mahalanobis_rb: float = 0.25

    # Feature saliency factors s_k: R_rb = s_k * P_lm (position block). The wrist is excluded.
    saliency_thumb: float = 1.5  # all four thumb landmarks (CMC, MCP, IP, tip)
    saliency_mcp: float = 1.5
    saliency_pip: float = 1.0
    saliency_dip: float = 1.5
    saliency_tip: float = 0.5

    # Probabilistic initialisation: weighted RANSAC over a window of frames.
    init_window_frames: int = 5  # frames of landmark motion the initialisation looks at
    ransac_iterations: int = 100
    # Inlier threshold of the weighted RANSAC (Table-I units, 7.9 sigma in physical units).
    ransac_inlier_mahalanobis: float = 0.25
    ransac_refinements: int = 2  # weighted-Kabsch refits on the inlier set
    min_inliers: int = 6  # landmarks needed to initialise and to correct the body

    # Re-initialisation: drop the body after this long without a correction.
    reinit_after_s: float = 0.5
    # Re-acquire a re-initialised hand in the body frame it had before (register the remembered
    # body model onto the new one), so hand poses stay comparable across the gap and the
    # kinematic level's displacements T(t) T(t0)^-1 remain valid. Off: every initialisation
    # defines a new body frame.
    reacquire_body_frame: bool = True

    # Publish covariances scaled by the smoothed a-posteriori variance of unit weight of the body
    # fit (1 when the noise model is right) and by the residual-correlation factor.
    calibrate_covariance: bool = True
    variance_factor_smoothing: float = 0.1  # per-frame EMA weight of the variance factor
    # Bound of the variance factor: each landmark's squared standardised residual enters it at
    # most as the 3-dof chi-square quantile of this many sigmas (3: 14.16), so the variance of
    # unit weight is at most that quantile / 2 (CovarianceCalibration; docs/estimation.md).
    variance_factor_residual_sigmas: float = 3.0
    # Upper bound of the published covariance's inflation for frame-to-frame error correlation,
    # (1 + rho) / (1 - rho) (1 = no inflation; HandTracker.correlation_factor).
    max_correlation_factor: float = 30.0

    # --- Physical terms (beyond Table I; see the module docstring) ---
    # Physical variance of one Table-I covariance unit [m^2 per unit]: R_lm = 0.05 units is the
    # detector's lateral noise, (7.1 mm)^2 (MediaPipe Hands: mean 2-D error 10 % of the palm).
    # 1.0 reads Table I literally in SI.
    variance_unit_m2: float = 1e-3
    # Along-ray variance of R_lm as a multiple of the lateral one (1 = the paper's isotropic R).
    depth_variance_factor: float = 2.0
    # Flexion std of each finger joint [rad] (articulation variance added to R_rb; 0 = rigid).
    articulation_std_rad: float = 0.15
    # Body-model refinement (template.BodyTemplate.refine): running mean of each landmark's
    # body-frame coordinates over up to this many frames (0 = fixed at initialisation) ...
    template_memory_frames: int = 60
    # ... and landmarks outside the initial model join it after this many observations.
    template_candidate_frames: int = 10

    # Ablation switch: False = uniform isotropic R_rb = R_lm (no saliency factors, no filter
    # covariance, no articulation; wrist used), isotropic R_lm, no gating at either level (nor
    # the body-model refinement's residual gate), uniform RANSAC sampling and residual weights.
    # Everything else is the same pipeline (covariance calibration, body-model refinement, ...).
    use_uncertainty_models: bool = True
    # With use_uncertainty_models False, keep the outlier gates of both levels and of the
    # body-model refinement on (the evaluation's "gates on" ablation, which separates the
    # gates from the noise models). No effect with the uncertainty models on.
    ablation_gates: bool = False

    # Kinematic motion model: predict the hand with the kinematic level's model when one is
    # given (False: static and constant velocity only; the evaluation's "ours w/o kin. prior").
    use_kinematic_prior: bool = True

    # Which detected hand to track: "manipulating" (hand identities kept by spatial continuity,
    # never by label or score; of two hands in view, the one that moved last, with hysteresis;
    # hands.py and docs/estimation.md#the-manipulating-hand), or "left" / "right" (only the hands
    # the detector labels so; for a detector whose labels can be trusted).
    hand_selection: str = "manipulating"
    # Identity by continuity: a detection whose centre (median landmark) is beyond this many
    # sigma of an identity's last centre, sigma = sqrt(hand_centre_std_m^2 + (hand_speed_std_mps
    # dt)^2) with dt since it was last seen, is not that hand.
    hand_association_gate_sigma: float = 4.0
    hand_centre_std_m: float = 0.03  # centre noise (occlusions move the median landmark)
    hand_speed_std_mps: float = 1.0  # hand speed (the generator's fastest demonstrations)
    hand_duplicate_distance_m: float = 0.03  # two detections this close are one hand
    hand_pair_memory_s: float = 2.0  # two hands count as in view this long after both were
    # Motion: a hand moved when the rigid motion from its anchor moves its landmarks by this RMS
    # for hand_motion_frames frames in a row (a resting hand's detections wander by up to 1.5 cm
    # over three frames on the tuning split, 8 cm in single frames); idle after
    # hand_idle_after_s without moving.
    hand_motion_threshold_m: float = 0.025
    hand_motion_frames: int = 3
    hand_idle_after_s: float = 1.0
    # Hysteresis: the body moves to the other hand only when the tracked one has not moved for
    # hand_switch_idle_s (a slow hand moves its landmarks 2.5 cm only every second or so) and the
    # other moved hand_switch_moves times since the tracked one last moved.
    hand_switch_idle_s: float = 2.0
    hand_switch_moves: int = 3
    # Two hands in view and neither moving: hold the frames back this long (they are estimated
    # late for the hand chosen), then take the better scored. Longer than the rest before a
    # manipulation usually lasts (about 1 s in the synthetic demonstrations): a wrong choice
    # costs a new body frame when the other hand then manipulates.
    hand_choice_wait_s: float = 4.0

    seed: int = 0  # seed of the tracker's RANSAC random generator

    def __post_init__(self) -> None:
        positive = {
            "nominal_dt_s": self.nominal_dt_s,
            "p0_lm_position_m2": self.p0_lm_position_m2,
            "p0_lm_velocity_m2ps2": self.p0_lm_velocity_m2ps2,
            "q_lm_position_m2": self.q_lm_position_m2,
            "q_lm_velocity_m2ps2": self.q_lm_velocity_m2ps2,
            "r_lm_m2": self.r_lm_m2,
            "lm_loss_trace_m2": self.lm_loss_trace_m2,
            "mahalanobis_lm": self.mahalanobis_lm,
            "p0_rb_position_m2": self.p0_rb_position_m2,
            "p0_rb_rotation_rad2": self.p0_rb_rotation_rad2,
            "p0_rb_linear_velocity_m2ps2": self.p0_rb_linear_velocity_m2ps2,
            "p0_rb_angular_velocity_rad2ps2": self.p0_rb_angular_velocity_rad2ps2,
            "q_rb_position_m2": self.q_rb_position_m2,
            "q_rb_rotation_rad2": self.q_rb_rotation_rad2,
            "q_rb_linear_velocity_m2ps2": self.q_rb_linear_velocity_m2ps2,
            "q_rb_angular_velocity_rad2ps2": self.q_rb_angular_velocity_rad2ps2,
            "mahalanobis_rb": self.mahalanobis_rb,
            "saliency_thumb": self.saliency_thumb,
            "saliency_mcp": self.saliency_mcp,
            "saliency_pip": self.saliency_pip,
            "saliency_dip": self.saliency_dip,
            "saliency_tip": self.saliency_tip,
            "ransac_inlier_mahalanobis": self.ransac_inlier_mahalanobis,
            "reinit_after_s": self.reinit_after_s,
            "hand_association_gate_sigma": self.hand_association_gate_sigma,
            "hand_centre_std_m": self.hand_centre_std_m,
            "hand_speed_std_mps": self.hand_speed_std_mps,
            "hand_duplicate_distance_m": self.hand_duplicate_distance_m,
            "hand_pair_memory_s": self.hand_pair_memory_s,
            "hand_motion_threshold_m": self.hand_motion_threshold_m,
            "hand_idle_after_s": self.hand_idle_after_s,
            "hand_switch_idle_s": self.hand_switch_idle_s,
            "hand_choice_wait_s": self.hand_choice_wait_s,
        }
        for name, value in positive.items():
            if not isinstance(value, (int, float)) or not value > 0.0 or value == float("inf"):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not 0.0 <= self.visibility_threshold <= 1.0:
            raise ValueError(f"visibility_threshold must be in [0, 1], got {self.visibility_threshold}")
        if self.init_window_frames < 1:
            raise ValueError(f"init_window_frames must be >= 1, got {self.init_window_frames}")
        if self.ransac_iterations < 1:
            raise ValueError(f"ransac_iterations must be >= 1, got {self.ransac_iterations}")
        if self.lm_confirm_corrections < 0:
            raise ValueError(f"lm_confirm_corrections must be >= 0, got {self.lm_confirm_corrections}")
        if self.ransac_refinements < 0:
            raise ValueError(f"ransac_refinements must be >= 0, got {self.ransac_refinements}")
        if self.min_inliers < 3:
            raise ValueError(f"min_inliers must be >= 3 (a rigid fit needs 3), got {self.min_inliers}")
        if self.hand_selection not in HAND_SELECTIONS:
            raise ValueError(f"hand_selection must be one of {HAND_SELECTIONS}, "
                             f"got {self.hand_selection!r}")
        for name in ("hand_switch_moves", "hand_motion_frames"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        for name in ("variance_unit_m2", "depth_variance_factor"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not 0.0 < value < float("inf"):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not 1.0 <= self.max_correlation_factor < float("inf"):
            raise ValueError(f"max_correlation_factor must be >= 1, got {self.max_correlation_factor}")
        if not 0.0 <= self.articulation_std_rad < float("inf"):
            raise ValueError(f"articulation_std_rad must be >= 0, got {self.articulation_std_rad}")
        if self.template_memory_frames < 0 or self.template_candidate_frames < 0:
            raise ValueError("template_memory_frames and template_candidate_frames must be >= 0")
        if not 0.0 < self.variance_factor_residual_sigmas < float("inf"):
            raise ValueError("variance_factor_residual_sigmas must be a finite number > 0, got "
                             f"{self.variance_factor_residual_sigmas!r}")
        if not 0.0 < self.variance_factor_smoothing <= 1.0:
            raise ValueError("variance_factor_smoothing must be in (0, 1], got "
                             f"{self.variance_factor_smoothing}")

    def internal(self) -> TrackerConfig:
        """This config in the filters' units: Table I's covariances in m^2/rad^2.

        Every Table-I covariance (``p0_*``, ``q_*``, ``r_lm_m2``, ``lm_loss_trace_m2``) is
        multiplied by ``variance_unit_m2`` and every Table-I Mahalanobis threshold
        (``mahalanobis_lm``, ``mahalanobis_rb``, ``ransac_inlier_mahalanobis``) divided by its
        square root, so the gains and the gate decisions are exactly Table I's while innovations,
        likelihoods and covariances are physical (module docstring). The physical fields (unit,
        depth, articulation, depth gate) are unchanged; the result has ``variance_unit_m2 = 1``.
        """
        c = self.variance_unit_m2
        if c == 1.0:
            return self
        values: dict[str, float] = {}
        for f in fields(self):
            if f.name in _TABLE_ONE_COVARIANCES:
                values[f.name] = getattr(self, f.name) * c
            elif f.name in _TABLE_ONE_GATES:
                values[f.name] = getattr(self, f.name) / math.sqrt(c)
        return replace(self, variance_unit_m2=1.0, **values)  # type: ignore[arg-type]

    @property
    def outlier_gates(self) -> bool:
        """Whether the Mahalanobis gates (landmark, body, body-model refinement) are on."""
        return self.use_uncertainty_models or self.ablation_gates

    def gate_sigmas(self) -> dict[str, float]:
        """The Table-I gates in sigma of the physical innovation they test (module docstring,
        "Gates in sigma"): each threshold of :meth:`internal`."""
        i = self.internal()
        return {"mahalanobis_lm": i.mahalanobis_lm, "mahalanobis_rb": i.mahalanobis_rb,
                "ransac_inlier_mahalanobis": i.ransac_inlier_mahalanobis}

    def saliency_factors(self) -> tuple[float, ...]:
        """s_k per landmark in MediaPipe order (21 values); the wrist's entry is 1.0 (unused)."""
        finger = (self.saliency_mcp, self.saliency_pip, self.saliency_dip, self.saliency_tip)
        return (1.0,) + (self.saliency_thumb,) * 4 + finger * 4


__all__ = ["HAND_SELECTIONS", "TrackerConfig"]
