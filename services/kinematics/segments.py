"""A sequence of kinematic models, one per contact phase (docs/estimation.md#contact-phases).

:class:`SegmentedEstimator` sits above :class:`~services.kinematics.estimator.KinematicEstimator`:
hand bodies in (stamp [ns], ``T_frame_hand`` 4x4, its 6x6 left-perturbation covariance, the
filtered landmarks (21, 3) [m], the tracker's body epoch), per frame the model to publish
out. It

- decides contact or free per frame (:class:`~services.kinematics.contact.ContactDetector`,
  the hand's cues; events dated back by at most ``max_lag_s``);
- feeds only contact frames to a joint estimate: at an onset it replays the buffered frames from
  the dated onset, at a release it rolls the estimate back to the dated release (checkpoints
  every ``CHECKPOINT_FRAMES`` fed frames, then the buffered frames replayed), so free motion
  never reaches a joint estimate and the published model stays current;
- keeps a phase only with model evidence of contact: a closed phase whose estimate has no type
  (unknown) or only "disconnected", a rigid one shorter than ``min_rigid_hold_s`` (a hand that
  rests a moment has not shown that it holds anything), a phase released while the hand moved
  (a hand lets go of a handle at rest) and a tentative initial phase without an articulated type
  are dropped (their index is used again);
- opens a new estimate per contact phase, except that a re-grasp of the joint of the latest
  phase with a verdict continues that phase's estimate: the new phase's motion is tested
  against the old model's screw (:func:`~services.kinematics.same_joint.screw_residual`) once
  it is significant (or when the phase ends), the same joint if the screw explains most of it;
  the continued estimator is fed the new poses carried onto the old grasp,
  ``T' = T T_1^-1 T_end`` (``T_1`` the new phase's first pose, ``T_end`` the old estimate's hand
  pose at its end), which leaves every displacement ``T'(t) T'(t0)^-1``, and so the joint,
  unchanged; its published ``reference_pose`` is carried back to the new grasp;
- restarts the open phase's estimate when the tracker starts a new body frame (``body_id``):
  poses of two body frames cannot be compared.

``model`` is what a publisher sends after each accepted frame (the open phase's model while in
contact, else :attr:`verdict_model`), ``verdict_model`` what ``get`` answers (the model of the
latest phase whose type is rigid, prismatic or revolute), ``models`` every phase, oldest
first. All three carry the current frame's ``stamp_ns`` and ``phase`` (docs/protocol.md).
No I/O, no clock.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import FRAME_IDS, KinematicModel, ProtocolError, pack_document
from services.common.snapshot import SnapshotError, SnapshotReader
from services.common.stamps import INT64_MAX
from services.kinematics.config import KinematicsConfig
from services.kinematics.contact import (
    ApertureCue,
    ContactDetector,
    ContactEvent,
    Phase,
    SegmentationConfig,
)
from services.kinematics.estimator import KinematicEstimator, RejectReason, UpdateResult
from services.kinematics.filters.geometry import se3_inverse_fast
from services.kinematics.prediction import predict_hand_pose
from services.kinematics.same_joint import screw_residual

Array = NDArray[np.float64]

SNAPSHOT_VERSION = 1
VERDICT_TYPES = ("rigid", "prismatic", "revolute")
ARTICULATED = ("prismatic", "revolute")
CHECKPOINT_FRAMES = 4
# A re-grasp still undecided after this many frames (a hold without motion) is decided then.
MAX_PENDING_FRAMES = 300
_CHI2_5_99 = 15.09  # 99 % point of the chi-square distribution with 5 degrees of freedom


@dataclass(frozen=True, eq=False)
class Frame:
    """One accepted hand body: stamp [ns], pose ``T_frame_hand`` (4x4), covariance (6x6), and
    the id of the tracker's body frame it is in (None: not stated)."""

    stamp_ns: int
    pose: Array
    covariance: Array
    body_id: int | None = None


