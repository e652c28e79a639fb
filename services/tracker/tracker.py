"""Hand tracker: 21 landmarks per frame in, hand rigid-body pose, twist and covariance out.

This module orchestrates the levels, whose computations live in the modules named below; it is
longer than the house's ~450 lines because what is left is one job, the per-frame state machine
over the state the levels share (hand identities, held-back frames, window, body, memory,
stamps), with its interface types. Per accepted frame (:meth:`HandTracker.step`):

1. Reject bad frames (bad, duplicate or out-of-order stamp, bad camera pose, a change between
   camera and world tracking) and bad hands (shape, handedness, non-finite visibility/score, a
   duplicate detection of one hand, a third hand), reporting each in the step's
   :class:`StepResult` and counting it in ``rejected[reason]``; nothing raises on bad data.
2. Give each hand its identity by position, never by label or score (``hands.py``), transform
   the landmarks and the detector noise ``R_lm`` (anisotropic about each viewing ray,
   ``depth_variance_factor``) into the tracking frame ("world" when ``T_world_camera`` is given,
   else "camera") and run the landmark KFs of both identities (``landmarks.py``). Choose the
   hand the body follows: the manipulating one (:meth:`HandTracker._tracked_slot`); while two
   hands are in view and neither has moved, the frames are held back and later run for the
   hand chosen (:meth:`HandTracker._replay`, ``StepResult.replayed``).
3. Before initialisation: collect a window of frames of the tracked hand and try the weighted
   RANSAC initialisation (``ransac.py``); the output says ``initialized=False``. The window also
   calibrates the new body (``calibration.py``): its first published covariance, the kinematic
   level's reference pose, is then already honest.
4. After: predict the motion models, choose, gate and correct the body EKF (``body.py``).
   The body level feeds back to the landmark level, as in OMIP: a landmark it rejects has its
   correction undone (as if the landmark gate had rejected it), and a landmark filter that
   (re)starts on the tracked hand starts with the body's velocity at that point. The body model
   is then refined and completed from the accepted landmarks (``template.py``).

All filter covariances are physical (m^2, rad^2): Table I's values times ``variance_unit_m2``
(``TrackerConfig.internal``). The published covariance is the filter's, scaled by the smoothed
a-posteriori variance factor of the body fit and by the frame-to-frame correlation factor of its
residuals (``calibration.py``; :attr:`HandTracker.variance_factor`); every covariance the body
level factors or adopts is checked and, if round-off broke it, repaired and counted
(``covariance.py``), so what is published is positive semi-definite. Every estimate names its
body frame's epoch (``HandBodyEstimate.body_epoch``).

``step`` returns a :class:`StepResult` without an estimate for rejected frames and for frames
that carry no correction of an initialised body (tracked hand absent, or fewer than
``min_inliers`` usable landmarks; counted in ``skipped``); publishing a prediction there would
look like a measurement downstream. The body is dropped and re-initialised after
``reinit_after_s`` without a correction.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import check_pose, skew
from services.tracker.body import MOTION_MODELS, HandBodyEkf, body_noise_matrices, select_and_gate
from services.tracker.calibration import (
    CovarianceCalibration,
    WindowFrame,
    fit_residuals,
    window_fit_covariance,
)
from services.tracker.config import TrackerConfig
from services.tracker.covariance import is_psd, psd_repaired
from services.tracker.hands import NUM_IDENTITIES, HandIdentities, robust_centre
from services.tracker.landmarks import (
    NUM_LANDMARKS,
    WRIST,
    LandmarkFilterBank,
    LandmarkUpdate,
    articulation_variances,
    body_landmark_mask,
    body_measurement_covariances,
    ray_measurement_covariances,
)
from services.tracker.ransac import initial_body, rigid_ransac
from services.tracker.template import BodyTemplate

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
KinematicPrior = Callable[[int], "tuple[np.ndarray, np.ndarray] | None"]

HANDS = ("left", "right")  # the handedness labels a detection may carry
STATUS_UNUSED = 0  # no filter, no measurement this frame, or not part of the body model
STATUS_USED = 1  # fresh measurement used by the body (or, before initialisation, collected)
STATUS_OUTLIER = 2  # rejected this step (landmark gate, body gates or RANSAC)
STATUS_EXCLUDED = 3  # the wrist, excluded by the saliency model

FrameRejection = Literal["bad_stamp", "duplicate_stamp", "out_of_order_stamp", "bad_camera_pose",
                         "frame_mismatch"]
HandRejection = Literal["bad_hand", "bad_shape", "bad_handedness", "non_finite_visibility",
                        "non_finite_score", "duplicate_hand", "extra_hand"]
FRAME_REJECTIONS: frozenset[str] = frozenset(get_args(FrameRejection))
Rejection = FrameRejection | HandRejection | Literal["bad_kinematic_prior"]
Skip = Literal["no_hand", "choosing_hand", "too_few_landmarks", "bad_covariance"]
SKIP_REASONS: tuple[Skip, ...] = get_args(Skip)
# Things a step handled that a consumer or operator should know of (counted in HandTracker.notes).
Note = Literal["second_hand_moving", "hand_switched", "covariance_repaired"]

_MAX_COORD_M = 1e3  # coordinates beyond 1 km are treated as missing (keeps the numerics finite)
_BAD_COVARIANCE = "bad_covariance"  # _track's answer for a correction that failed outright
_I3 = np.eye(3)


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
      axes parallel to ``frame_id`` (``ransac.py``). A re-initialisation re-acquires that body
      frame when the remembered body model registers onto the new landmarks
      (``reacquire_body_frame``; :meth:`HandTracker.reacquire`), else it starts a new one.
    - ``twist``: (6,) left twist ``[v, w]`` (m/s, rad/s) in ``frame_id``:
      ``T(t + dt) ~= Exp(dt twist) T(t)``.
    - ``covariance``: (12, 12) over [pose left perturbation (v, w), twist (v, w)].
    - ``motion_model``: the prediction that won this step.
    - ``landmark_points``: (21, 3) float32 filtered positions in ``frame_id``, NaN where no filter.
    - ``landmark_variance``: (21,) float32 ``trace(R_rb)`` (m^2), the body-level measurement
      variance (saliency factor times the trace of the filter's position covariance, plus the
      articulation variance; the wrist's is ``trace(P_lm)``; ``3 r_lm`` for every landmark in
      the ablation), NaN where no filter.
    - ``landmark_status``: (21,) uint8: 0 unused, 1 used, 2 outlier this step, 3 excluded (wrist).
    - ``body_epoch``: which body frame ``pose`` is in (:attr:`HandTracker.body_epoch`): it
      changes exactly when the body frame is defined anew without re-acquisition; poses of
      different epochs must never be compared.
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
    body_epoch: int = 0


@dataclass(frozen=True, eq=False)
class StepResult:
    """What :meth:`HandTracker.step` made of one frame.

    - ``estimate``: the hand body to publish, or None.
    - ``reason``: why there is no estimate (None when there is one): the frame was rejected
      (a :data:`FrameRejection`), or it was accepted but carries no correction of the body
      (a :data:`Skip`: ``no_hand``, the tracked hand is absent; ``choosing_hand``, two hands in
      view and neither known to manipulate yet; ``too_few_landmarks``, fewer than
      ``min_inliers`` usable landmarks of an initialised body; ``bad_covariance``, the body's
      covariance could not be made positive semi-definite, so nothing is published).
    - ``rejected``: every input rejected in this step, one entry per rejection, in order: the
      frame itself (then the only entry, equal to ``reason``), or hands of an accepted frame and
      its kinematic prior (``bad_kinematic_prior``), whether or not there is an estimate.
    - ``notes``: what this step handled that is worth counting (:data:`Note`):
      ``second_hand_moving`` (a second hand moved while the tracked one manipulated; it was
      ignored: two hands on two parts are out of scope, and the estimate follows the first),
      ``hand_switched`` (the body now follows the other hand: a new body epoch follows) and
      ``covariance_repaired`` (:attr:`HandTracker.covariance_repairs`).
    - ``replayed``: estimates of earlier frames, oldest first, that this step produced late, to
      be published (in order) before ``estimate``: while two hands were in view and neither was
      known to manipulate, the frames were held back (``choosing_hand``) and are now run for
      the hand chosen (``HandTracker._replay``), so that the kinematic level sees that hand's
      whole stream, its rest before the motion included.
    """

    estimate: HandBodyEstimate | None
    reason: FrameRejection | Skip | None = None
    rejected: tuple[Rejection, ...] = ()
    notes: tuple[Note, ...] = ()
    replayed: tuple[HandBodyEstimate, ...] = ()

    @property
    def skipped(self) -> bool:
        """Whether the frame was accepted but produced no estimate (``reason`` is a Skip)."""
        return self.reason in SKIP_REASONS


def _valid_pose(T: object) -> Array | None:
    """T as a float (4, 4) rigid transform, or None if it is not one (:func:`check_pose`)."""
    return None if check_pose(T) is not None else np.asarray(T, dtype=float)


class HandTracker:
    """Landmark KFs of two hands + weighted RANSAC initialisation + hand-body EKF of the hand
    that manipulates.

    ``rejected``: reason -> count of rejected frames/hands/priors; ``skipped``: reason -> count of
    accepted frames that produced no estimate; ``notes``: note -> count (:data:`Note`);
    ``covariance_repairs``: where a covariance had to be repaired -> count (``merge_pose``,
    ``posterior``, ``window_fit``; ``linalg_error`` for a correction that failed outright);
    ``reinitializations``: bodies dropped; ``reacquisitions``: initialisations that continued a
    remembered body frame (of ``reacquire_attempts``); ``hand_switches``: times the body moved
    to the other hand; ``body_epoch``: the current body frame's epoch.
    """

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self._cfg = config.internal()  # Table I in physical units (TrackerConfig.internal)
        config = self._cfg
        self.rejected: dict[str, int] = {}
        self.skipped: dict[str, int] = {}
        self.notes: dict[str, int] = {}
        self.covariance_repairs: dict[str, int] = {}
        self._rejections: list[Rejection] = []  # this step's, for its StepResult
        self._notes: list[Note] = []  # this step's
        self.reinitializations = 0
        self.reacquisitions = 0
        self.reacquire_attempts = 0
        self.hand_switches = 0
        # The body epoch survives reset(): a body frame defined after a reset is a new one too.
        self.body_epoch = 0
        self._epoch_used = False  # whether a body frame of the current epoch was defined
        self._identities = HandIdentities(config)
        self._deferred: deque[tuple[int, dict[int, tuple[float, Array]], Array | None]] = deque()
        # At most twice the frames of the choice's wait at the nominal rate (a faster stream
        # replays fewer of its oldest frames, as if they were lost).
        self._max_deferred = max(1, int(2.0 * config.hand_choice_wait_s / config.nominal_dt_s))
        self._body_mask = body_landmark_mask(config)
        self._P0_rb, self._Q_rb = body_noise_matrices(
            (config.p0_rb_position_m2, config.p0_rb_rotation_rad2,
             config.p0_rb_linear_velocity_m2ps2, config.p0_rb_angular_velocity_rad2ps2),
            (config.q_rb_position_m2, config.q_rb_rotation_rad2,
             config.q_rb_linear_velocity_m2ps2, config.q_rb_angular_velocity_rad2ps2))
        self._bank = LandmarkFilterBank(NUM_IDENTITIES * NUM_LANDMARKS, config)
        # The constant terms of body_measurement_covariances (R_rb), computed once.
        self._saliency = np.asarray(config.saliency_factors(), dtype=float)[:, None, None]
        self._R_uniform = body_measurement_covariances(np.zeros((NUM_LANDMARKS, 3, 3)), config)
        self._R_uniform.flags.writeable = False
        self._window: deque[WindowFrame] = deque(maxlen=config.init_window_frames)
        self._calibration = CovarianceCalibration(config)
        self.reset()

    # --- public API -------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget everything (filters, body, stamps, tracking frame); re-seed the rng."""
        self._bank.reset()
        self._window.clear()
        self._rng = np.random.default_rng(self._cfg.seed)
        self._last_stamp_ns: int | None = None
        self._frame_id: str | None = None
        self._identities.reset()
        self._slot: int | None = None  # the hand identity the body follows
        self._undecided_ns: int | None = None  # since when two idle hands wait for a choice
        self._deferred.clear()  # frames held back while choosing (_replay)
        self._deferred_start: tuple[tuple[Array, ...], int | None] | None = None
        self._ekf: HandBodyEkf | None = None
        self._template: BodyTemplate | None = None  # the body model while a body is tracked
        self._memory: Array | None = None  # the last body model, for re-acquisition
        self._set_articulation(np.zeros(NUM_LANDMARKS))
        self._body_stamp_ns = 0
        self._calibration.reset()

    @property
    def initialized(self) -> bool:
        """Whether a hand body is being tracked."""
        return self._ekf is not None

    @property
    def body_points(self) -> Array | None:
        """(21, 3) body-frame coordinates fixed at initialisation (NaN: not in the body model)."""
        return None if self._template is None else self._template.points.copy()

    def remembered_body(self) -> tuple[str, Array] | None:
        """(tracking frame id, (21, 3) body model) to persist: the current body model, else the
        one remembered for re-acquisition; None before any initialisation."""
        points = self._template.points if self._template is not None else self._memory
        if points is None or self._frame_id is None:
            return None
        return self._frame_id, points.copy()

    def remember_body(self, frame_id: str, points_body: Array, body_epoch: int | None = None
                      ) -> bool:
        """Adopt a persisted body model (from :meth:`remembered_body`): the next initialisation
        re-acquires its body frame. ``body_epoch``: that body frame's epoch (persisted with it;
        :attr:`body_epoch`), so that a re-acquisition continues it; without it the epoch stays
        where it is, and either way a failed re-acquisition starts the next one. Refused (False)
        if malformed or in another tracking frame than the one already in use."""
        points = np.asarray(points_body, dtype=float)
        if (points.shape != (NUM_LANDMARKS, 3) or frame_id not in ("camera", "world")
                or (self._frame_id is not None and frame_id != self._frame_id)
                or int(np.isfinite(points).all(axis=1).sum()) < self._cfg.min_inliers
                or (body_epoch is not None and (isinstance(body_epoch, bool)
                                                or not isinstance(body_epoch, (int, np.integer))
                                                or body_epoch < 0))):
            return False
        self._memory = points.copy()
        if body_epoch is not None:
            self.body_epoch = int(body_epoch)
        # A body frame was in use: a new one (re-acquisition failing) is a new epoch.
        self._epoch_used = True
        return True

    def continue_epochs(self, body_epoch: int) -> None:
        """Continue the body-epoch count of an earlier run (a state file without a body model:
        written after a ``reset``): the next body frame is a new epoch after ``body_epoch``."""
        if isinstance(body_epoch, bool) or not isinstance(body_epoch, (int, np.integer)) or (
                body_epoch < 0):
            raise ValueError(f"body_epoch must be a whole number >= 0, got {body_epoch!r}")
        self.body_epoch = int(body_epoch)
        self._epoch_used = True

    def step(self, stamp_ns: int, hands: Sequence[HandObservation],
             T_world_camera: np.ndarray | None = None,
             kinematic_prior: KinematicPrior | None = None) -> StepResult:
        """Process one frame of detections (see module docstring): its estimate, or the reason
        there is none, and what was rejected (:class:`StepResult`).

        ``T_world_camera``: camera pose for a moving camera (landmarks are then tracked in
        "world"). ``kinematic_prior(stamp_ns)``: (predicted ``T_frame_hand`` (4, 4), its 6x6
        left-perturbation covariance) in the tracking frame, or None.
        """
        self._rejections = []
        self._notes = []
        if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, (int, np.integer)):
            return self._rejected_frame("bad_stamp")
        stamp_ns = int(stamp_ns)
        if self._last_stamp_ns is not None:
            if stamp_ns == self._last_stamp_ns:
                return self._rejected_frame("duplicate_stamp")
            if stamp_ns < self._last_stamp_ns:
                return self._rejected_frame("out_of_order_stamp")
        T_wc: Array | None = None
        if T_world_camera is not None:
            T_wc = _valid_pose(T_world_camera)
            if T_wc is None:
                return self._rejected_frame("bad_camera_pose")
        frame_id = "camera" if T_wc is None else "world"
        if self._frame_id is not None and frame_id != self._frame_id:
            return self._rejected_frame("frame_mismatch")
        self._frame_id = frame_id

        observed = self._observed_hands(stamp_ns, hands, T_wc)
        deferring = (self._ekf is None and self._slot is None
                     and self._identities.contested(stamp_ns))
        if deferring and not self._deferred:
            self._deferred_start = (self._bank.snapshot(), self._last_stamp_ns)
        update = self._update_landmarks(stamp_ns, observed, T_wc)
        slot = self._tracked_slot(stamp_ns, observed)
        if self._deferred or (deferring and slot is None):
            self._deferred.append((stamp_ns, observed, T_wc))
            if slot is None:
                if len(self._deferred) > self._max_deferred:  # the wait forces a choice first
                    self._deferred.popleft()
                return self._skipped("choosing_hand")
            return self._replay(slot)
        return self._body_step(stamp_ns, slot, observed, update, kinematic_prior)

    def _update_landmarks(self, stamp_ns: int, observed: dict[int, tuple[float, Array]],
                          T_wc: Array | None) -> LandmarkUpdate:
        """Predict every landmark filter to ``stamp_ns`` and correct it with this frame's hands
        (``observed``: identity -> (score, camera-frame points)); filters that start on the
        body's hand start with the body's velocity there."""
        z_camera = np.full((NUM_IDENTITIES * NUM_LANDMARKS, 3), np.nan)
        for s, (_, points) in observed.items():
            z_camera[s * NUM_LANDMARKS:(s + 1) * NUM_LANDMARKS] = points
        z = z_camera if T_wc is None else z_camera @ T_wc[:3, :3].T + T_wc[:3, 3]
        R_lm = self._measurement_noise(z_camera, T_wc)
        if self._last_stamp_ns is not None:
            self._bank.predict((stamp_ns - self._last_stamp_ns) * 1e-9)
        self._last_stamp_ns = stamp_ns
        body_slot = self._slot if self._ekf is not None else None
        return self._bank.update(z, R_lm, gate=self._cfg.outlier_gates,
                                 v_start=self._start_velocities(body_slot, z))

    def _body_step(self, stamp_ns: int, slot: int | None,
                   observed: dict[int, tuple[float, Array]], update: LandmarkUpdate,
                   kinematic_prior: KinematicPrior | None) -> StepResult:
        """The body level for the hand ``slot`` after the landmark ``update`` of this frame."""
        if slot is None or slot not in observed:
            if self._ekf is not None:
                self._maybe_drop_body(stamp_ns)
            else:
                self._window.clear()
                if self._cfg.hand_selection == "manipulating":
                    self._slot = None
            return self._skipped("no_hand")

        rows = slice(slot * NUM_LANDMARKS, (slot + 1) * NUM_LANDMARKS)
        status = np.zeros(NUM_LANDMARKS, dtype=np.uint8)
        status[update.rejected[rows]] = STATUS_OUTLIER
        if self._cfg.use_uncertainty_models:
            status[WRIST] = STATUS_EXCLUDED
        usable = update.fresh[rows] & self._body_mask
        inputs = self._body_inputs(rows)
        model: str | None
        if self._ekf is None:
            model, inputs = self._initialise(stamp_ns, rows, usable, status, inputs)
        else:
            model, inputs = self._track(stamp_ns, rows, usable, status, kinematic_prior, inputs)
        if model is None:
            return self._skipped("too_few_landmarks")
        if model == _BAD_COVARIANCE:
            return self._skipped("bad_covariance")
        # Outputs after the body step (_track recomputed the inputs where a body-level
        # rejection undid a landmark correction or the articulation variances changed).
        positions, R_rb = inputs
        trace = R_rb[:, 0, 0] + R_rb[:, 1, 1] + R_rb[:, 2, 2]
        variance = np.where(self._bank.alive[rows], trace, np.nan)
        return StepResult(self._estimate(stamp_ns, positions, variance, status, model),
                          rejected=tuple(self._rejections), notes=tuple(self._notes))

    def _replay(self, slot: int) -> StepResult:
        """The deferred frames, and this one, as if the hand ``slot`` had been alone in view.

        While two hands were in view and neither was known to manipulate, the frames were held
        back (``choosing_hand``); now that ``slot`` is chosen, its landmark filters are taken back
        to where they were when the wait began and run again on its detections alone, and its
        body is initialised and tracked through those frames, without a kinematic prior (the
        kinematic level has not seen them). The other hand's filters stay as they are. Returns
        this frame's result with the earlier frames' estimates in ``replayed``.
        """
        frames = list(self._deferred)
        self._deferred.clear()
        assert self._deferred_start is not None
        snapshot, last_stamp_ns = self._deferred_start
        bank = self._bank
        rows = np.zeros(bank.n, dtype=bool)
        rows[slot * NUM_LANDMARKS:(slot + 1) * NUM_LANDMARKS] = True
        now = bank.snapshot()
        bank.restore(snapshot, rows)
        self._last_stamp_ns = last_stamp_ns
        self._window.clear()
        rejections, notes = self._rejections, self._notes
        skipped = dict(self.skipped)  # the held-back frames were counted when they came
        estimates: list[HandBodyEstimate] = []
        result = StepResult(None)
        for stamp_ns, observed, T_wc in frames:
            self._rejections, self._notes = [], []
            mine = {slot: observed[slot]} if slot in observed else {}
            self._slot = slot
            update = self._update_landmarks(stamp_ns, mine, T_wc)
            result = self._body_step(stamp_ns, slot, mine, update, None)
            if result.estimate is not None:
                estimates.append(result.estimate)
            rejections += self._rejections
            notes += self._notes
        bank.restore(now, ~rows)
        self.skipped = skipped
        if result.reason is not None:
            self.skipped[result.reason] = self.skipped.get(result.reason, 0) + 1
        if self._slot is None and self._ekf is None:
            self._slot = slot  # the choice stays while its hand is briefly out of view
        self._rejections, self._notes = rejections, notes
        earlier = tuple(estimates[:-1] if result.estimate is not None else estimates)
        return StepResult(result.estimate, result.reason, tuple(rejections), tuple(notes),
                          replayed=earlier)

    # --- internals --------------------------------------------------------------------------

    def _reject(self, reason: Rejection) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        self._rejections.append(reason)

    def _note(self, note: Note) -> None:
        self.notes[note] = self.notes.get(note, 0) + 1
        self._notes.append(note)

    def _repaired(self, site: str) -> None:
        self.covariance_repairs[site] = self.covariance_repairs.get(site, 0) + 1
        self._note("covariance_repaired")

    def _rejected_frame(self, reason: FrameRejection) -> StepResult:
        self._reject(reason)
        return StepResult(None, reason, (reason,))

    def _skipped(self, reason: Skip) -> StepResult:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1
        return StepResult(None, reason, tuple(self._rejections), tuple(self._notes))

    def _parse_hands(self, hands: Sequence[HandObservation]) -> list[tuple[float, Array]]:
        """Valid hands, highest score first: (score, points (21, 3) in the camera frame with NaN
        where missing). With ``hand_selection`` "left" or "right" only the hands so labelled."""
        out: list[tuple[float, Array]] = []
        selection = self._cfg.hand_selection
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
            if not math.isfinite(score):
                self._reject("non_finite_score")
                continue
            if selection not in ("manipulating", handedness):
                continue
            # missing_mask(points, visibility, threshold), with coordinates beyond 1 km missing
            # too: |x| < 1 km is False for NaN and inf, so it also covers the finiteness test.
            present = ((np.abs(points) < _MAX_COORD_M).all(axis=1)
                       & (visibility >= self._cfg.visibility_threshold))
            out.append((score, np.where(present[:, None], points, np.nan)))
        out.sort(key=lambda h: -h[0])  # stable: equal scores keep their order
        return out

    def _observed_hands(self, stamp_ns: int, hands: Sequence[HandObservation],
                        T_wc: Array | None) -> dict[int, tuple[float, Array]]:
        """This frame's valid hands by identity (:mod:`~services.tracker.hands`): slot ->
        (score, camera-frame points (21, 3), NaN = missing).

        Two detections of one hand (centres closer than ``hand_duplicate_distance_m``) keep the
        better scored (the other is rejected ``duplicate_hand``), and hands beyond the second are
        rejected ``extra_hand``. A slot that a new hand takes (:meth:`HandIdentities.associate`)
        forgets its landmark filters, so that they start again on the new hand.
        """
        parsed = self._parse_hands(hands)
        kept: list[tuple[float, Array]] = []
        points: list[Array] = []
        centres: list[Array | None] = []
        for score, camera_points in parsed:
            z = (camera_points if T_wc is None
                 else camera_points @ T_wc[:3, :3].T + T_wc[:3, 3])
            centre = robust_centre(z) if len(parsed) > 1 else None  # one hand: no duplicate
            if centre is not None and any(
                    c is not None and float(np.linalg.norm(c - centre))
                    < self._cfg.hand_duplicate_distance_m for c in centres):
                self._reject("duplicate_hand")
                continue
            if len(kept) == NUM_IDENTITIES:
                self._reject("extra_hand")
                continue
            kept.append((score, camera_points))
            points.append(z)
            centres.append(centre)
        slots, fresh = self._identities.associate(stamp_ns, points, self._slot,
                                                  centres if len(parsed) > 1 else None)
        for slot, restart in zip(slots, fresh, strict=True):
            if restart:
                rows = np.zeros(self._bank.n, dtype=bool)
                rows[slot * NUM_LANDMARKS:(slot + 1) * NUM_LANDMARKS] = True
                self._bank.forget(rows)
        return dict(zip(slots, kept, strict=True))

    def _tracked_slot(self, stamp_ns: int, observed: dict[int, tuple[float, Array]]
                      ) -> int | None:
        """The identity the body follows this frame (docs/estimation.md#the-manipulating-hand).

        One hand in view (not :meth:`HandIdentities.contested`): that hand, kept until it is
        absent while no body is tracked. Two: with a body, its hand, unless it has not moved for
        ``hand_switch_idle_s`` while the other one moved ``hand_switch_moves`` times since it
        last moved (then the body is dropped and the other hand followed: a new body frame); a
        second hand moving while the tracked one moves too is counted (``second_hand_moving``)
        and ignored. Without a body, the hand that moved last; while neither moves, none until
        they have been in view together for ``hand_choice_wait_s``, then the better scored.
        The landmark motion of both is measured (:meth:`HandIdentities.observe_motion`, on the
        landmarks whose filters are confirmed, ``lm_confirm_corrections``) while two hands are in
        view.
        """
        ids = self._identities
        if not ids.contested(stamp_ns):
            self._undecided_ns = None
            if self._slot is None and observed:
                self._slot = max(observed, key=lambda s: observed[s][0])
            return self._slot
        bank = self._bank
        confirmed = bank.alive & (bank.corrections >= self._cfg.lm_confirm_corrections)
        for s in observed:  # confirmed filters only: a filter settling after its start is no motion
            rows = slice(s * NUM_LANDMARKS, (s + 1) * NUM_LANDMARKS)
            ids.observe_motion(s, stamp_ns, np.where(confirmed[rows, None], bank.x[rows, :3],
                                                      np.nan))
        cfg = self._cfg
        if self._ekf is not None and self._slot is not None:
            tracked, other = self._slot, 1 - self._slot
            if other in observed and ids.moving(other, stamp_ns):
                if ids.moving(tracked, stamp_ns):
                    self._note("second_hand_moving")
                elif (ids.idle_s(tracked, stamp_ns) >= cfg.hand_switch_idle_s
                      and ids.hands[other].moves_since(ids.hands[tracked].moved_ns)
                      >= cfg.hand_switch_moves):
                    self._switch_hand(other)
            return self._slot
        moving = [s for s in observed if ids.moving(s, stamp_ns)]
        pick: int | None
        if moving:
            pick = max(moving, key=lambda s: ids.hands[s].moved_ns or 0)
            self._undecided_ns = None
        elif self._slot is not None and self._slot in observed and self._undecided_ns is None:
            pick = self._slot  # a choice made stays while nothing moves
        else:
            if self._undecided_ns is None:
                self._undecided_ns = stamp_ns
            waited = (stamp_ns - self._undecided_ns) * 1e-9
            pick = (max(observed, key=lambda s: observed[s][0])
                    if observed and waited >= cfg.hand_choice_wait_s else None)
            if pick is not None:
                self._undecided_ns = None
        if pick != self._slot:
            self._window.clear()
            self._slot = pick
        return pick

    def _switch_hand(self, slot: int) -> None:
        """Follow the hand ``slot`` from now on: drop the body and its memory (the other hand's
        body model must not be re-acquired on this one); the next initialisation starts a new
        body frame."""
        self._drop_body()
        self._memory = None
        self._slot = slot
        self.hand_switches += 1
        self._note("hand_switched")

    def _measurement_noise(self, z_camera: Array, T_wc: Array | None) -> Array:
        """``R_lm`` (N, 3, 3) in the tracking frame: isotropic ``r_lm I3`` in the ablation or with
        ``depth_variance_factor = 1``, else anisotropic about each landmark's viewing ray
        (:func:`~services.tracker.landmarks.ray_measurement_covariances`)."""
        cfg = self._cfg
        factor = cfg.depth_variance_factor if cfg.use_uncertainty_models else 1.0
        if factor == 1.0:
            # Isotropic: R_wc R_lm R_wc' = R_lm, the same in the camera and world frames.
            return np.broadcast_to(cfg.r_lm_m2 * np.eye(3), (z_camera.shape[0], 3, 3))
        rays = z_camera  # the viewing rays, unnormalised (ray_measurement_covariances normalises)
        if T_wc is not None:
            rays = rays @ T_wc[:3, :3].T  # R = r (I - u u') + f r u u' rotates with its ray
        return ray_measurement_covariances(rays, cfg.r_lm_m2, factor)

    def _maybe_drop_body(self, stamp_ns: int) -> None:
        """Drop the body once it has gone ``reinit_after_s`` without a correction."""
        if (stamp_ns - self._body_stamp_ns) * 1e-9 >= self._cfg.reinit_after_s:
            self._drop_body()

    def _drop_body(self) -> None:
        """Drop the body, remembering its model for re-acquisition."""
        self._memory = None if self._template is None else self._template.points
        self._ekf = None
        self._template = None
        self._set_articulation(np.zeros(NUM_LANDMARKS))
        self._calibration.forget_last_residuals()
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
            landmark_status=status, body_epoch=self.body_epoch)

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

    def _set_articulation(self, variances: Array) -> None:
        """Articulation variances ``a_k`` (21,) of R_rb, with their ``a_k I3`` terms."""
        self._articulation = variances
        self._articulation_I3 = variances[:, None, None] * _I3

    def _body_inputs(self, rows: slice) -> tuple[Array, Array]:
        """Filtered positions (21, 3) and ``R_rb`` (21, 3, 3) of the tracked hand
        (:func:`~services.tracker.landmarks.body_measurement_covariances`, its per-landmark
        terms precomputed; the ablation's uniform ``R_rb`` is shared, read-only)."""
        bank = self._bank
        positions = np.where(bank.alive[rows, None], bank.x[rows, :3], np.nan)
        if not self._cfg.use_uncertainty_models:
            return positions, self._R_uniform
        R_rb: Array = self._saliency * bank.P[rows, :3, :3] + self._articulation_I3
        return positions, R_rb

    def _initialise(self, stamp_ns: int, rows: slice, usable: BoolArray,
                    status: NDArray[np.uint8], inputs: tuple[Array, Array]
                    ) -> tuple[str, tuple[Array, Array]]:
        """Collect the window; try the weighted RANSAC once it is full. ``inputs``: this frame's
        :meth:`_body_inputs`. Returns the model name and the body inputs after this step."""
        positions, R_rb = inputs
        r_rb = (R_rb[:, 0, 0] + R_rb[:, 1, 1] + R_rb[:, 2, 2]) / 3.0
        self._window.append(WindowFrame(stamp_ns, positions, r_rb, usable.copy()))
        status[usable] = STATUS_USED
        cfg = self._cfg
        if len(self._window) < cfg.init_window_frames:
            return MOTION_MODELS[0], inputs
        first, last = self._window[0], self._window[-1]
        eligible = first.usable & last.usable
        if eligible.sum() < cfg.min_inliers:
            return MOTION_MODELS[0], inputs
        result = rigid_ransac(first.positions[eligible], last.positions[eligible],
                              first.variances[eligible], last.variances[eligible],
                              iterations=cfg.ransac_iterations,
                              threshold=cfg.ransac_inlier_mahalanobis,
                              refinements=cfg.ransac_refinements, rng=self._rng)
        if result is None or result.inliers.sum() < cfg.min_inliers:
            return MOTION_MODELS[0], inputs
        inliers = np.zeros(NUM_LANDMARKS, dtype=bool)
        inliers[np.flatnonzero(eligible)[result.inliers]] = True
        frames = list(self._window)
        body = initial_body(np.stack([f.positions for f in frames]),
                            np.stack([f.variances for f in frames]),
                            np.stack([f.usable for f in frames]),
                            np.array([f.stamp_ns for f in frames], dtype=float) * 1e-9,
                            inliers, result.transform)
        T_frame_body, points_body = body.T_frame_body, body.points_body
        X = None
        if self._memory is not None and cfg.reacquire_body_frame:
            X = self.reacquire(points_body, frames[-1].variances)
            if X is not None:  # p_new = X p_old: the remembered frame is T_new X
                T_frame_body = T_frame_body @ X
                points_body = (points_body - X[:3, 3]) @ X[:3, :3]
        if X is None:  # a new body frame: a new epoch (the first one is epoch 0)
            if self._epoch_used:
                self.body_epoch += 1
            self._epoch_used = True
        self._ekf = HandBodyEkf(T_frame_body, body.twist, self._P0_rb, self._Q_rb,
                                cfg.nominal_dt_s)
        self._template = BodyTemplate(points_body, np.where(
            np.isfinite(body.points_body).all(axis=1), float(len(frames)), 0.0), cfg)
        self._memory = None  # the body model is the memory from now on
        if cfg.use_uncertainty_models:
            self._set_articulation(articulation_variances(points_body, cfg.articulation_std_rad))
            inputs = self._body_inputs(rows)
        self._seed_from_window(frames)
        self._body_stamp_ns = stamp_ns
        self._window.clear()
        status[usable & ~inliers] = STATUS_OUTLIER
        return MOTION_MODELS[0], inputs

    def reacquire(self, points_body: Array, variances: Array) -> Array | None:
        """The transform X (4x4) with ``points_body ~= X p_old`` for the remembered body model
        ``p_old``, or None when it does not register.

        A weighted RANSAC (the initialisation's, on the same gate) between the remembered and the
        new body-frame coordinates of the landmarks both know; a changed grasp moves a few
        fingers, which become outliers. Needs ``min_inliers`` inliers and at least half of the
        common landmarks; per-axis ``variances`` (21,) are those of the newest window frame.
        """
        memory = self._memory
        assert memory is not None
        cfg = self._cfg
        common = np.isfinite(memory).all(axis=1) & np.isfinite(points_body).all(axis=1)
        if common.sum() < cfg.min_inliers:
            return None
        self.reacquire_attempts += 1
        var = variances[common]
        result = rigid_ransac(memory[common], points_body[common], var, var,
                              iterations=cfg.ransac_iterations,
                              threshold=cfg.ransac_inlier_mahalanobis,
                              refinements=cfg.ransac_refinements, rng=self._rng)
        if (result is None or result.inliers.sum() < cfg.min_inliers
                or 2 * result.inliers.sum() < common.sum()):
            return None
        self.reacquisitions += 1
        return result.transform

    def _seed_from_window(self, frames: list[WindowFrame]) -> None:
        """Calibrate the new body from its initialisation window, so that its very first
        published covariance (the kinematic level's reference pose) is honest: the window's fit
        residuals seed the covariance calibration (:meth:`CovarianceCalibration.seed`), and the
        initial pose fit's covariance adds to the pose block of ``P0``
        (:func:`~services.tracker.calibration.window_fit_covariance`)."""
        ekf = self._ekf
        assert ekf is not None and self._template is not None
        points_body = self._template.points
        model = np.isfinite(points_body).all(axis=1)
        template = points_body @ ekf.T[:3, :3].T + ekf.T[:3, 3]
        self._calibration.seed(template, model, frames)
        P_fit = window_fit_covariance(template, model, frames[-1])
        if P_fit is not None:
            if is_psd(P_fit):
                ekf.P[:6, :6] += P_fit
            else:  # an ill-conditioned fit (nearly collinear landmarks): Table I's P0 alone
                self._repaired("window_fit")

    @property
    def variance_factor(self) -> float:
        """Scale applied to the filter covariance for publication
        (:attr:`CovarianceCalibration.variance_factor`)."""
        return self._calibration.variance_factor

    @property
    def correlation_factor(self) -> float:
        """The residual correlation's share of :attr:`variance_factor`
        (:attr:`CovarianceCalibration.correlation_factor`)."""
        return self._calibration.correlation_factor

    def _kinematic(self, prior: KinematicPrior | None, stamp_ns: int
                   ) -> tuple[Array, Array] | None:
        """The caller's kinematic prediction for this stamp, validated (None if absent/bad)."""
        if prior is None or not self._cfg.use_kinematic_prior:
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
        # Positive semi-definite up to round-off (a joint's prediction is rank-deficient, its
        # zero eigenvalues come out at ~-1e-20 of the largest); anything more is refused.
        if np.linalg.eigvalsh(Sigma)[0] < -1e-9 * scale:
            self._reject("bad_kinematic_prior")
            return None
        # The prior is in the published units (metres, radians); the filter's are Table I's.
        return T, Sigma / self.variance_factor

    def _failed_correction(self, stamp_ns: int) -> str:
        """A correction that failed on a singular or non-finite matrix (positive semi-definite
        covariances rule that out, so the filter's is repaired, or the body dropped if it cannot
        be): counted, the frame goes uncorrected. Returns ``_BAD_COVARIANCE``."""
        self._repaired("linalg_error")
        ekf = self._ekf
        assert ekf is not None
        if not is_psd(ekf.P):
            fixed = psd_repaired(ekf.P)
            if fixed is None or not (np.isfinite(ekf.T).all() and np.isfinite(ekf.xi).all()):
                self._drop_body()
                return _BAD_COVARIANCE
            ekf.P = fixed
        self._maybe_drop_body(stamp_ns)
        return _BAD_COVARIANCE

    def _track(self, stamp_ns: int, rows: slice, usable: BoolArray, status: NDArray[np.uint8],
               prior: KinematicPrior | None, inputs: tuple[Array, Array]
               ) -> tuple[str | None, tuple[Array, Array]]:
        """Predict, choose the motion model, gate and correct the body EKF. ``inputs``: this
        frame's :meth:`_body_inputs`.

        Returns the winning model's name, or None when the initialised body could not be
        corrected (too few landmarks; a body dropped then instead starts a new initialisation
        window with this frame), or ``_BAD_COVARIANCE`` when the correction failed on a singular
        innovation covariance (counted in ``covariance_repairs["linalg_error"]``; the filter's
        covariance is repaired if it has to be), and the body inputs after this step.
        """
        ekf, template = self._ekf, self._template
        assert ekf is not None and template is not None
        cfg = self._cfg
        positions, R_rb = inputs
        candidates = usable & template.in_model
        idx = np.flatnonzero(candidates)
        if idx.size >= cfg.min_inliers:
            dt = (stamp_ns - self._body_stamp_ns) * 1e-9
            try:
                predictions = ekf.predict(dt, self._kinematic(prior, stamp_ns))
                step = select_and_gate(predictions, positions[idx], template.points[idx],
                                       R_rb[idx], cfg.mahalanobis_rb,
                                       gate=cfg.outlier_gates)
            except np.linalg.LinAlgError:
                return self._failed_correction(stamp_ns), inputs
            if not np.isfinite(step.log_likelihood).all():  # a covariance that is not finite
                return self._failed_correction(stamp_ns), inputs
            rejected = idx[step.rejected]
            status[rejected] = STATUS_OUTLIER
            if rejected.size:
                mask = np.zeros(self._bank.n, dtype=bool)
                mask[rows.start + rejected] = True
                self._bank.reject(mask)
                usable[rejected] = False
            used = idx[step.accepted]
            if used.size >= cfg.min_inliers:
                chosen = predictions[step.model]
                try:
                    repairs = ekf.update_chosen(predictions, step)
                except np.linalg.LinAlgError:
                    return self._failed_correction(stamp_ns), inputs
                for site in repairs:
                    self._repaired(site)
                W = step.W[step.accepted]
                residual, d2 = fit_residuals(ekf.T, template.points, used, positions, W)
                self._calibration.update(used, residual, d2, W)
                changed = (template.refine(ekf.T, positions, used, d2, usable & ~candidates)
                           and cfg.use_uncertainty_models)
                if changed:  # a landmark joined the model: its articulation variance too
                    self._set_articulation(articulation_variances(template.points,
                                                                  cfg.articulation_std_rad))
                self._body_stamp_ns = stamp_ns
                status[used] = STATUS_USED
                if rejected.size or changed:
                    inputs = self._body_inputs(rows)
                return chosen.model, inputs
        self._maybe_drop_body(stamp_ns)
        if self._ekf is not None:
            return None, inputs
        return self._initialise(stamp_ns, rows, usable, status, self._body_inputs(rows))


__all__ = [
    "HANDS",
    "SKIP_REASONS",
    "STATUS_EXCLUDED",
    "STATUS_OUTLIER",
    "STATUS_UNUSED",
    "STATUS_USED",
    "FrameRejection",
    "HandBodyEstimate",
    "HandObservation",
    "HandRejection",
    "HandTracker",
    "Rejection",
    "Skip",
    "StepResult",
]
