"""Online contact-phase detection from the hand's own cues (docs/estimation.md#contact-phases).

:class:`ContactDetector` decides, frame by frame and causally, whether the hand holds something
("contact") or moves freely ("free"). Its input per frame is what a ``HandBody`` carries: the
stamp [ns], the hand position in the tracking frame [m] and the filtered landmark positions
(21, 3) [m] (NaN where untracked). Two cues:

- **Finger aperture** (:class:`ApertureCue`): the mean distance of ten distal finger landmarks
  (thumb IP and tip; DIP and tip of each finger) from the palm centre (wrist and the four
  MCPs), divided by the palm size (mean wrist-knuckle distance), so it depends neither on the
  hand's size nor on its pose or frame; the two largest and two smallest distances are dropped
  (a depth error or a swapped finger moves one or two of them by centimetres). A landmark the
  tracker lost keeps its last distance (the tips are untracked in a quarter of the frames;
  dropping them would move the mean with whichever are missing). Smoothed causally.
- **Hand speed**: of the hand origin over the last ``speed_window_frames`` frames.

Rules, after the grasp as people perform it (a reach that decelerates, the fingers closing on
the handle while the hand is slow, a moment of stillness before the stroke; the fingers open to
let go while the handle is at rest, then the hand leaves):

- **onset**: while free, the aperture fell from at least ``open_aperture`` by at least
  ``closure_drop`` to at most ``closed_aperture`` within ``closure_window_s``; at the middle of
  the fall the hand was at most ``closure_speed_m_per_s`` fast (fingers that change posture in
  the course of a free movement close while it is fast); the aperture has settled (no lower by
  ``settle_margin`` for ``settle_frames`` frames) and the hand is slower than
  ``still_speed_m_per_s``. Dated at the first frame within ``settle_margin`` of the settled
  minimum (the fingers closed).
- **release**: while in contact, the aperture stayed ``opening_rise`` above the contact level (the
  median aperture of the contact from ``contact_level_window_s`` to ``level_lag_s`` ago) for
  ``opening_frames`` frames. Dated at the foot of the rise (the last frame within
  ``opening_margin`` of the lowest aperture of the ``level_lag_s`` before it). A release with
  the hand faster than ``release_speed_m_per_s`` is flagged ``moving``: a hand lets go of a
  handle at rest, so that phase held nothing.
- **initial**: the first decision of a stream (after ``warmup_frames`` frames with an aperture)
  with a closed hand (at most ``closed_aperture``) that has not moved (never faster than
  ``still_speed_m_per_s``: a hand on a handle rests before its first stroke) starts a tentative
  contact at the first frame (a stream cut at the grasp, or a service started
  mid-demonstration). It ends like any other, and also when the hand is seen closing (it was
  open, so it held nothing).

Lag: events are dated back, never further than ``max_lag_s``, so the phase of a frame is final
``max_lag_s`` after it; the decision at a frame's own time is the phase the detector is in then.
Frames without landmarks keep the current phase. The model evidence (does a joint explain the
motion?) lives one level up, in :mod:`services.kinematics.segments`. No I/O, no clock: time comes
only from the stamps.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass, fields
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from services.common.snapshot import SnapshotError, SnapshotReader

Array = NDArray[np.float64]

Phase = Literal["free", "contact"]
PHASES: tuple[Phase, ...] = ("free", "contact")

# Landmark indices (MediaPipe order, docs/protocol.md).
PALM_LANDMARKS = (0, 5, 9, 13, 17)
KNUCKLES = (5, 9, 13, 17)
DISTAL_LANDMARKS = (3, 4, 7, 8, 11, 12, 15, 16, 19, 20)
_WRIST = 0
_TRIM = 2  # distances dropped at either end before averaging


@dataclass(frozen=True)
class SegmentationConfig:
    """Parameters of contact-phase segmentation (the ``[segmentation]`` config section).

    Aperture values are in palm sizes (mean wrist-knuckle distance, about 8-9 cm on an adult
    hand): the open pre-shape of a reach is about 1.3-1.5, a power grasp 0.7-0.8, a pinch 0.9-1.0.
    Tuned on the tuning partitions only (docs/estimation.md#contact-phases).
    """

    # Off: every hand body feeds one estimate, the demonstration is one contact phase (as before
    # segmentation existed).
    enabled: bool = True
    # Causal exponential smoothing of the aperture: weight of the newest frame.
    aperture_smoothing: float = 0.5
    # Palm-size smoothing (the palm does not change; its measurement is noisy): newest weight.
    palm_smoothing: float = 0.1
    # Hand speed: displacement of the hand origin over this many frames, divided by their time.
    speed_window_frames: int = 5
    # Frames with an aperture before the detector decides anything (the landmark filters and the
    # palm size settle).
    warmup_frames: int = 8
    # Onset: the hand was open (aperture at least this) ...
    open_aperture: float = 1.2
    # ... the aperture fell by this much below that maximum ...
    closure_drop: float = 0.25
    # ... to at most this (a grasp, not a relaxed hand) ...
    closed_aperture: float = 1.15
    # ... the maximum taken over this long a window [s] ...
    closure_window_s: float = 1.5
    # ... at most this fast at the middle of the fall [m/s] ...
    closure_speed_m_per_s: float = 0.3
    # ... no new minimum (lower by more than settle_margin) for this many frames ...
    settle_frames: int = 4
    settle_margin: float = 0.05
    # ... and the hand slower than this [m/s].
    still_speed_m_per_s: float = 0.12
    # Release: the aperture rose this far above the contact level ...
    opening_rise: float = 0.2
    # ... in this many consecutive frames with landmarks (a tracker transient lasts one or two).
    opening_frames: int = 3
    # A release with the hand faster than this [m/s] (over the 0.1 s up to the dated release)
    # ends a phase that held nothing.
    release_speed_m_per_s: float = 0.2
    # The release is dated at the last frame within this margin of the lowest aperture before
    # the rise.
    opening_margin: float = 0.06
    # Contact level: median of the aperture over the contact's last this many seconds (robust to
    # the fingers tightening and loosening on the handle during a stroke).
    contact_level_window_s: float = 2.0
    # ... up to this long ago [s] (an opening, or the slow opening of a reach, does not raise it).
    level_lag_s: float = 0.5
    # Events are never dated back further than this [s]: the lag of a final phase decision.
    max_lag_s: float = 0.6
    # --- model evidence (services.kinematics.segments) ---
    # A re-grasp continues the previous joint when the new contact's motion fits its screw: once
    # that motion is significant (squared Mahalanobis norm of the displacement since the new
    # grasp at least same_joint_significance), the screw must leave at most same_joint_fraction
    # of it unexplained (squared Mahalanobis residual of the best 1-DOF fit).
    same_joint_significance: float = 25.0
    same_joint_fraction: float = 0.5
    # An open phase publishes its type once a joint filter has started and the hand has then
    # been slower than still_speed_m_per_s for this many frames (a stroke that ended at rest, as
    # on a handle; free motion that closed the fingers on nothing goes on, or ends by opening
    # them while moving); until then its type is "unknown".
    confirm_still_frames: int = 6
    # A phase whose verdict is rigid (the hand held still) is kept only if it lasted this long [s]:
    # a hand resting a moment with curled fingers has not shown that it holds anything.
    min_rigid_hold_s: float = 2.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"{f.name} must be finite, got {value!r}")
        for name in ("aperture_smoothing", "palm_smoothing"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)!r}")
        for name in ("closure_drop", "closure_window_s", "closure_speed_m_per_s",
                     "still_speed_m_per_s", "opening_rise", "max_lag_s", "contact_level_window_s",
                     "release_speed_m_per_s",
                     "same_joint_significance", "same_joint_fraction", "min_rigid_hold_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("settle_margin", "opening_margin", "level_lag_s"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("speed_window_frames", "settle_frames", "warmup_frames", "opening_frames",
                     "confirm_still_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")


class ApertureCue:
    """Finger aperture in palm sizes from filtered landmarks (module docstring); None until every
    distal landmark and the palm have been seen."""

    def __init__(self, palm_smoothing: float) -> None:
        self._alpha = palm_smoothing
        self.reset()

    def reset(self) -> None:
        self._last = [math.nan] * len(DISTAL_LANDMARKS)
        self._palm = math.nan

    @staticmethod
    def provided(points: Array | None) -> bool:
        """Whether ``points`` (21, 3) carry landmarks at all: not None, not all NaN, not all the
        same point (a producer without landmarks sends zeros)."""
        if points is None:
            return False
        rows = np.asarray(points, dtype=float)
        finite = rows[np.isfinite(rows).all(axis=1)] if rows.ndim == 2 else rows[:0]
        return len(finite) > 1 and float(np.ptp(finite, axis=0).max()) > 0.0

    def update(self, points: Array) -> float | None:
        """The aperture of one frame; ``points`` (21, 3) [m], NaN rows untracked."""
        rows = np.asarray(points, dtype=float).tolist()
        palm = [rows[k] for k in PALM_LANDMARKS if math.isfinite(rows[k][0] + rows[k][1]
                                                                 + rows[k][2])]
        if len(palm) < 3:
            return None
        n = len(palm)
        cx = sum(p[0] for p in palm) / n
        cy = sum(p[1] for p in palm) / n
        cz = sum(p[2] for p in palm) / n
        wx, wy, wz = rows[_WRIST]
        if math.isfinite(wx + wy + wz):
            sizes = [math.dist(rows[k], rows[_WRIST]) for k in KNUCKLES
                     if math.isfinite(rows[k][0] + rows[k][1] + rows[k][2])]
            size = sum(sizes) / len(sizes) if sizes else 0.0
            if size > 0.01:  # a palm of zeros (no landmarks) is no palm
                self._palm = size if math.isnan(self._palm) else (
                    self._palm + self._alpha * (size - self._palm))
        last = self._last
        for i, k in enumerate(DISTAL_LANDMARKS):
            x, y, z = rows[k]
            if math.isfinite(x + y + z):
                last[i] = math.sqrt((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2)
        if not (math.isfinite(sum(last)) and self._palm > 0.0):
            return None
        # Trimmed mean: a landmark with a depth error or swapped with its neighbour moves one or
        # two of the distances by centimetres.
        kept = sorted(last)[_TRIM:-_TRIM]
        return sum(kept) / (len(kept) * self._palm)

    def to_state(self) -> dict[str, Any]:
        """The last distances [m] (None: not seen yet) and the palm size [m] (None: not yet)."""
        return {"last": [None if math.isnan(x) else x for x in self._last],
                "palm": None if math.isnan(self._palm) else self._palm}

    def restore(self, r: SnapshotReader) -> None:
        """Adopt :meth:`to_state` read through ``r`` (SnapshotError names what is wrong)."""
        last = r.raw("last")
        if not isinstance(last, list) or len(last) != len(DISTAL_LANDMARKS):
            raise SnapshotError(f"{r.path}.last: expected {len(DISTAL_LANDMARKS)} distances")
        values = []
        for x in last:
            if x is None:
                values.append(math.nan)
            elif isinstance(x, (int, float)) and not isinstance(x, bool) and 0.0 <= x < 10.0:
                values.append(float(x))
            else:
                raise SnapshotError(f"{r.path}.last: {x!r} is not a distance")
        palm = r.raw("palm")
        if palm is not None and not (isinstance(palm, float) and 0.0 < palm < 10.0):
            raise SnapshotError(f"{r.path}.palm: {palm!r} is not a palm size")
        self._last = values
        self._palm = math.nan if palm is None else palm


@dataclass(frozen=True)
class ContactEvent:
    """A phase change found at the current frame: ``kind`` "onset" or "release", dated at
    ``stamp_ns`` (an earlier frame's stamp: the first frame of the contact for an onset, its last
    frame for a release). ``initial``: an onset because the demonstration starts with a closed
    hand, not because the hand was seen closing (tentative; docs/estimation.md#contact-phases).
    ``moving``: a release with the hand faster than ``release_speed_m_per_s``: a hand lets go
    of a handle at rest, so the phase held nothing."""

    kind: Literal["onset", "release"]
    stamp_ns: int
    initial: bool = False
    moving: bool = False


@dataclass
class _Frame:
    stamp_ns: int
    aperture: float | None  # smoothed; None without landmarks
    speed: float | None     # m/s; None until the window is full


class ContactDetector:
    """Causal contact/free decision with dated events (module docstring)."""

    def __init__(self, config: SegmentationConfig | None = None) -> None:
        self.config = SegmentationConfig() if config is None else config
        self.reset()

    def reset(self) -> None:
        """Forget everything: the hand is free."""
        self.phase: Phase = "free"
        self._cue = ApertureCue(self.config.palm_smoothing)
        self._smoothed: float | None = None
        self._frames: deque[_Frame] = deque()
        self._positions: deque[tuple[int, float, float, float]] = deque(
            maxlen=self.config.speed_window_frames + 1)
        self._last_event_ns: int | None = None
        self._seen = 0
        self._initial_phase = False  # in the tentative contact a stream started with

    @property
    def aperture(self) -> float | None:
        """The smoothed aperture of the last frame with landmarks [palm sizes]."""
        return self._smoothed

    @property
    def speed(self) -> float | None:
        """The hand speed at the last frame [m/s] (None until the window is full)."""
        return self._frames[-1].speed if self._frames else None

    def update(self, stamp_ns: int, position: Array, landmarks: Array | None) -> ContactEvent | None:
        """One frame: stamp [ns] (strictly increasing), hand origin (3,) [m] in the tracking
        frame, landmark positions (21, 3) [m] or None; returns the event found at this frame."""
        cfg = self.config
        x, y, z = np.asarray(position, dtype=float).tolist()
        self._positions.append((int(stamp_ns), x, y, z))
        speed = None
        if len(self._positions) == self._positions.maxlen:
            t0, x0, y0, z0 = self._positions[0]
            span = (int(stamp_ns) - t0) * 1e-9
            if span > 0.0:
                speed = math.sqrt((x - x0) ** 2 + (y - y0) ** 2 + (z - z0) ** 2) / span
        raw = None if landmarks is None else self._cue.update(landmarks)
        if raw is not None:
            self._seen += 1
            s = self._smoothed
            self._smoothed = raw if s is None else s + cfg.aperture_smoothing * (raw - s)
        frame = _Frame(int(stamp_ns), None if raw is None else self._smoothed, speed)
        frames = self._frames
        frames.append(frame)
        horizon = int(stamp_ns) - int(max(cfg.closure_window_s, cfg.max_lag_s,
                                          cfg.contact_level_window_s) * 1e9)
        while frames and frames[0].stamp_ns < horizon:
            frames.popleft()
        if frame.aperture is None or self._seen < cfg.warmup_frames:
            return None
        if self._seen == cfg.warmup_frames and self._last_event_ns is None:
            return self._initial(frame)
        if self.phase == "free":
            return self._onset(frame)
        return self._release(frame)

    # ------------------------------------------------------------------------------- events

    def _dated(self, stamp_ns: int, now_ns: int) -> int:
        """An event's stamp, never earlier than ``max_lag_s`` before now nor than the previous
        event."""
        earliest = now_ns - int(self.config.max_lag_s * 1e9)
        if self._last_event_ns is not None:
            earliest = max(earliest, self._last_event_ns + 1)
        candidates = [f.stamp_ns for f in self._frames if f.stamp_ns >= earliest]
        stamp = max(stamp_ns, earliest)
        return min((s for s in candidates if s >= stamp), default=now_ns)

    def _initial(self, now: _Frame) -> ContactEvent | None:
        """The first decision: a stream that starts with a closed hand starts in contact (the
        hand already held the handle), dated at its first frame within the lag."""
        assert now.aperture is not None
        cfg = self.config
        moving = [f.speed for f in self._frames if f.speed is not None and f.speed > (
            cfg.still_speed_m_per_s)]
        if now.aperture > cfg.closed_aperture or moving:
            return None  # open, or moving: a hand on a handle rests before its first stroke
        stamp = self._dated(self._frames[0].stamp_ns, now.stamp_ns)
        self.phase = "contact"
        self._initial_phase = True
        self._last_event_ns = stamp
        return ContactEvent("onset", stamp, initial=True)

    def _closure(self, now: _Frame) -> tuple[int, int, float] | None:
        """``(peak stamp, closed stamp, peak aperture)`` of a grasp closure that has just
        settled (module docstring), or None."""
        cfg = self.config
        if now.speed is None or now.speed > cfg.still_speed_m_per_s:
            return None
        window_start = now.stamp_ns - int(cfg.closure_window_s * 1e9)
        if self._last_event_ns is not None:
            window_start = max(window_start, self._last_event_ns + 1)
        values = [(f.stamp_ns, f.aperture, f.speed) for f in self._frames
                  if f.stamp_ns >= window_start and f.aperture is not None]
        n_settle = cfg.settle_frames
        if len(values) <= n_settle + 1:
            return None
        apertures = [v[1] for v in values]
        peak_i = max(range(len(values) - n_settle), key=apertures.__getitem__)
        peak = apertures[peak_i]
        if peak < cfg.open_aperture:
            return None
        low = min(apertures[peak_i:len(values) - n_settle])
        # A fall deep enough, to a grasp, and no further fall since (settled).
        if (peak - low < cfg.closure_drop or low > cfg.closed_aperture
                or min(apertures[-n_settle:]) < low - cfg.settle_margin):
            return None
        middle = peak - 0.5 * (peak - low)
        mid = next(v for v in values[peak_i:] if v[1] <= middle)
        if mid[2] is not None and mid[2] > cfg.closure_speed_m_per_s:
            return None
        closed = next(v for v in values[peak_i:] if v[1] <= low + cfg.settle_margin)
        if now.stamp_ns - closed[0] > cfg.max_lag_s * 1e9:
            return None  # closed longer ago than an onset may be dated back: not a grasp now
        return values[peak_i][0], closed[0], peak

    def _onset(self, now: _Frame) -> ContactEvent | None:
        closure = self._closure(now)
        if closure is None:
            return None
        stamp = self._dated(closure[1], now.stamp_ns)
        self.phase = "contact"
        self._last_event_ns = stamp
        return ContactEvent("onset", stamp)

    def _level(self, now: _Frame) -> float:
        """The contact level: median aperture of the contact's frames from ``contact_level_
        window_s`` to ``level_lag_s`` ago (an opening in progress does not raise it), or of its
        first ``opening_frames`` frames while it is younger."""
        cfg = self.config
        start = self._last_event_ns or 0
        since = max(start, now.stamp_ns - int(cfg.contact_level_window_s * 1e9))
        until = now.stamp_ns - int(cfg.level_lag_s * 1e9)
        held = [f.aperture for f in self._frames
                if f.aperture is not None and since <= f.stamp_ns <= until]
        if not held:
            held = [f.aperture for f in self._frames
                    if f.aperture is not None and f.stamp_ns >= start][:cfg.opening_frames]
        return statistics.median(held) if held else now.aperture  # type: ignore[arg-type]

    def _release(self, now: _Frame) -> ContactEvent | None:
        """The fingers opened (module docstring)."""
        cfg = self.config
        level = self._level(now)
        recent = [f.aperture for f in self._frames if f.aperture is not None][-cfg.opening_frames:]
        if len(recent) < cfg.opening_frames or min(recent) - level < cfg.opening_rise:  # type: ignore[type-var, operator]
            # A tentative initial contact ends when the hand is seen closing on something: it
            # was open before, so it held nothing (docs/estimation.md#contact-phases).
            closure = self._closure(now) if self._initial_phase else None
            if closure is None:
                return None
            # ... seen open: more open than in the phase, or open after moving like a reach
            reached = max((f.speed for f in self._frames if f.speed is not None
                           and (self._last_event_ns or 0) <= f.stamp_ns <= closure[0]),
                          default=0.0)
            if closure[2] - level < cfg.opening_rise and reached < cfg.closure_speed_m_per_s:
                return None
            before = [f for f in self._frames if f.stamp_ns < closure[0]]
            return self.force_release(self._dated(before[-1].stamp_ns if before
                                                  else closure[0], now.stamp_ns))
        # Dated at the foot of the rise: the last frame before it within opening_margin of the
        # lowest aperture of the level_lag_s before it.
        seen = [f for f in self._frames if f.aperture is not None]
        rise = seen[-cfg.opening_frames].stamp_ns
        start = max(self._last_event_ns or 0, rise - int(cfg.level_lag_s * 1e9))
        before = [f for f in seen if start <= f.stamp_ns < rise]
        last_closed = rise
        if before:
            base = min(f.aperture for f in before)  # type: ignore[type-var]
            last_closed = next(f.stamp_ns for f in reversed(before)
                               if f.aperture <= base + cfg.opening_margin)  # type: ignore[operator]
        return self.force_release(self._dated(last_closed, now.stamp_ns))

    def force_release(self, stamp_ns: int) -> ContactEvent:
        """End the contact at ``stamp_ns`` (a frame's stamp; also the model evidence's way to
        end it); the hand is free from the next frame on. ``moving`` if the hand was faster than
        ``release_speed_m_per_s`` in the 0.1 s up to it."""
        stamp = int(stamp_ns)
        speeds = [f.speed for f in self._frames
                  if stamp - 100_000_000 <= f.stamp_ns <= stamp and f.speed is not None]
        self.phase = "free"
        self._initial_phase = False
        self._last_event_ns = stamp
        moving = bool(speeds) and max(speeds) > self.config.release_speed_m_per_s  # type: ignore[type-var]
        return ContactEvent("release", stamp, moving=moving)

    # ------------------------------------------------------------------------------- snapshot

    def to_state(self) -> dict[str, Any]:
        """Everything :meth:`from_state` needs to continue identically."""
        return {
            "phase": self.phase, "cue": self._cue.to_state(), "smoothed": self._smoothed,
            "last_event_ns": self._last_event_ns, "seen": self._seen,
            "initial_phase": self._initial_phase,
            "frames": [{"stamp_ns": f.stamp_ns, "aperture": f.aperture, "speed": f.speed}
                       for f in self._frames],
            "positions": [list(p) for p in self._positions],
        }

    @classmethod
    def from_state(cls, state: Any, config: SegmentationConfig,
                   path: str = "detector") -> ContactDetector:
        """Rebuild from :meth:`to_state`; SnapshotError names the first field that is wrong."""
        r = SnapshotReader(state, path)
        d = cls(config)
        d.phase = r.choice("phase", PHASES)  # type: ignore[assignment]
        d._cue.restore(r.map("cue"))
        d._smoothed = None if r.is_none("smoothed") else r.number("smoothed")
        d._last_event_ns = r.optional_integer("last_event_ns", 0)
        d._seen = r.integer("seen", 0)
        d._initial_phase = r.boolean("initial_phase")
        frames, positions = r.raw("frames"), r.raw("positions")
        if not isinstance(frames, list) or not isinstance(positions, list):
            raise SnapshotError(f"{path}.frames, {path}.positions: expected lists")
        for i, raw in enumerate(frames):
            f = SnapshotReader(raw, f"{path}.frames[{i}]")
            d._frames.append(_Frame(f.integer("stamp_ns", 0),
                                    None if f.is_none("aperture") else f.number("aperture"),
                                    None if f.is_none("speed") else f.number("speed")))
        for i, raw in enumerate(positions):
            if not (isinstance(raw, list) and len(raw) == 4 and isinstance(raw[0], int)
                    and all(isinstance(v, float) and math.isfinite(v) for v in raw[1:])):
                raise SnapshotError(f"{path}.positions[{i}]: expected [stamp, x, y, z]")
            d._positions.append((raw[0], raw[1], raw[2], raw[3]))
        stamps = [f.stamp_ns for f in d._frames]
        if stamps != sorted(stamps):
            raise SnapshotError(f"{path}.frames: stamps out of order")
        return d


__all__ = [
    "DISTAL_LANDMARKS",
    "PALM_LANDMARKS",
    "PHASES",
    "ApertureCue",
    "ContactDetector",
    "ContactEvent",
    "Phase",
    "SegmentationConfig",
]
