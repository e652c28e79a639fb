"""Configuration of the kinematic-model estimator (joint EKFs and model selection).

Defaults are the ICRA-25 Table I values for the joint EKFs and OMIP's ``joint_tracker_cfg.yaml``
(master, plus the ``wip_integrate_proprio_and_ft`` disconnected constant) for model selection; see
docs/estimation.md#parameters and the sections it links. Every field is a plain
``float``/``int``/``bool``/``str`` so the ``[kinematics]`` TOML section can set it.

Process-noise scales follow OMIP's dt scaling: a value ``s`` for an axis angle, a point coordinate or
the joint value ``q`` adds the variance ``s * dt**3 / 3`` per prediction of ``dt`` seconds, and a value
for the joint velocity adds ``s * dt``. Both kinds therefore have the unit ``unit**2 / s**3`` (m or
rad), written in the field names.

Departures from Table I / OMIP (axis and point process noise 100x below Table I,
``revolute_inflation_scale`` 3, filter start at 0.3 rad and 4 sigma with a provisional prismatic
start at 3 sigma, the tempered outlier-class likelihood, the rigid test instead of OMIP's motion
memory) and their tuning-partition evidence: docs/estimation.md#tuning-record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

LIKELIHOOD_AGGREGATIONS = ("tempered", "product", "mean")


@dataclass(frozen=True)
class KinematicsConfig:
    """Parameters of :class:`services.kinematics.estimator.KinematicEstimator`."""

    # --- Prismatic EKF, state (axis tangent b1, b2 [rad], q [m], qdot [m/s]) (Table I) ---
    # P0 = s * I4 (rad^2 for the axis, m^2 for q, m^2/s^2 for qdot).
    prismatic_initial_variance: float = 3.0
    # Q scale of each axis tangent coordinate: s * dt^3 / 3 [rad^2]
    # (Table I: 2.55; docs/estimation.md#tuning-record).
    prismatic_axis_noise_rad2_per_s3: float = 0.0255
    # Q scale of q: s * dt^3 / 3 [m^2].
    prismatic_q_noise_m2_per_s3: float = 0.7
    # Q scale of qdot: s * dt [m^2/s^2].
    prismatic_qdot_noise_m2_per_s3: float = 75.0

    # --- Revolute EKF, state (axis b1, b2 [rad], point p [m] (3), q [rad], qdot [rad/s]) ---
    revolute_initial_variance: float = 1.0
    # Axis Q scale [rad^2/s^3] (Table I: 2.55; docs/estimation.md#tuning-record).
    revolute_axis_noise_rad2_per_s3: float = 0.0255
    # Q scale of each point coordinate (applied orthogonally to the axis): s * dt^3 / 3 [m^2]
    # (Table I: 0.3; docs/estimation.md#tuning-record).
    revolute_point_noise_m2_per_s3: float = 0.0003
    revolute_q_noise_rad2_per_s3: float = 5.1
    revolute_qdot_noise_rad2_per_s3: float = 75.0

    # --- Measurement noise R = f * Sigma_z + floor * I (docs/estimation.md#measurement-noise) ---
    # Prismatic: f = 1 / (1 - exp(-|z| / length)), |z| = displacement norm [m].
    prismatic_inflation_length_m: float = 0.03
    # Revolute: f = 1 / (1 - exp(-sin(|w| / 2) / scale)), |w| = rotation angle of the delta [rad]
    # (OMIP: 1; docs/estimation.md#tuning-record).
    revolute_inflation_scale: float = 3.0
    # Both factors are clipped at this value.
    max_inflation_factor: float = 1e6
    # Variance added to every diagonal entry of R [m^2 or rad^2].
    measurement_noise_floor: float = 1e-6

    # --- Published covariance (docs/estimation.md#published-covariance) ---
    # The published joint covariance is the filter's times covariance_correlation_scale
    # (1 + rho) / (1 - rho), rho the lag-one autocorrelation of the filter's whitened innovations
    # (the filter counts correlated frames as independent), at least 1 and at most
    # max_covariance_inflation. The scale was fitted on the tuning partitions
    # (docs/estimation.md#tuning-record).
    covariance_correlation_scale: float = 0.5
    max_covariance_inflation: float = 30.0

    # Longest prediction step [s]: a longer gap between stamps is predicted as this long. The
    # constant-velocity model is not extrapolated over a long loss of tracking (for a revolute
    # joint that would pick an arbitrary 2 pi branch of q; the process noise grows as dt^3).
    max_prediction_dt_s: float = 0.5

    # --- Filter start (no init from a near-zero delta; docs/estimation.md#filter-start) ---
    # The prismatic filter starts once the hand origin moved this far from the reference [m].
    prismatic_min_translation_m: float = 0.01
    # The revolute filter starts once the hand rotated this much from the reference [rad]
    # (OMIP rev_min_rot_for_ee: 0.045; ours is above the drift of a landmark-tracked hand).
    revolute_min_rotation_rad: float = 0.3
    # ... and only once that motion is this many standard deviations of its measurement noise
    # (sqrt of the Mahalanobis form of the displacement / rotation vector), so the initial axis is
    # not drawn from noise.
    min_motion_sigmas: float = 4.0
    # The prismatic filter starts provisionally at this many sigmas (short strokes may never reach
    # min_motion_sigmas) and restarts from the displacement that first reaches min_motion_sigmas.
    prismatic_min_motion_sigmas: float = 3.0
    # ... once the displacement has been beyond the rigid test (rigid_test_sigmas) for this long
    # [s]: a displacement that persists, not a single noisy frame.
    prismatic_min_motion_s: float = 0.1
    # While the hand has not moved (the rigid test passes, no joint filter started), fuse every
    # pose into the reference pose (docs/estimation.md#reference-refinement). Off by default: it
    # changes the contact-phase segmentation's behaviour, which has not been re-validated.
    refine_reference_while_still: bool = False
    # ... until the displacement or the rotation from the reference exceeds this many sigmas.
    reference_still_sigmas: float = 2.5
    # A still pose is fused this long after its stamp, if the hand stayed still until then [s].
    reference_fusion_lag_s: float = 0.3
    # Each time the rotation from the reference has grown by this factor since the revolute filter
    # started (or was last checked), its axis is compared with the axis of the current delta; the
    # filter restarts from that delta when they differ by more than revolute_restart_sigmas (an
    # EKF started from a noisy axis converges slowly while its covariance shrinks;
    # docs/estimation.md#filter-start).
    revolute_recheck_growth: float = 1.5
    revolute_restart_sigmas: float = 4.0

    # --- Model selection (docs/estimation.md#model-selection) ---
    # Number of history entries sampled uniformly over the whole demonstration.
    likelihood_sample_num: int = 100
    # Fixed standard deviations of the per-sample error densities.
    likelihood_sigma_translation_m: float = 0.05
    likelihood_sigma_rotation_rad: float = 0.2
    # "tempered" (default): per-sample mixture of the error density and an outlier class, summed
    # and scaled to the effective number of independent samples
    # (docs/estimation.md#model-selection).
    # "product": log L = sum of the per-sample log densities (the samples as independent).
    # "mean": log L = log of the arithmetic mean of the densities (OMIP's formula).
    likelihood_aggregation: str = "tempered"
    # Weight of the outlier class in each sample's mixture: a sample the hypothesis does not
    # explain still scores this times the disconnected density ("tempered" only).
    likelihood_outlier_weight: float = 0.1
    # Correlation time of the hand-pose errors [s]: "tempered" counts one independent sample per
    # this much demonstration (at least 1, at most the number of samples).
    likelihood_correlation_time_s: float = 0.14
    # Rigid test (docs/estimation.md#rigid-test): a component of a sample's delta (hand
    # displacement; rotation) whose Mahalanobis distance against the published covariance is
    # within this many sigmas is no motion; beyond it, the sigmas in excess are rigid's error. The
    # rotation of the prismatic hypothesis is tested the same way.
    rigid_test_sigmas: float = 2.5
    # Std of the normal prior on the distance from the revolute axis to the hand [m].
    revolute_max_joint_distance_m: float = 0.5
    # Per-sample density level of the "disconnected" hypothesis (OMIP wip disconnected_ne; with
    # the 0.25 prior this is OMIP's constant score 0.8).
    disconnected_density: float = 3.2
    # Unnormalised prior of each type (OMIP: 1/4 each).
    prior_rigid: float = 0.25
    prior_prismatic: float = 0.25
    prior_revolute: float = 0.25
    prior_disconnected: float = 0.25

    # --- History and reporting ---
    # Maximum number of stored deltas; when full, every other one is dropped and the sampling
    # stride doubles, so the stored entries stay uniformly spread over the demonstration.
    history_capacity: int = 256
    # The belief's type stays "unknown" for the first this-many updates (OMIP creates the joint
    # filters on the 5th frame of a pair).
    min_updates_for_type: int = 5
    # Without enough motion to start a joint filter, the type stays "unknown" until the hand has
    # been observed for this long [s]; after that "rigid" is a supported conclusion.
    min_still_duration_for_rigid_s: float = 1.0

    # --- Input gates (docs/estimation.md#input-gates) ---
    # A hand pose is an outlier, not used, when the squared Mahalanobis distance of its innovation
    # from the confident joint model's prediction, and of its jump from the last accepted pose's
    # innovation, exceed the chi-square (6 dof) quantile of this many standard deviations
    # (8: 82.2; on the synthetic demonstrations the first stays below 29).
    outlier_gate_sigmas: float = 8.0
    # ... applied once the published type is prismatic or revolute with at least this probability.
    outlier_gate_min_probability: float = 0.999
    # Whatever the model, a hand pose this far from the demonstration's first one is an outlier [m].
    max_hand_displacement_m: float = 3.0
    # A run of at least this many consecutive outliers spanning at least outlier_run_s of stamps
    # is the hand's real motion: against a joint prediction the gate yields (the poses are used
    # until one is inside the gate again); against the displacement bound the demonstration
    # restarts from the current pose.
    outlier_run_count: int = 15
    outlier_run_s: float = 0.5

    def __post_init__(self) -> None:
        positive = (
            "prismatic_initial_variance", "revolute_initial_variance",
            "prismatic_inflation_length_m", "revolute_inflation_scale",
            "likelihood_sigma_translation_m", "likelihood_sigma_rotation_rad",
            "likelihood_correlation_time_s",
            "revolute_max_joint_distance_m", "disconnected_density",
            "prismatic_min_translation_m", "revolute_min_rotation_rad", "max_prediction_dt_s",
            "outlier_gate_sigmas", "max_hand_displacement_m", "covariance_correlation_scale",
            "revolute_restart_sigmas", "reference_still_sigmas",
        )
        non_negative = (
            "prismatic_axis_noise_rad2_per_s3", "prismatic_q_noise_m2_per_s3",
            "prismatic_qdot_noise_m2_per_s3", "revolute_axis_noise_rad2_per_s3",
            "revolute_point_noise_m2_per_s3", "revolute_q_noise_rad2_per_s3",
            "revolute_qdot_noise_rad2_per_s3", "measurement_noise_floor",
            "prior_rigid", "prior_prismatic", "prior_revolute", "prior_disconnected",
            "min_still_duration_for_rigid_s", "min_motion_sigmas", "outlier_run_s",
            "prismatic_min_motion_sigmas", "prismatic_min_motion_s",
            "rigid_test_sigmas", "reference_fusion_lag_s",
        )
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"{f.name} must be finite, got {value!r}")
        for name in positive:
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in non_negative:
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not self.revolute_recheck_growth > 1.0:
            raise ValueError("revolute_recheck_growth must be > 1, got "
                             f"{self.revolute_recheck_growth!r}")
        if not self.max_covariance_inflation >= 1.0:
            raise ValueError("max_covariance_inflation must be >= 1, got "
                             f"{self.max_covariance_inflation!r}")
        if not self.max_inflation_factor >= 1.0:
            raise ValueError(f"max_inflation_factor must be >= 1, got {self.max_inflation_factor!r}")
        if self.prior_disconnected <= 0.0:
            raise ValueError("prior_disconnected must be > 0 (the posterior needs one finite score)")
        if self.prismatic_min_motion_sigmas > self.min_motion_sigmas:
            raise ValueError("prismatic_min_motion_sigmas must be <= min_motion_sigmas, got "
                             f"{self.prismatic_min_motion_sigmas!r} > {self.min_motion_sigmas!r}")
        if not 0.0 < self.likelihood_outlier_weight < 1.0:
            raise ValueError("likelihood_outlier_weight must be in (0, 1), got "
                             f"{self.likelihood_outlier_weight!r}")
        if self.likelihood_sample_num < 1:
            raise ValueError(f"likelihood_sample_num must be >= 1, got {self.likelihood_sample_num}")
        if self.history_capacity < 2 * self.likelihood_sample_num or self.history_capacity % 2:
            raise ValueError(
                f"history_capacity must be even and >= 2 * likelihood_sample_num "
                f"({2 * self.likelihood_sample_num}), got {self.history_capacity}")
        if not 0.0 < self.outlier_gate_min_probability <= 1.0:
            raise ValueError("outlier_gate_min_probability must be in (0, 1], got "
                             f"{self.outlier_gate_min_probability!r}")
        if self.outlier_run_count < 1:
            raise ValueError(f"outlier_run_count must be >= 1, got {self.outlier_run_count}")
        if self.min_updates_for_type < 1:
            raise ValueError(f"min_updates_for_type must be >= 1, got {self.min_updates_for_type}")
        if self.likelihood_aggregation not in LIKELIHOOD_AGGREGATIONS:
            raise ValueError(f"likelihood_aggregation must be one of {LIKELIHOOD_AGGREGATIONS}, "
                             f"got {self.likelihood_aggregation!r}")
