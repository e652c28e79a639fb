"""Hand tracker: 21 landmarks per frame in, hand rigid-body pose, twist and covariance out.

Per accepted frame (:meth:`HandTracker.step`):

1. Reject bad frames (duplicate or out-of-order stamp, bad camera pose, a change between
   camera and world tracking) and bad hands (shape, handedness, non-finite visibility/score),
   counting each in ``rejected[reason]``; nothing raises on bad data.
2. Transform the landmarks and the detector noise ``R_lm`` into the tracking frame ("world" when
   ``T_world_camera`` is given, else "camera") and run the landmark KFs of both hand slots
   (``landmarks.py``).
3. Before initialisation: collect a window of frames of the tracked hand and try the weighted
   RANSAC initialisation (``ransac.py``); the output says ``initialized=False``.
4. After: predict the motion models, choose, gate and correct the body EKF (``body.py``).
   The body level feeds back to the landmark level, as in OMIP: a landmark it rejects has its
   correction undone (as if the landmark gate had rejected it), and a landmark filter that
   (re)starts on the tracked hand starts with the body's velocity at that point.

``step`` returns None for rejected frames and for frames that carry no correction of an
initialised body (tracked hand absent, or fewer than ``min_inliers`` usable landmarks; counted in
``skipped``); publishing a prediction there would look like a measurement downstream. The body is
dropped and re-initialised after ``reinit_after_s`` without a correction.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import skew
from services.tracker.body import (
    MOTION_MODELS,
    HandBodyEkf,
    body_noise_matrices,
    select_and_gate,
)
from services.tracker.config import TrackerConfig
from services.tracker.landmarks import (
    NUM_LANDMARKS,
    WRIST,
    LandmarkFilterBank,
    body_landmark_mask,
    body_measurement_variances,
    missing_mask,
)
from services.tracker.ransac import initial_body, rigid_ransac

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
KinematicPrior = Callable[[int], "tuple[np.ndarray, np.ndarray] | None"]

HANDS = ("left", "right")  # slot order of the landmark filter bank
STATUS_UNUSED = 0  # no filter, no measurement this frame, or not part of the body model
STATUS_USED = 1  # fresh measurement used by the body (or, before initialisation, collected)
STATUS_OUTLIER = 2  # rejected this step (landmark gate, body gates or RANSAC)
STATUS_EXCLUDED = 3  # the wrist, excluded by the saliency model

_ROTATION_TOL = 1e-6
_MAX_COORD_M = 1e3  # coordinates beyond 1 km are treated as missing (keeps the numerics finite)


@dataclass(frozen=True, eq=False)
class HandObservation:
    """One detected hand: ``points`` (21, 3) in the camera frame (m), NaN = missing (so is any
    non-finite coordinate, one beyond 1 km, or a visibility below the threshold);
    ``visibility`` (21,) in [0, 1]; ``handedness`` "left" / "right"; detection ``score``."""

    handedness: str
    score: float
    points: np.ndarray
    visibility: np.ndarray


@dataclass(frozen=True, eq=False)
class HandBodyEstimate:
    """The tracked hand body at ``stamp_ns``, in ``frame_id`` ("camera" or "world").

    - ``pose``: ``T_frame_hand`` (4, 4); identity while not ``initialized``. The hand (body)
      frame is fixed at initialisation: origin at the centroid of the RANSAC inlier landmarks,
      axes parallel to ``frame_id`` (``ransac.py``); a re-initialisation starts a new one.
    - ``twist``: (6,) left twist ``[v, w]`` (m/s, rad/s) in ``frame_id``:
      ``T(t + dt) ~= Exp(dt twist) T(t)``.
    - ``covariance``: (12, 12) over [pose left perturbation (v, w), twist (v, w)].
    - ``motion_model``: the prediction that won this step.
    - ``landmark_points``: (21, 3) float32 filtered positions in ``frame_id``, NaN where no filter.
    - ``landmark_variance``: (21,) float32 ``trace(R_rb)`` (m^2), the body-level measurement
      variance (saliency factor times the trace of the filter's position covariance; the
      wrist's is ``trace(P_lm)``; ``3 r_lm`` for every landmark in the ablation), NaN where no
      filter.
    - ``landmark_status``: (21,) uint8: 0 unused, 1 used, 2 outlier this step, 3 excluded (wrist).
    """

    stamp_ns: int
    frame_id: str
    initialized: bool
    pose: Array
    twist: Array
    covariance: Array
    motion_model: str
    landmark_points: NDArray[np.float32]
    landmark_variance: NDArray[np.float32]
    landmark_status: NDArray[np.uint8]


@dataclass(frozen=True, eq=False)
class _WindowFrame:
    stamp_ns: int
    positions: Array  # (21, 3)
    variances: Array  # (21,) per-axis R_rb
    usable: BoolArray  # (21,)


def _valid_pose(T: object) -> Array | None:
    """T as a float (4, 4) rigid transform, or None if it is not one."""
    try:
        M = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        return None
    if M.shape != (4, 4) or not np.isfinite(M).all():
        return None
    if np.abs(M[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-9:
        return None
    Rm = M[:3, :3]
    if np.abs(Rm.T @ Rm - np.eye(3)).max() > _ROTATION_TOL or np.linalg.det(Rm) <= 0.0:
        return None
    return M


class HandTracker:
    """Landmark KFs + weighted RANSAC initialisation + hand-body EKF for one tracked hand.

    ``rejected``: reason -> count of rejected frames/hands/priors; ``skipped``: reason -> count of
    accepted frames that produced no estimate; ``reinitializations``: bodies dropped.
    """

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self.rejected: dict[str, int] = {}
        self.skipped: dict[str, int] = {}
        self.reinitializations = 0
        self._body_mask = body_landmark_mask(config)
        self._P0_rb, self._Q_rb = body_noise_matrices(
            (config.p0_rb_position_m2, config.p0_rb_rotation_rad2,
             config.p0_rb_linear_velocity_m2ps2, config.p0_rb_angular_velocity_rad2ps2),
            (config.q_rb_position_m2, config.q_rb_rotation_rad2,
             config.q_rb_linear_velocity_m2ps2, config.q_rb_angular_velocity_rad2ps2))
        self._bank = LandmarkFilterBank(len(HANDS) * NUM_LANDMARKS, config)
        self._window: deque[_WindowFrame] = deque(maxlen=config.init_window_frames)
        self.reset()

    # --- public API -------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget everything (filters, body, stamps, tracking frame); re-seed the rng."""
        self._bank.reset()
        self._window.clear()
        self._rng = np.random.default_rng(self.config.seed)
        self._last_stamp_ns: int | None = None
        self._frame_id: str | None = None
        self._slot: int | None = None
        self._ekf: HandBodyEkf | None = None
        self._points_body: Array | None = None
        self._body_stamp_ns = 0
        self._variance_factor: float | None = None

    @property
    def initialized(self) -> bool:
        """Whether a hand body is being tracked."""
        return self._ekf is not None

    @property
    def body_points(self) -> Array | None:
        """(21, 3) body-frame coordinates fixed at initialisation (NaN: not in the body model)."""
        return None if self._points_body is None else self._points_body.copy()

    def step(self, stamp_ns: int, hands: Sequence[HandObservation],
             T_world_camera: np.ndarray | None = None,
             kinematic_prior: KinematicPrior | None = None) -> HandBodyEstimate | None:
        """Process one frame of detections (see module docstring); None if nothing to report.

        ``T_world_camera``: camera pose for a moving camera (landmarks are then tracked in
        "world"). ``kinematic_prior(stamp_ns)``: (predicted ``T_frame_hand`` (4, 4), its 6x6
        left-perturbation covariance) in the tracking frame, or None.
        """
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, (int, np.integer)):
            self._reject("bad_stamp")
            return None
        stamp_ns = int(stamp_ns)
        if self._last_stamp_ns is not None:
            if stamp_ns == self._last_stamp_ns:
                self._reject("duplicate_stamp")
                return None
            if stamp_ns < self._last_stamp_ns:
                self._reject("out_of_order_stamp")
                return None
        T_wc: Array | None = None
        if T_world_camera is not None:
            T_wc = _valid_pose(T_world_camera)
            if T_wc is None:
                self._reject("bad_camera_pose")
                return None
        frame_id = "camera" if T_wc is None else "world"
        if self._frame_id is not None and frame_id != self._frame_id:
            self._reject("frame_mismatch")
            return None
        self._frame_id = frame_id

        observed = self._parse_hands(hands)
        slot = self._tracked_slot(observed)
        z = np.full((len(HANDS) * NUM_LANDMARKS, 3), np.nan)
        for s, (_, points) in observed.items():
            z[s * NUM_LANDMARKS:(s + 1) * NUM_LANDMARKS] = (
                points if T_wc is None else points @ T_wc[:3, :3].T + T_wc[:3, 3])
        # The detector noise R_lm = r I3 is isotropic, so R_wc R_lm R_wc' = R_lm: the covariance
        # transform into the world frame is exact and leaves the scalar unchanged.
        if self._last_stamp_ns is not None:
            self._bank.predict((stamp_ns - self._last_stamp_ns) * 1e-9)
        self._last_stamp_ns = stamp_ns
        update = self._bank.update(z, self.config.r_lm_m2, gate=self.config.use_uncertainty_models,
                                   v_start=self._start_velocities(slot, z))

        if slot is None or slot not in observed:
            if self._ekf is not None:
                self._maybe_drop_body(stamp_ns)
            else:
                self._window.clear()
                if self.config.hand_selection == "best":
                    self._slot = None
            self._skip("no_hand")
            return None

        rows = slice(slot * NUM_LANDMARKS, (slot + 1) * NUM_LANDMARKS)
        status = np.zeros(NUM_LANDMARKS, dtype=np.uint8)
        status[update.rejected[rows]] = STATUS_OUTLIER
        if self.config.use_uncertainty_models:
            status[WRIST] = STATUS_EXCLUDED
        usable = update.fresh[rows] & self._body_mask
        model: str | None
        if self._ekf is None:
            model = self._initialise(stamp_ns, rows, usable, status)
        else:
            model = self._track(stamp_ns, rows, usable, status, kinematic_prior)
        if model is None:
            return None
        # Outputs after the body step: a body-level rejection undoes the landmark correction.
        positions, r_rb = self._body_inputs(rows)
        variance = np.where(self._bank.alive[rows], 3.0 * r_rb, np.nan)
        return self._estimate(stamp_ns, positions, variance, status, model)

    # --- internals --------------------------------------------------------------------------

    def _reject(self, reason: str) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1

    def _skip(self, reason: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1

    def _parse_hands(self, hands: Sequence[HandObservation]) -> dict[int, tuple[float, Array]]:
        """Valid hands by slot: (score, points (21, 3) with NaN where missing)."""
        out: dict[int, tuple[float, Array]] = {}
        for hand in hands:
            try:
                points = np.asarray(hand.points, dtype=float)
                visibility = np.asarray(hand.visibility, dtype=float)
                score = float(hand.score)
                handedness = str(hand.handedness).lower()
            except (TypeError, ValueError, AttributeError):
                self._reject("bad_hand")
                continue
            if points.shape != (NUM_LANDMARKS, 3) or visibility.shape != (NUM_LANDMARKS,):
                self._reject("bad_shape")
                continue
            if handedness not in HANDS:
                self._reject("bad_handedness")
                continue
            if not np.isfinite(visibility).all():
                self._reject("non_finite_visibility")
                continue
            if not np.isfinite(score):
                self._reject("non_finite_score")
                continue
            slot = HANDS.index(handedness)
            if slot in out:
                self._reject("duplicate_handedness")
                if score <= out[slot][0]:
                    continue
            missing = missing_mask(points, visibility, self.config.visibility_threshold)
            missing |= ~(np.abs(points) < _MAX_COORD_M).all(axis=1)  # NaN compares False
            out[slot] = (score, np.where(missing[:, None], np.nan, points))
        return out

    def _tracked_slot(self, observed: dict[int, tuple[float, Array]]) -> int | None:
        """The slot of the tracked hand; "best" locks the best-scored hand until re-init."""
        selection = self.config.hand_selection
        if selection != "best":
            return HANDS.index(selection)
        if self._slot is None and observed:
            self._slot = max(observed, key=lambda s: observed[s][0])
        return self._slot

    def _maybe_drop_body(self, stamp_ns: int) -> None:
        """Drop the body once it has gone ``reinit_after_s`` without a correction."""
        if (stamp_ns - self._body_stamp_ns) * 1e-9 >= self.config.reinit_after_s:
            self._ekf = None
            self._points_body = None
            self._window.clear()
            self.reinitializations += 1

    def _estimate(self, stamp_ns: int, positions: Array, variance: Array,
                  status: NDArray[np.uint8], motion_model: str) -> HandBodyEstimate:
        assert self._frame_id is not None
        ekf = self._ekf
        return HandBodyEstimate(
            stamp_ns=stamp_ns, frame_id=self._frame_id, initialized=ekf is not None,
            pose=np.eye(4) if ekf is None else ekf.T.copy(),
            twist=np.zeros(6) if ekf is None else ekf.xi.copy(),
            covariance=self._P0_rb.copy() if ekf is None else ekf.P * self.variance_factor,
            motion_model=motion_model,
            landmark_points=positions.astype(np.float32),
            landmark_variance=variance.astype(np.float32),
            landmark_status=status)

    def _start_velocities(self, slot: int | None, z: Array) -> Array | None:
        """Initial velocities for landmark filters that start this frame: on the tracked hand,
        the velocity of the body at the landmark, ``v + w x z`` (left twist); else 0."""
        if self._ekf is None or slot is None:
            return None
        v = np.zeros_like(z)
        rows = slice(slot * NUM_LANDMARKS, (slot + 1) * NUM_LANDMARKS)
        xi = self._ekf.xi
        v[rows] = xi[:3] + z[rows] @ skew(xi[3:]).T  # NaN rows are not started
        return v

    def _body_inputs(self, rows: slice) -> tuple[Array, Array]:
        """Filtered positions (21, 3) and per-axis ``R_rb`` variances (21,) of the tracked hand."""
        bank = self._bank
        positions = np.where(bank.alive[rows, None], bank.x[rows, :3], np.nan)
        return positions, body_measurement_variances(bank.pp[rows], self.config)

    def _initialise(self, stamp_ns: int, rows: slice, usable: BoolArray,
                    status: NDArray[np.uint8]) -> str:
        """Collect the window; try the weighted RANSAC once it is full. Returns the model name."""
        positions, r_rb = self._body_inputs(rows)
        self._window.append(_WindowFrame(stamp_ns, positions, r_rb, usable.copy()))
        status[usable] = STATUS_USED
        cfg = self.config
        if len(self._window) < cfg.init_window_frames:
            return MOTION_MODELS[0]
        first, last = self._window[0], self._window[-1]
        eligible = first.usable & last.usable
        if eligible.sum() < cfg.min_inliers:
            return MOTION_MODELS[0]
        result = rigid_ransac(first.positions[eligible], last.positions[eligible],
                              first.variances[eligible], last.variances[eligible],
                              iterations=cfg.ransac_iterations,
                              threshold=cfg.ransac_inlier_mahalanobis,
                              refinements=cfg.ransac_refinements, rng=self._rng)
        if result is None or result.inliers.sum() < cfg.min_inliers:
            return MOTION_MODELS[0]
        inliers = np.zeros(NUM_LANDMARKS, dtype=bool)
        inliers[np.flatnonzero(eligible)[result.inliers]] = True
        frames = list(self._window)
        body = initial_body(np.stack([f.positions for f in frames]),
                            np.stack([f.variances for f in frames]),
                            np.stack([f.usable for f in frames]),
                            np.array([f.stamp_ns for f in frames], dtype=float) * 1e-9,
                            inliers, result.transform)
        self._ekf = HandBodyEkf(body.T_frame_body, body.twist, self._P0_rb, self._Q_rb,
                                cfg.nominal_dt_s)
        self._points_body = body.points_body
        self._body_stamp_ns = stamp_ns
        self._window.clear()
        status[usable & ~inliers] = STATUS_OUTLIER
        return MOTION_MODELS[0]

    def _update_variance_factor(self, positions: Array, points_body: Array, r_rb: Array) -> None:
        """Track the a-posteriori variance of unit weight of the body fit.

        Table I's covariances are right only up to one global scale (about (20 cm)^2 against
        mm-level landmark noise). ``sum(|r_i|^2 / R_i) / (3n - 6)`` over the posterior residuals
        ``r_i = z_i - T p_i`` estimates that scale; it is smoothed over frames and applied to the
        published covariance, so downstream consumers get metres and radians. Kalman gains do
        not change under a global scale, so the estimates themselves are unaffected.
        """
        ekf = self._ekf
        assert ekf is not None
        n = positions.shape[0]
        if n * 3 <= 6:
            return
        residual = positions - (points_body @ ekf.T[:3, :3].T + ekf.T[:3, 3])
        sample = float(np.sum(residual * residual / r_rb[:, None])) / (3 * n - 6)
        if not math.isfinite(sample) or sample <= 0.0:
            return
        if self._variance_factor is None:
            self._variance_factor = sample
        else:
            a = self.config.variance_factor_smoothing
            self._variance_factor += a * (sample - self._variance_factor)

    @property
    def variance_factor(self) -> float:
        """Scale applied to the published covariance (1 until measured or when disabled)."""
        if not self.config.calibrate_covariance or self._variance_factor is None:
            return 1.0
        return self._variance_factor

    def _kinematic(self, prior: KinematicPrior | None, stamp_ns: int
                   ) -> tuple[Array, Array] | None:
        """The caller's kinematic prediction for this stamp, validated (None if absent/bad)."""
        if prior is None:
            return None
        value = prior(stamp_ns)
        if value is None:
            return None
        try:
            T_raw, Sigma_raw = value
            Sigma = np.asarray(Sigma_raw, dtype=float)
        except (TypeError, ValueError):
            self._reject("bad_kinematic_prior")
            return None
        T = _valid_pose(T_raw)
        if T is None or Sigma.shape != (6, 6) or not np.isfinite(Sigma).all():
            self._reject("bad_kinematic_prior")
            return None
        Sigma = 0.5 * (Sigma + Sigma.T)
        scale = max(float(np.abs(Sigma).max()), 1e-300)
        if np.linalg.eigvalsh(Sigma)[0] < -1e-9 * scale:
            self._reject("bad_kinematic_prior")
            return None
        return T, Sigma

    def _track(self, stamp_ns: int, rows: slice, usable: BoolArray, status: NDArray[np.uint8],
               prior: KinematicPrior | None) -> str | None:
        """Predict, choose the motion model, gate and correct the body EKF.

        Returns the winning model's name, or None when no correction was possible (the body may
        then have been dropped, in which case this frame starts a new initialisation window).
        """
        ekf = self._ekf
        assert ekf is not None and self._points_body is not None
        cfg = self.config
        positions, r_rb = self._body_inputs(rows)
        candidates = usable & np.isfinite(self._points_body).all(axis=1)
        idx = np.flatnonzero(candidates)
        if idx.size >= cfg.min_inliers:
            dt = (stamp_ns - self._body_stamp_ns) * 1e-9
            predictions = ekf.predict(dt, self._kinematic(prior, stamp_ns))
            step = select_and_gate(predictions, positions[idx], self._points_body[idx],
                                   r_rb[idx], cfg.mahalanobis_rb, gate=cfg.use_uncertainty_models)
            rejected = idx[step.rejected]
            status[rejected] = STATUS_OUTLIER
            if rejected.size:
                mask = np.zeros(self._bank.n, dtype=bool)
                mask[rows][rejected] = True
                self._bank.reject(mask)
                usable[rejected] = False
            used = idx[step.accepted]
            if used.size >= cfg.min_inliers:
                chosen = predictions[step.model]
                ekf.update_chosen(predictions, step)
                self._update_variance_factor(positions[used], self._points_body[used], r_rb[used])
                self._body_stamp_ns = stamp_ns
                status[used] = STATUS_USED
                return chosen.model
        self._maybe_drop_body(stamp_ns)
        if self._ekf is not None:
            self._skip("too_few_landmarks")
            return None
        return self._initialise(stamp_ns, rows, usable, status)


__all__ = [
    "HANDS",
    "STATUS_EXCLUDED",
    "STATUS_OUTLIER",
    "STATUS_UNUSED",
    "STATUS_USED",
    "HandBodyEstimate",
    "HandObservation",
    "HandTracker",
]