@dataclass(frozen=True, eq=False)
class SegmentedUpdate:
    """What one :meth:`SegmentedEstimator.update` did: the model to publish (None and a
    ``reason`` when the input was rejected), the phase event found at this frame, if any, and
    the joint estimate's ``note`` (:class:`~services.kinematics.estimator.UpdateResult`)."""

    model: KinematicModel | None
    reason: RejectReason | None = None
    event: ContactEvent | None = None
    note: str = ""


def verdict_of(closed: tuple[KinematicModel, ...], latest: KinematicModel) -> KinematicModel:
    """What ``get`` answers given the closed phases' models (oldest first) and the ``latest``
    published model: ``latest`` itself when the hand is free (it is then the latest verdict) or
    when it is a verdict (rigid, prismatic, revolute); else the latest closed phase with a
    verdict, with ``latest``'s envelope (seq, stamp_ns) and phase; else ``latest``."""
    if latest.phase == "free" or latest.type in VERDICT_TYPES:
        return latest
    chosen = next((m for m in reversed(closed) if m.type in VERDICT_TYPES), None)
    if chosen is None:
        return latest
    return replace(chosen, seq=latest.seq, stamp_ns=latest.stamp_ns, phase=latest.phase)


class _Open:
    """The open contact phase: its estimator and what a release or a re-grasp test needs."""

    def __init__(self, index: int, start_ns: int, estimator: KinematicEstimator,
                 pending: bool, body_id: int | None) -> None:
        self.index = index
        self.start_ns = start_ns
        self.body_id = body_id             # the body frame of the frames fed so far
        self.first_segment = index
        self.estimator = estimator
        self.pose_map = np.eye(4)          # estimator pose = raw pose @ pose_map
        self.pending = pending             # re-grasp test not decided yet
        self.frames: list[Frame] = []      # the phase's raw frames while pending
        self.checkpoints: deque[tuple[int, dict[str, Any]]] = deque()
        self.fed = 0
        self.initial = False               # began because the stream began with a closed hand
        self.confirmed = False             # a stroke ended at rest: its type may be published
        self.cued = True                   # found by the hand's cues (not a stream without them)
        self.still = 0                     # still frames since the joint filter started


