"""Configuration of the hand tracker: landmark KFs, weighted RANSAC and the hand-body EKF.

Defaults are the ICRA-25 paper's Table I values (``helping-hand-kse-icra2025.tex``).

Units and dt-scaling of Table I
-------------------------------
All values are SI: positions in m, rotations in rad, velocities in m/s and rad/s, so a variance
is in m^2, rad^2, (m/s)^2 or (rad/s)^2. Initial covariances ``P0`` and the measurement noise
``R_lm`` are absolute. Process noises ``Q`` are the variance added **per nominal frame** of
``nominal_dt_s`` = 1/30 s (the Azure Kinect's 30 Hz), and are scaled linearly with the elapsed
time, ``Q_k = Q * dt / nominal_dt_s``, so a dropped frame adds the noise of two frames.

Why this reading: the paper's filters ran at a fixed 30 Hz, where a per-step ``Q`` is the simplest
implementation, and it is the one reading under which *every* Table-I threshold acts at a
physically meaningful distance:

- landmark gate ``M_lm = 0.19``: the steady-state innovation covariance is S ~ 0.22 m^2 per axis,
  so measurements that jump by more than ~9 cm from the landmark prediction are outliers;
- loss threshold ``trace(P_lm) >= 0.3``: the steady-state posterior trace is 0.12 and one frame
  of process noise adds 0.39, so a landmark whose correction is skipped once (missing or outlier)
  is dropped and re-initialised from its next measurement; ``3 * P0`` = 0.27 stays just below it;
- body gate ``M_rb = 0.25``: S ~ 0.8 m^2 (dominated by ``Q_rb``), i.e. ~22 cm against the
  predicted landmark; the leave-one-out check at the same threshold (``body.py``) carries only
  the uncertainty left once the other landmarks are seen and acts at ~3-6 cm on the filtered
  landmark (saliency 0.5 to 1.5), i.e. on jumps of ~4-7 cm in the detections;
- the landmark KF gain is ~0.78, so the filtered landmark lags the measurement by ~0.3 frame.

Read as variances per second instead (``Q_k = Q dt``), the landmark filter would smooth with a
gain of ~0.27 and lag fast hand motion by several cm. Either way the covariances are ~(20 cm)^2,
far above real detector noise (~1 cm): Table I is a consistent filter only up to a global
covariance scale, for which its tiny Mahalanobis thresholds compensate. Scaling every covariance
(``P0``, ``Q``, ``R`` and the loss threshold) by ``c`` and the thresholds by ``1/sqrt(c)`` leaves
every gain and gate decision unchanged (only the motion-model choice and the reported covariance
scale change); with ``c = sigma^2 / r_lm`` the reported covariances match landmark noise
``sigma`` (the tests' NEES check: ~4.9 for 6 DOF, slightly conservative because a landmark
filter's covariance overstates its error when the hand moves more smoothly than ``Q_lm``).

Body-EKF blocks are ordered (translation, rotation, linear velocity, angular velocity), our
reading of Table I's ``P0_rb``/``Q_rb`` (OMIP_JOINT_FILTERS.md §7.6), and are hand-centred:
noise of the hand about its own origin, carried into the tracking frame with ``Ad(T)``.
"""

from __future__ import annotations

from dataclasses import dataclass

HAND_SELECTIONS = ("best", "left", "right")


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
    mahalanobis_lm: float = 0.19  # outlier if sqrt(y' S^-1 y) >= this (landmark level)

    # Hand-body EKF on SE(3), error state [pose (v, w), twist (v, w)].
    p0_rb_position_m2: float = 0.05
    p0_rb_rotation_rad2: float = 0.2
    p0_rb_linear_velocity_m2ps2: float = 0.1
    p0_rb_angular_velocity_rad2ps2: float = 0.2
    q_rb_position_m2: float = 0.75
    q_rb_rotation_rad2: float = 3.0
    q_rb_linear_velocity_m2ps2: float = 2.4
    q_rb_angular_velocity_rad2ps2: float = 4.8
    mahalanobis_rb: float = 0.25  # outlier if sqrt(y_i' S_i^-1 y_i) >= this (body level)

    # Feature saliency factors s_k: R_rb = s_k * P_lm (position block). The wrist is excluded.
    saliency_thumb: float = 1.5  # all four thumb landmarks (CMC, MCP, IP, tip)
    saliency_mcp: float = 1.5
    saliency_pip: float = 1.0
    saliency_dip: float = 1.5
    saliency_tip: float = 0.5

    # Probabilistic initialisation: weighted RANSAC over a window of frames.
    init_window_frames: int = 5  # frames of landmark motion the initialisation looks at
    ransac_iterations: int = 100
    ransac_inlier_mahalanobis: float = 0.25  # weighted residual threshold (same scale as M_rb)
    ransac_refinements: int = 2  # weighted-Kabsch refits on the inlier set
    min_inliers: int = 6  # landmarks needed to initialise and to correct the body

    # Re-initialisation: drop the body after this long without a correction.
    reinit_after_s: float = 0.5

    # Publish covariances in metres/radians: scale by the smoothed a-posteriori variance of unit
    # weight of the body fit (Table I's covariances hold only up to a global scale).
    calibrate_covariance: bool = True
    variance_factor_smoothing: float = 0.1  # per-frame EMA weight of the variance factor

    # Ablation switch: False = uniform R_rb, no saliency factors (wrist used), no gating,
    # uniform RANSAC sampling and residual weights.
    use_uncertainty_models: bool = True

    # Which detected hand to track: "left", "right", or "best" (the highest-scoring hand when
    # the initialisation window starts; that handedness is kept, also across a re-initialisation,
    # until the hand is absent while no body is tracked).
    hand_selection: str = "best"

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
        if self.ransac_refinements < 0:
            raise ValueError(f"ransac_refinements must be >= 0, got {self.ransac_refinements}")
        if self.min_inliers < 3:
            raise ValueError(f"min_inliers must be >= 3 (a rigid fit needs 3), got {self.min_inliers}")
        if self.hand_selection not in HAND_SELECTIONS:
            raise ValueError(f"hand_selection must be one of {HAND_SELECTIONS}, "
                             f"got {self.hand_selection!r}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if not 0.0 < self.variance_factor_smoothing <= 1.0:
            raise ValueError("variance_factor_smoothing must be in (0, 1], got "
                             f"{self.variance_factor_smoothing}")

    def saliency_factors(self) -> tuple[float, ...]:
        """s_k per landmark in MediaPipe order (21 values); the wrist's entry is 1.0 (unused)."""
        finger = (self.saliency_mcp, self.saliency_pip, self.saliency_dip, self.saliency_tip)
        return (1.0,) + (self.saliency_thumb,) * 4 + finger * 4


__all__ = ["HAND_SELECTIONS", "TrackerConfig"]
