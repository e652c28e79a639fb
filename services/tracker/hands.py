"""Which detected hand is which, and which one manipulates (docs/estimation.md#the-manipulating-hand).

A detector reports up to two hands per frame with a handedness label and a score, and both are
unreliable: labels flip (both hands are often reported "right"), and an idle hand resting in full
view scores higher than the partly occluded hand on a handle. So the tracker never uses either to
say which hand is which. Two hand identities (slots of the landmark filter bank) are kept by
**spatial continuity**:

- each detection is summarised by its robust centre (:func:`robust_centre`: the coordinate-wise
  median of its landmarks, tracking frame);
- while two hands have been seen together recently (:meth:`HandIdentities.contested`), each
  detection goes to the identity whose last centre explains it best, the assignment with the
  least summed squared distance in sigma, ``d / sqrt(s_c^2 + (v dt)^2)`` (``s_c`` =
  ``hand_centre_std_m``, ``v`` = ``hand_speed_std_mps``, ``dt`` the time since that identity was
  last seen); a detection beyond ``hand_association_gate_sigma`` of every identity is a new hand
  and restarts the identity it takes (the one whose last sighting it could least be, the
  tracked hand last);
- otherwise (one hand in view) the one detection is the tracked hand, as if there were no second
  identity at all.

Motion, measured while two hands are in view: each identity keeps an anchor (its filtered landmark
positions when it last moved); each frame the rigid motion from the anchor to the current
landmarks (trimmed Kabsch) moves the landmarks by an RMS :func:`rigid_displacement`, and when that
stays beyond ``hand_motion_threshold_m`` for ``hand_motion_frames`` frames in a row the hand has
*moved*: the time is recorded and the anchor re-set. A hand that has not moved for
``hand_idle_after_s`` is idle. Why the persistence: a resting hand's detections wander with the
detector's slowly varying errors, in single frames as far as a moving hand's (measured on the
paper's tuning split with an idle hand, 2 seeds: up to 8.2 cm RMS in one frame, at most 1.5 cm
held over three frames, while every manipulating hand held 6.6 cm or more). Which hand the body follows
is :class:`HandTracker`'s policy on top of these facts (``tracker.py``).

Frames and units: centres and landmark positions in the tracking frame (m), stamps in ns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from services.common.kabsch import weighted_kabsch
from services.tracker.config import TrackerConfig

Array = NDArray[np.float64]

NUM_IDENTITIES = 2
_MIN_COMMON = 6  # landmarks needed to compare a hand with its anchor
_MOVES_KEPT = 8


def robust_centre(points: Array) -> Array | None:
    """Coordinate-wise median (3,) of the finite rows of ``points`` (21, 3), None below 3 rows
    (robust to the depth outliers of single landmarks)."""
    finite = np.isfinite(points).all(axis=1)
    n = int(finite.sum())
    if n < 3:
        return None
    ordered = np.sort(points[finite], axis=0)  # np.median's result, at a fraction of its cost
    out: Array = 0.5 * (ordered[(n - 1) // 2] + ordered[n // 2])
    return out


def rigid_displacement(anchor: Array, current: Array) -> float | None:
    """RMS displacement (m) of the landmarks under the rigid motion from ``anchor`` to
    ``current`` (both (21, 3), NaN = no landmark), or None with fewer than 6 common landmarks.

    Kabsch on the common landmarks, refitted once without those whose residual exceeds three
    times the median (a depth outlier or a flexing finger must not look like motion of the hand);
    the motion then moves each landmark ``a`` by ``|R a + t - a|``, the hand's own displacement
    with the landmark noise averaged out by the fit.
    """
    common = np.isfinite(anchor).all(axis=1) & np.isfinite(current).all(axis=1)
    if common.sum() < _MIN_COMMON:
        return None
    a, c = anchor[common], current[common]
    weights = np.ones(a.shape[0])
    R, t = weighted_kabsch(a, c, weights)
    residual = np.linalg.norm(a @ R.T + t - c, axis=1)
    keep = residual <= 3.0 * float(np.median(residual))
    if keep.sum() >= _MIN_COMMON and not keep.all():
        a, c = a[keep], c[keep]
        R, t = weighted_kabsch(a, c, np.ones(a.shape[0]))
    moved = a @ R.T + t - a
    return float(np.sqrt(np.mean(np.sum(moved * moved, axis=1))))


@dataclass
class HandIdentity:
    """What is known of one hand identity: its last detection's landmarks ``points`` (21, 3)
    (tracking frame) and their :meth:`centre`, and when it was ``seen_ns``;
    its motion ``anchor`` (21, 3), the stamp it last ``moved_ns`` (None: not seen moving since its
    motion has been measured, from ``measured_ns``), and ``moves``, the stamps of its last
    motion events (at most ``_MOVES_KEPT``)."""

    points: Array | None = None
    seen_ns: int | None = None
    anchor: Array | None = None
    measured_ns: int | None = None
    moved_ns: int | None = None
    moves: list[int] = field(default_factory=list)  # stamps of the last motion events
    above: int = 0  # consecutive frames displaced beyond the threshold
    _centre: Array | None = None  # of points, computed when first asked for

    def centre(self) -> Array | None:
        """:func:`robust_centre` of the last detection (None: unknown)."""
        if self._centre is None and self.points is not None:
            self._centre = robust_centre(self.points)
        return self._centre

    def moves_since(self, stamp_ns: int | None) -> int:
        """Motion events after ``stamp_ns`` (all of them for None)."""
        return sum(1 for m in self.moves if stamp_ns is None or m > stamp_ns)


class HandIdentities:
    """The two hand identities (module docstring); ``config``: the tracker's."""

    def __init__(self, config: TrackerConfig) -> None:
        self._cfg = config
        self.reset()

    def reset(self) -> None:
        """Forget both hands."""
        self.hands = [HandIdentity() for _ in range(NUM_IDENTITIES)]
        self._together_ns: int | None = None  # the last frame with two hands in view

    def contested(self, stamp_ns: int) -> bool:
        """Whether two hands were in view together within the last ``hand_pair_memory_s``."""
        t = self._together_ns
        return t is not None and (stamp_ns - t) * 1e-9 <= self._cfg.hand_pair_memory_s

    def associate(self, stamp_ns: int, points: list[Array], tracked: int | None,
                  centres: list[Array | None] | None = None) -> tuple[list[int], list[bool]]:
        """The identity of each detection (its landmarks ``points`` (21, 3), tracking frame, NaN
        = missing; ``centres`` their :func:`robust_centre` if the caller has them) and whether
        that identity restarts with it (a new hand). ``tracked``: the identity the body follows
        (None: none yet). At most two detections."""
        if len(points) > NUM_IDENTITIES:
            raise ValueError(f"at most {NUM_IDENTITIES} hands per frame, got {len(points)}")
        if len(points) == NUM_IDENTITIES:
            self._together_ns = stamp_ns
        if not points:
            return [], []
        if not self.contested(stamp_ns):  # one hand in view: no centre needed now
            slot = tracked if tracked is not None else self._last_seen()
            self._saw(slot, points[0], None if centres is None else centres[0], stamp_ns)
            return [slot], [False]
        if centres is None:
            centres = [robust_centre(z) for z in points]
        gate = self._cfg.hand_association_gate_sigma
        best: tuple[float, tuple[int, ...]] | None = None
        orders = [(0,), (1,)] if len(centres) == 1 else [(0, 1), (1, 0)]
        for order in orders:
            cost = 0.0
            for centre, slot in zip(centres, order, strict=True):
                d = self._distance_sigma(slot, centre, stamp_ns)
                cost += min(d, gate) ** 2 if d is not None else gate ** 2
                if d is None or d >= gate:  # a restart: rather the stalest, the tracked last
                    age = self._age(slot, stamp_ns)
                    cost += 1e-6 * (2.0 if slot == tracked else 1.0) + 1e-9 / (1.0 + age)
            if best is None or cost < best[0]:
                best = (cost, order)
        assert best is not None
        slots = list(best[1])
        fresh = []
        for z, centre, slot in zip(points, centres, slots, strict=True):
            d = self._distance_sigma(slot, centre, stamp_ns)
            restart = d is None or d >= gate
            if restart:
                self.hands[slot] = HandIdentity()
            fresh.append(restart)
            self._saw(slot, z, centre, stamp_ns)
        return slots, fresh

    def observe_motion(self, slot: int, stamp_ns: int, positions: Array) -> None:
        """Measure the motion of identity ``slot`` from its filtered landmark ``positions``
        (21, 3) (module docstring)."""
        hand = self.hands[slot]
        if hand.anchor is None:
            hand.anchor, hand.measured_ns = positions.copy(), stamp_ns
            return
        moved = rigid_displacement(hand.anchor, positions)
        if moved is None:  # too few common landmarks: compare with these from now on
            hand.anchor, hand.above = positions.copy(), 0
        elif moved < self._cfg.hand_motion_threshold_m:
            hand.above = 0
        else:
            hand.above += 1
            if hand.above >= self._cfg.hand_motion_frames:
                hand.anchor, hand.moved_ns, hand.above = positions.copy(), stamp_ns, 0
                hand.moves = [*hand.moves[1 - _MOVES_KEPT:], stamp_ns]

    def moving(self, slot: int, stamp_ns: int) -> bool:
        """Whether identity ``slot`` moved within the last ``hand_idle_after_s``."""
        moved = self.hands[slot].moved_ns
        return moved is not None and (stamp_ns - moved) * 1e-9 < self._cfg.hand_idle_after_s

    def idle_s(self, slot: int, stamp_ns: int) -> float:
        """How long identity ``slot`` has been measured not to move (s; 0 when not measured)."""
        hand = self.hands[slot]
        since = hand.moved_ns if hand.moved_ns is not None else hand.measured_ns
        return 0.0 if since is None else (stamp_ns - since) * 1e-9

    # --- internals ------------------------------------------------------------------------

    def _saw(self, slot: int, points: Array, centre: Array | None, stamp_ns: int) -> None:
        hand = self.hands[slot]
        hand.points, hand._centre, hand.seen_ns = points, centre, stamp_ns

    def _last_seen(self) -> int:
        seen = [h.seen_ns if h.seen_ns is not None else -1 for h in self.hands]
        return int(np.argmax(seen))  # slot 0 when neither was seen

    def _age(self, slot: int, stamp_ns: int) -> float:
        seen = self.hands[slot].seen_ns
        return math.inf if seen is None else (stamp_ns - seen) * 1e-9

    def _distance_sigma(self, slot: int, centre: Array | None, stamp_ns: int) -> float | None:
        """``|c - c_slot| / sqrt(s_c^2 + (v dt)^2)``, None when either centre is unknown."""
        hand = self.hands[slot]
        last = hand.centre()
        if centre is None or last is None or hand.seen_ns is None:
            return None
        cfg = self._cfg
        dt = (stamp_ns - hand.seen_ns) * 1e-9
        sigma = math.hypot(cfg.hand_centre_std_m, cfg.hand_speed_std_mps * dt)
        return float(np.linalg.norm(centre - last)) / sigma


__all__ = ["NUM_IDENTITIES", "HandIdentities", "HandIdentity", "rigid_displacement",
           "robust_centre"]