class SegmentedEstimator:
    """Contact-phase segmentation and one kinematic estimate per phase (module docstring).

    ``update`` never raises on bad input; it rejects what :class:`KinematicEstimator` would
    reject (shapes, finiteness, stamp order) and says why.
    """

    def __init__(self, config: KinematicsConfig | None = None,
                 segmentation: SegmentationConfig | None = None,
                 frame_id: str = "camera") -> None:
        self.config = KinematicsConfig() if config is None else config
        self.segmentation = SegmentationConfig() if segmentation is None else segmentation
        self.frame_id = frame_id
        self.reset()

    # ------------------------------------------------------------------------------ state

    def reset(self) -> None:
        """Forget the demonstration: every phase, the detector, the buffered frames."""
        self._detector = ContactDetector(self.segmentation)
        self._recent: deque[Frame] = deque()
        self._closed: list[KinematicModel] = []
        self._open: _Open | None = None
        # The latest phase with a verdict, for a re-grasp to continue: its record index, the
        # estimator snapshot at its end and its hand pose at the end (estimator space).
        self._candidate: tuple[int, dict[str, Any], Array] | None = None
        self._last_stamp: int | None = None
        self._cueless_since: int | None = None
        self._accepted = 0  # frames of this demonstration (since a restart: a restored one)
        self._note = ""
        self._empty = replace(KinematicEstimator(self.config, self.frame_id).model,
                              phase="free")

    @property
    def phase(self) -> Phase:
        """What the hand does at the last accepted frame."""
        return "contact" if self._open is not None else "free"

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the last accepted frame of this demonstration, None before one."""
        return self._last_stamp

    @property
    def closed(self) -> tuple[KinematicModel, ...]:
        """The closed phases' models as of their last frame, oldest first."""
        return tuple(self._closed)

    @property
    def segments(self) -> tuple[KinematicModel, ...]:
        """Every phase's model, oldest first (the open one last, as of its last frame)."""
        out = list(self._closed)
        if self._open is not None:
            out.append(self._open_model())
        return tuple(out)

    @property
    def model(self) -> KinematicModel:
        """What to publish now: the open phase's model in contact, else :attr:`verdict_model`."""
        if self._open is not None:
            return self._stamped(self._open_model())
        return self.verdict_model

    @property
    def verdict_model(self) -> KinematicModel:
        """The model of the latest phase with a verdict (rigid, prismatic or revolute), else of
        the open phase, else of the latest phase, else the empty model; with the current stamp
        and phase (:func:`verdict_of`)."""
        if self._open is not None:
            return verdict_of(self.closed, self._stamped(self._open_model()))
        chosen = next((m for m in reversed(self._closed) if m.type in VERDICT_TYPES),
                      self._closed[-1] if self._closed else self._empty)
        return self._stamped(chosen)

    @property
    def models(self) -> tuple[KinematicModel, ...]:
        """Every phase's model, oldest first, with the current stamp and phase."""
        return tuple(self._stamped(m) for m in self.segments)

    def continuation(self) -> tuple[KinematicModel, dict[str, Any], Array] | None:
        """The latest closed phase with a verdict, for another source of poses to continue
        (:mod:`services.kinematics.robot_fusion`): its model, its estimator's snapshot and its
        hand pose at its end (estimator space); None without one. Changes nothing."""
        if self._candidate is None:
            return None
        record, snapshot, T_end = self._candidate
        return self._closed[record], snapshot, T_end

    def _stamped(self, model: KinematicModel) -> KinematicModel:
        stamp = model.stamp_ns if self._last_stamp is None else self._last_stamp
        return replace(model, stamp_ns=stamp, phase=self.phase)

    def _open_model(self, final: bool = False) -> KinematicModel:
        """The open phase's model; its type "unknown" until the phase is confirmed (a stroke
        ended at rest, module docstring), unless ``final`` (the phase closes held)."""
        o = self._open
        assert o is not None
        m = o.estimator.model
        reference = np.asarray(m.reference_pose, dtype=float) @ se3_inverse_fast(o.pose_map)
        reference.flags.writeable = False
        return replace(m, reference_pose=reference, segment=o.index,
                       segment_start_ns=o.start_ns, segment_end_ns=None, phase="contact",
                       first_segment=None if o.first_segment == o.index else o.first_segment,
                       type=m.type if (o.confirmed or final) else "unknown")

    def _confirm(self) -> None:
        """Count the still frames after the joint filter started; confirm the phase after
        ``confirm_still_frames`` of them (module docstring)."""
        o = self._open
        assert o is not None
        if o.confirmed:
            return
        est = o.estimator
        if est.prismatic is None and est.revolute is None:
            o.still = 0
            return
        speed = self._detector.speed
        o.still = o.still + 1 if speed is not None and speed <= (
            self.segmentation.still_speed_m_per_s) else 0
        o.confirmed = o.still >= self.segmentation.confirm_still_frames

    # ------------------------------------------------------------------------------ input

    def _check(self, stamp_ns: Any, T: Any, cov: Any,
               body_id: int | None) -> tuple[RejectReason | None, Frame | None]:
        """:class:`KinematicEstimator`'s input guards, applied to every frame (also free ones)."""
        if (isinstance(stamp_ns, bool) or not isinstance(stamp_ns, (int, np.integer))
                or not 0 <= int(stamp_ns) <= INT64_MAX):
            return "invalid_stamp", None
        try:
            T = np.array(T, dtype=float)
            cov = np.array(cov, dtype=float)
        except (TypeError, ValueError):
            return "invalid_value", None
        if T.shape != (4, 4) or cov.shape != (6, 6):
            return "bad_shape", None
        if not (math.isfinite(float(T.sum())) and math.isfinite(float(cov.sum()))):
            return "non_finite", None
        if min(cov.diagonal().tolist()) < 0.0:
            return "invalid_covariance", None
        if self._last_stamp is not None:
            if int(stamp_ns) == self._last_stamp:
                return "duplicate_stamp", None
            if int(stamp_ns) < self._last_stamp:
                return "out_of_order", None
        T.flags.writeable = False
        cov.flags.writeable = False
        return None, Frame(int(stamp_ns), T, cov, body_id)

    def update(self, stamp_ns: int, T_frame_hand: Array, pose_covariance: Array,
               landmarks: Array | None = None, body_id: int | None = None) -> SegmentedUpdate:
        """Absorb one hand body (module docstring); ``landmarks`` (21, 3) [m] in ``frame``,
        NaN rows untracked, or None (no hand-shape cue for this frame). ``body_id``: the
        tracker's body frame (None: one frame throughout); a pose in another body frame than the
        open phase's so far restarts that phase's estimate from it (the phase keeps its start)."""
        reason, frame = self._check(stamp_ns, T_frame_hand, pose_covariance, body_id)
        if reason is not None or frame is None:
            return SegmentedUpdate(model=None, reason=reason)
        self._last_stamp = frame.stamp_ns
        self._accepted += 1
        self._buffer(frame)
        self._note = ""
        cfg = self.segmentation
        if not cfg.enabled:
            event = None if self._open is not None else ContactEvent("onset", frame.stamp_ns)
        else:
            event = (self._cueless(frame, landmarks)
                     or self._detector.update(frame.stamp_ns, frame.pose[:3, 3], landmarks))
        reason = None
        if event is not None and event.kind == "onset":
            self._start(event.stamp_ns, event.initial)
            if self._open is not None and (self._cueless_since is not None or not cfg.enabled):
                self._open.confirmed = True  # nothing to doubt it with
                self._open.cued = False
        elif self._open is not None:
            if frame.body_id != self._open.body_id:
                self._restart(frame.body_id)
            reason = self._feed_live(frame)
            self._confirm()
            if event is None and self._open.cued and self._open.confirmed and (
                    self._open.estimator.model.type == "disconnected"):
                # No joint explains the hand's motion any more: it holds nothing.
                event = replace(self._detector.force_release(frame.stamp_ns), moving=True)
        if event is not None and event.kind == "release" and self._open is not None:
            self._close(event.stamp_ns, held=not event.moving)
        if reason is not None:
            return SegmentedUpdate(model=None, reason=reason, event=event, note=self._note)
        return SegmentedUpdate(model=self.model, event=event, note=self._note)

    def _buffer(self, frame: Frame) -> None:
        recent = self._recent
        recent.append(frame)
        horizon = frame.stamp_ns - int((self.segmentation.max_lag_s + 0.2) * 1e9)
        while recent and recent[0].stamp_ns < horizon:
            recent.popleft()

    def _cueless(self, frame: Frame, landmarks: Array | None) -> ContactEvent | None:
        """A stream whose first frame carries no landmarks (a producer that sends none) is one
        contact phase from that frame, as without segmentation (module docstring)."""
        if self._accepted != 1 or ApertureCue.provided(landmarks):
            return None
        self._cueless_since = frame.stamp_ns
        self._detector.phase = "contact"
        return ContactEvent("onset", frame.stamp_ns)

    # ------------------------------------------------------------------------------ phases

    def _start(self, onset_ns: int, initial: bool) -> None:
        """Open a phase at ``onset_ns`` and feed it the buffered frames from there; an
        ``initial`` one is kept only with an articulated verdict (module docstring)."""
        if self._open is not None:  # cannot happen with the detector's alternation; be safe
            self._close(self._open.estimator.model.stamp_ns)
        index = len(self._closed)
        estimator = KinematicEstimator(self.config, self.frame_id)
        body_id = self._recent[-1].body_id
        self._open = _Open(index, onset_ns, estimator, pending=self._candidate is not None,
                           body_id=body_id)
        self._open.initial = initial
        self._checkpoint()
        for frame in list(self._recent):
            if frame.stamp_ns >= onset_ns and frame.body_id == body_id:
                self._feed_live(frame)

    def _restart(self, body_id: int | None) -> None:
        """The tracker started a new body frame: the open phase's estimate starts again from
        the next frame (the poses fed so far are in the old one)."""
        o = self._open
        assert o is not None
        o.body_id = body_id
        o.pending = self._candidate is not None
        o.first_segment = o.index
        o.pose_map = np.eye(4)
        o.frames = []
        o.still = 0
        o.estimator = KinematicEstimator(self.config, self.frame_id)
        o.checkpoints.clear()
        o.fed = 0
        self._checkpoint()

    def _feed(self, frame: Frame) -> RejectReason | None:
        o = self._open
        assert o is not None
        T = frame.pose if o.pending or o.first_segment == o.index else frame.pose @ o.pose_map
        result: UpdateResult = o.estimator.update(frame.stamp_ns, T, frame.covariance)
        self._note = result.note
        if result.reason is not None:
            return result.reason
        o.fed += 1
        if o.fed % CHECKPOINT_FRAMES == 0:
            self._checkpoint()
        return None

    def _feed_live(self, frame: Frame) -> RejectReason | None:
        o = self._open
        assert o is not None
        if not o.pending:
            return self._feed(frame)
        o.frames.append(frame)
        reason = self._feed(frame)
        same = self._regrasp_test(o.frames, final=len(o.frames) >= MAX_PENDING_FRAMES)
        if same is not None:
            self._decide(o.frames, same, complete=True)
        return reason

    def _regrasp_test(self, frames: list[Frame], final: bool) -> bool | None:
        """The re-grasp test on the open phase's ``frames`` so far (module docstring): True (the
        candidate's joint moves), False (another joint), None (the motion is not significant
        yet; ``final``: decide anyway, as at the end of the phase)."""
        assert self._candidate is not None
        if len(frames) < 2:
            return True if final else None
        cfg = self.segmentation
        first, last = frames[0], frames[-1]
        previous = self._closed[self._candidate[0]]
        residual, motion = screw_residual(previous, se3_inverse_fast(first.pose),
                                          first.covariance, last.pose, last.covariance)
        if motion < cfg.same_joint_significance and not final:
            return None
        return residual <= max(cfg.same_joint_fraction * motion, _CHI2_5_99)

    def _checkpoint(self) -> None:
        """Remember the open estimator's state; keep what a release within the lag may need."""
        o = self._open
        assert o is not None
        est = o.estimator
        o.checkpoints.append((est.model.stamp_ns, est.to_snapshot()))
        if self._last_stamp is not None:
            horizon = self._last_stamp - int(self.segmentation.max_lag_s * 1e9)
            while len(o.checkpoints) > 1 and o.checkpoints[1][0] <= horizon:
                o.checkpoints.popleft()

    def _decide(self, frames: list[Frame], same: bool, complete: bool) -> None:
        """Settle the re-grasp test: continue the candidate's joint (``same``) or keep the new
        estimate, fed with ``frames`` (the phase's frames so far; ``complete``: all of them,
        already fed to the new estimate)."""
        o = self._open
        assert o is not None and self._candidate is not None
        o.pending = False
        o.frames = []
        if not same:
            if complete:
                return  # the new estimate has been fed every frame already
            o.estimator = KinematicEstimator(self.config, self.frame_id)
        else:
            record, snapshot, T_end = self._candidate
            previous = self._closed[record]
            o.estimator = KinematicEstimator.from_snapshot(snapshot, self.config)
            o.first_segment = (previous.first_segment if previous.first_segment is not None
                               else previous.segment)
            o.pose_map = se3_inverse_fast(frames[0].pose) @ T_end
        o.checkpoints.clear()
        o.fed = 0
        self._checkpoint()
        for frame in frames:
            self._feed(frame)

    def _close(self, release_ns: int, held: bool = True) -> None:
        """End the open phase at ``release_ns`` (its last frame): roll its estimate back to it;
        drop it without evidence of contact (not ``held``, or no verdict; module docstring)."""
        o = self._open
        assert o is not None
        if o.pending:
            kept = [f for f in o.frames if f.stamp_ns <= release_ns]
            if kept:
                same = self._regrasp_test(kept, final=True)
                self._decide(kept, bool(same), complete=len(kept) == len(o.frames))
            o.pending = False
        self._rollback(release_ns)
        model = replace(self._open_model(final=True), segment_end_ns=max(release_ns, o.start_ns))
        self._open = None
        short_hold = model.type == "rigid" and (
            release_ns - o.start_ns < self.segmentation.min_rigid_hold_s * 1e9)
        if not held or short_hold or model.type not in (
                ARTICULATED if o.initial else VERDICT_TYPES):
            return  # no evidence that the hand held anything: not a contact phase
        self._closed.append(model)
        if model.type in VERDICT_TYPES:
            T_end = predict_hand_pose(o.estimator.model, o.estimator.model.stamp_ns)
            assert T_end is not None
            self._candidate = (len(self._closed) - 1, o.estimator.to_snapshot(), T_end[0])

    def _rollback(self, release_ns: int) -> None:
        o = self._open
        assert o is not None
        if o.estimator.model.stamp_ns <= release_ns:
            return
        usable = [c for c in o.checkpoints if c[0] <= release_ns]
        if not usable:
            return  # (only after a restart: the release is then dated at the restart)
        stamp, snapshot = usable[-1]
        o.estimator = KinematicEstimator.from_snapshot(snapshot, self.config)
        o.checkpoints = deque(c for c in o.checkpoints if c[0] <= stamp)
        for frame in list(self._recent):
            if (stamp < frame.stamp_ns <= release_ns and frame.stamp_ns >= o.start_ns
                    and frame.body_id == o.body_id):
                self._feed(frame)

    # ------------------------------------------------------------------------------ snapshot

    def to_snapshot(self) -> dict[str, Any]:
        """The complete state as a dict of str/int/float/bool/None/list/dict/np.ndarray values:
        every closed phase, the open one, the detector and the buffered frames (not the
        rollback checkpoints: a release found after a restart is not rolled back past it)."""
        o = self._open
        return {
            "version": SNAPSHOT_VERSION,
            "frame_id": self.frame_id,
            "last_stamp_ns": self._last_stamp,
            "cueless_since_ns": self._cueless_since,
            "accepted": self._accepted,
            "detector": self._detector.to_state(),
            "recent": [_frame_state(f) for f in self._recent],
            "closed": [m.to_dict() for m in self._closed],
            "candidate": None if self._candidate is None else {
                "record": self._candidate[0], "estimator": self._candidate[1],
                "end_pose": self._candidate[2]},
            "open": None if o is None else {
                "index": o.index, "start_ns": o.start_ns, "first_segment": o.first_segment,
                "initial": o.initial, "confirmed": o.confirmed, "still": o.still,
                "cued": o.cued,
                "estimator": o.estimator.to_snapshot(),
                "pose_map": o.pose_map, "pending": o.pending, "body_id": o.body_id,
                "frames": [_frame_state(f) for f in o.frames]},
        }

    @classmethod
    def from_snapshot(cls, d: Any, config: KinematicsConfig,
                      segmentation: SegmentationConfig) -> SegmentedEstimator:
        """Rebuild from :meth:`to_snapshot`. Every value is checked (the joint estimates by
        :meth:`KinematicEstimator.from_snapshot`, the phases' models by the wire checks of a
        received one): :class:`~services.common.snapshot.SnapshotError` names the first field
        that is wrong."""
        r = SnapshotReader(d, "estimator")
        version = r.raw("version")
        if version != SNAPSHOT_VERSION:
            raise SnapshotError(f"estimator.version: unsupported snapshot version {version!r} "
                                f"(this version writes {SNAPSHOT_VERSION})")
        est = cls(config, segmentation, frame_id=r.choice("frame_id", FRAME_IDS))
        est._last_stamp = r.optional_integer("last_stamp_ns", 0, INT64_MAX)
        est._cueless_since = r.optional_integer("cueless_since_ns", 0, INT64_MAX)
        est._accepted = r.integer("accepted", 0)
        est._detector = ContactDetector.from_state(r.raw("detector"), segmentation,
                                                   "estimator.detector")
        est._recent = deque(_frames(r, "recent"))
        closed = r.raw("closed")
        if not isinstance(closed, list):
            raise SnapshotError("estimator.closed: expected a list")
        for i, m in enumerate(closed):
            try:
                model = KinematicModel.from_msgpack(pack_document(m))
            except (ProtocolError, TypeError, ValueError) as exc:
                raise SnapshotError(f"estimator.closed[{i}]: {exc}") from exc
            if model.segment != i or model.segment_end_ns is None:
                raise SnapshotError(f"estimator.closed[{i}]: not closed phase {i}")
            est._closed.append(model)
        c = r.optional_map("candidate")
        if c is not None:
            record = c.integer("record", 0, len(est._closed) - 1)
            snapshot = c.raw("estimator")
            _joint_estimate(snapshot, config, "estimator.candidate")  # validates it
            est._candidate = (record, snapshot, c.pose("end_pose"))
        o = r.optional_map("open")
        if o is not None:
            opened = _Open(o.integer("index", len(est._closed), len(est._closed)),
                           o.integer("start_ns", 0, INT64_MAX),
                           _joint_estimate(o.raw("estimator"), config, "estimator.open"),
                           o.boolean("pending"), o.optional_integer("body_id"))
            opened.first_segment = o.integer("first_segment", 0, opened.index)
            opened.initial = o.boolean("initial")
            opened.confirmed = o.boolean("confirmed")
            opened.cued = o.boolean("cued")
            opened.still = o.integer("still", 0)
            opened.pose_map = o.pose("pose_map")
            opened.frames = _frames(o, "frames")
            if opened.pending and est._candidate is None:
                raise SnapshotError("estimator.open.pending: no phase to continue")
            est._open = opened
            est._checkpoint()
        return est


def _joint_estimate(snapshot: Any, config: KinematicsConfig, where: str) -> KinematicEstimator:
    """:meth:`KinematicEstimator.from_snapshot`, its errors naming the path from the document's
    top (``estimator.open.estimator.updates: ...``)."""
    try:
        return KinematicEstimator.from_snapshot(snapshot, config)
    except SnapshotError as exc:
        raise SnapshotError(f"{where}.{exc}") from exc


def _frame_state(f: Frame) -> dict[str, Any]:
    return {"stamp_ns": f.stamp_ns, "pose": f.pose, "covariance": f.covariance,
            "body_id": f.body_id}


def _frames(r: SnapshotReader, key: str) -> list[Frame]:
    rows = r.raw(key)
    if not isinstance(rows, list):
        raise SnapshotError(f"{r.path}.{key}: expected a list")
    out = []
    for i, row in enumerate(rows):
        f = SnapshotReader(row, f"{r.path}.{key}[{i}]")
        out.append(Frame(f.integer("stamp_ns", 0, INT64_MAX), f.pose("pose"),
                         f.covariance("covariance", 6), f.optional_integer("body_id")))
    if [f.stamp_ns for f in out] != sorted({f.stamp_ns for f in out}):
        raise SnapshotError(f"{r.path}.{key}: stamps not strictly increasing")
    return out


__all__ = ["VERDICT_TYPES", "Frame", "SegmentedEstimator", "SegmentedUpdate", "verdict_of"]
