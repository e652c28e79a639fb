"""The timeline of a demonstration: contact phases on the object's joints and free hand legs.

A **contact** holds the part of one joint from ``t0`` to ``t1`` [s] while the joint follows a
rest/stroke plan (:mod:`services.synthetic.motion`); a **leg** moves the free hand from one pose
to another (:mod:`services.synthetic.free_motion`) or keeps it still. Legs name their end poses
relative to a contact's start or end pose (:class:`PoseRef`), so the free motion meets the grasp
exactly; the poses themselves are evaluated in :mod:`services.synthetic.compose`.

Variants (docs/synthetic.md#variants):

- ``cut``: one contact, nothing else (the paper's setting);
- ``whole``: rest (0.3-0.8 s), reach from 10-30 cm (grasp point) with the fingers opening,
  closure onto the handle (0.25-0.5 s, fingers closing), the contact, release (0.2-0.4 s,
  fingers opening, hand lifting 1-3 cm off), withdrawal 10-30 cm, rest;
- ``sequence``: as ``whole`` but two contacts on two joints (the lock first, ending at its full
  range) with a transfer between them;
- ``regrasp``: as ``whole`` but two strokes of one joint (to 40-65 % of the range, then to the
  range) separated by a release, a free return 5-15 cm away and a new grasp; a ratchet object
  (knob, dial, valve, key) is grasped again where the first grasp was, others at the moved
  handle;
- gap ``regrasp``: one joint, the hand lets go at a rest and is out of sight for 0.3-1.5 s
  (release, away, back, closure inside the gap) before grasping the handle again;
- gap ``dropout``: one contact, the detector loses the hand for 0.3-1.5 s somewhere in its
  middle half while the manipulation goes on.

Free-leg turns are 15-40 deg about a random axis; reach and withdrawal directions lie within
~50 deg of the outward direction (from the object towards its camera viewpoints).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import se3_exp
from services.synthetic import motion as mo
from services.synthetic.free_motion import leg_duration
from services.synthetic.hand import Participant
from services.synthetic.objects import ObjectPreset
from services.synthetic.placement import grasp_pose, regrasp_pose

Array = NDArray[np.float64]

PREGRASP_M = (0.02, 0.04)       # closure starts this far from the grasp (along PREGRASP_DIR_H)
RELEASE_LIFT_M = (0.01, 0.03)
REACH_M = (0.10, 0.30)
RETURN_M = (0.05, 0.15)
TURN_DEG = (15.0, 40.0)
GAP_S = (0.3, 1.5)
# Pre-grasp offset direction in the hand frame: back along the forearm and off the back of the
# hand (the hand closes onto the handle palm first).
PREGRASP_DIR_H = np.array([-1.0, 0.0, 0.7]) / np.linalg.norm([-1.0, 0.0, 0.7])


@dataclass(frozen=True)
class Scene:
    """The joints of one object in its frame ``o`` (every part frame = ``o`` at q = 0).

    ``mounts[j]``: the joint whose part carries joint ``j``'s base (None: the fixed base).
    """

    presets: tuple[ObjectPreset, ...]
    mounts: tuple[int | None, ...]

    def part_poses(self, q: Array) -> Array:
        """``T_o_part`` (J, N, 4, 4) of every joint for joint values ``q`` (J, N)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        n_j, n = q.shape
        out = np.empty((n_j, n, 4, 4))
        done: set[int] = set()

        def build(j: int) -> None:
            if j in done:
                return
            xi = self.presets[j].twist_object()
            own = np.stack([se3_exp(qk * xi) for qk in q[j]])
            m = self.mounts[j]
            if m is None:
                out[j] = own
            else:
                build(m)
                out[j] = out[m] @ own
            done.add(j)

        for j in range(n_j):
            build(j)
        return out


@dataclass(frozen=True, eq=False)
class PoseRef:
    """A hand pose: contact ``contact``'s ``at`` ("start"/"end") pose, its grasp point moved by
    ``shift_o`` (frame ``o``) plus ``shift_h`` (that pose's hand frame), turned by the rotation
    vector ``turn`` (frame ``o``) about the grasp point [m, rad]."""

    contact: int
    at: str
    shift_o: Array = field(default_factory=lambda: np.zeros(3))
    shift_h: Array = field(default_factory=lambda: np.zeros(3))
    turn: Array = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True, eq=False)
class FingerRef:
    """Finger angles: a fixed posture (5, 4) [rad], or contact ``contact``'s ``at`` angles."""

    posture: Array | None = None
    contact: int = -1
    at: str = "start"


@dataclass(frozen=True, eq=False)
class Contact:
    """The hand holds joint ``joint``'s part on [t0, t1] [s] (``plan`` in absolute time)."""

    index: int
    joint: int
    t0: float
    t1: float
    plan: mo.ArticulationPlan
    T_part_hand0: Array      # (4, 4) grasp pose on the part at t0 (before slip)
    grasp_part: Array        # (3,) the held point in the part frame


@dataclass(frozen=True, eq=False)
class Leg:
    """The free hand on [t0, t1] [s]: ``start`` -> ``end`` (``still``: stays at ``start``)."""

    kind: str
    t0: float
    t1: float
    start: PoseRef
    end: PoseRef
    fingers_start: FingerRef
    fingers_end: FingerRef
    finger_window: tuple[float, float] = (0.0, 1.0)  # fraction of the leg the fingers move in
    bump_fraction: float = 0.0
    bump_dir: Array = field(default_factory=lambda: np.zeros(3))
    still: bool = False
    anchor_end: bool = False       # a still leg's tremor is 0 at its end (else at its start)
    detected: bool = True


@dataclass(frozen=True, eq=False)
class Timeline:
    """Contacts and legs, contiguous in time from 0 to ``duration_s``."""

    contacts: tuple[Contact, ...]
    legs: tuple[Leg, ...]
    duration_s: float
    dropout: tuple[float, float] | None   # [s] interval the detector misses the hand
    q_ranges: tuple[float, ...]

    def items(self) -> list[tuple[float, float, str, int]]:
        """(t0, t1, "contact"/"leg", index) sorted by time."""
        out = [(c.t0, c.t1, "contact", c.index) for c in self.contacts]
        out += [(g.t0, g.t1, "leg", i) for i, g in enumerate(self.legs)]
        return sorted(out)

    def joint_plan(self, j: int) -> mo.ArticulationPlan:
        """Joint ``j``'s value over the whole timeline (0 before its first contact)."""
        segs = tuple(s for c in self.contacts if c.joint == j for s in c.plan.segments)
        if not segs:
            return mo.rest_plan(0.0, self.duration_s)
        return mo.ArticulationPlan(segs)


def _unit(v: Array) -> Array:
    return v / np.linalg.norm(v)


def _cone(rng: np.random.Generator, outward: Array, spread: float = 0.7) -> Array:
    """A unit direction within ~50 deg of ``outward`` (never below 0.35 of it)."""
    while True:
        d = _unit(outward + spread * rng.standard_normal(3))
        if d @ outward >= 0.35:
            return d


def _turn(rng: np.random.Generator, deg: tuple[float, float] = TURN_DEG) -> Array:
    return _unit(rng.standard_normal(3)) * np.deg2rad(rng.uniform(*deg))


class _Builder:
    """Appends contacts and legs back to back (times in seconds from 0)."""

    def __init__(self, rng: np.random.Generator, part: Participant, scale: float) -> None:
        self.rng = rng
        self.part = part
        self.scale = scale
        self.t = 0.0
        self.contacts: list[Contact] = []
        self.legs: list[Leg] = []

    def contact(self, joint: int, plan: mo.ArticulationPlan, T_ph: Array,
                grasp_part: Array) -> int:
        k = len(self.contacts)
        self.contacts.append(Contact(k, joint, self.t, self.t + plan.duration_s,
                                     mo.shifted(plan, self.t), T_ph, grasp_part))
        self.t += plan.duration_s
        return k

    def leg(self, kind: str, duration: float, start: PoseRef, end: PoseRef, f0: FingerRef,
            f1: FingerRef, **kw: object) -> None:
        self.legs.append(Leg(kind, self.t, self.t + duration, start, end, f0, f1,
                             **kw))  # type: ignore[arg-type]
        self.t += duration

    def free_s(self, distance_m: float) -> float:
        return leg_duration(self.rng, distance_m, self.part.duration_factor * self.scale)

    def rest_s(self, bounds: tuple[float, float]) -> float:
        return float(self.rng.uniform(*bounds)) * self.scale

    def pregrasp(self, k: int) -> PoseRef:
        return PoseRef(k, "start", shift_h=self.rng.uniform(*PREGRASP_M) * PREGRASP_DIR_H,
                       turn=_turn(self.rng, (2.0, 6.0)))


def plan_timeline(rng: np.random.Generator, variant: str, gap: str | None, scene: Scene,
                  part: Participant, outward: Array, g_h: tuple[Array, ...],
                  open_posture: Array, relaxed_posture: Array,
                  duration_scale: float) -> Timeline:
    """Draw the timeline of ``variant`` (module docstring) on ``scene``.

    ``g_h``: each joint's grasp point in the hand frame; ``outward`` (3,) unit, frame ``o``.
    """
    b = _Builder(rng, part, duration_scale)
    presets = scene.presets
    q_ranges = tuple(
        1.0 if p.joint_type == "rigid" else
        p.range_nominal * part.range_factor * rng.uniform(1 - p.range_spread, 1 + p.range_spread)
        for p in presets)
    strokes = tuple(p.stroke_duration_s * part.duration_factor for p in presets)
    first_grasps = [grasp_pose(rng, p, part, g) for p, g in zip(presets, g_h, strict=True)]

    def full_plan(j: int) -> mo.ArticulationPlan:
        p = presets[j]
        if p.joint_type == "rigid":
            return mo.rest_plan(0.0, rng.uniform(*p.hold_s) * duration_scale)
        return mo.plan_articulation(rng, q_ranges[j], strokes[j], duration_scale)

    def two_plans(j: int, gap_rest: bool) -> tuple[mo.ArticulationPlan, mo.ArticulationPlan]:
        p = presets[j]
        if p.joint_type == "rigid":
            lo, hi = p.hold_s
            f = 0.5 if gap_rest else 1.0
            return (mo.rest_plan(0.0, rng.uniform(lo, hi) * f * duration_scale),
                    mo.rest_plan(0.0, rng.uniform(lo, hi) * f * duration_scale))
        r = q_ranges[j]
        mid = r * rng.uniform(0.4, 0.65)
        a = mo.plan_strokes(rng, 0.0, (mid,), r, strokes[j], first_rest_s=(0.3, 0.8),
                            last_rest_s=(0.2, 0.5), duration_scale=duration_scale)
        targets: tuple[float, ...] = (r,)
        if gap_rest and rng.random() < 0.5:
            targets = (r, r * (1.0 - rng.uniform(0.3, 1.0)))
        second = mo.plan_strokes(rng, mid, targets, r, strokes[j], first_rest_s=(0.2, 0.5),
                                 duration_scale=duration_scale)
        return a, second

    def regrasp(j: int, k_prev: int) -> tuple[Array, Array]:
        """Grasp pose and held point of a new grasp of joint j after contact k_prev."""
        prev = b.contacts[k_prev]
        first = next(c for c in b.contacts if c.joint == j)
        p = presets[j]
        if p.ratchet and p.joint_type == "revolute":
            q_all = np.zeros((len(presets), 1))
            q_all[j] = prev.plan.segments[-1].q1
            T_now = scene.part_poses(q_all)[j, 0]
            T_first = scene.part_poses(np.zeros((len(presets), 1)))[j, 0]
            back = np.linalg.inv(T_now) @ T_first
            T_ph = regrasp_pose(rng, back @ first.T_part_hand0, g_h[j])
            return T_ph, back[:3, :3] @ first.grasp_part + back[:3, 3]
        return regrasp_pose(rng, prev.T_part_hand0, g_h[j]), prev.grasp_part.copy()

    open_f = FingerRef(open_posture)
    relaxed_f = FingerRef(relaxed_posture)
    whole = variant != "cut"

    def reach(k: int) -> None:
        start = PoseRef(k, "start", shift_o=rng.uniform(*REACH_M) * _cone(rng, outward),
                        turn=_turn(rng))
        b.leg("rest", b.rest_s((0.3, 0.8)), start, start, relaxed_f, relaxed_f, still=True,
              anchor_end=True)
        pre = b.pregrasp(k)
        b.leg("reach", b.free_s(float(np.linalg.norm(start.shift_o))), start, pre, relaxed_f,
              open_f, finger_window=(0.0, 0.7), bump_fraction=0.15, bump_dir=_unit(
                  rng.standard_normal(3)))
        b.leg("closure", b.rest_s((0.25, 0.5)), pre, PoseRef(k, "start"), open_f,
              FingerRef(contact=k, at="start"), finger_window=(0.1, 1.0))

    def release(k: int, detected: bool = True, duration: float | None = None) -> PoseRef:
        lift = PoseRef(k, "end", shift_h=rng.uniform(*RELEASE_LIFT_M) * PREGRASP_DIR_H)
        b.leg("release", duration or b.rest_s((0.2, 0.4)), PoseRef(k, "end"), lift,
              FingerRef(contact=k, at="end"), open_f, finger_window=(0.0, 0.8),
              detected=detected)
        return lift

    def withdraw(k: int, lift: PoseRef) -> None:
        away = PoseRef(k, "end", shift_o=rng.uniform(*REACH_M) * _cone(rng, outward),
                       turn=_turn(rng))
        b.leg("withdraw", b.free_s(float(np.linalg.norm(away.shift_o))), lift, away, open_f,
              relaxed_f, bump_fraction=0.15, bump_dir=_unit(rng.standard_normal(3)))
        b.leg("rest", b.rest_s((0.3, 0.8)), away, away, relaxed_f, relaxed_f, still=True)

    def approach(k_next: int, via: PoseRef, distance: float, f_via: FingerRef,
                 detected: bool = True, durations: tuple[float, float] | None = None) -> None:
        pre = b.pregrasp(k_next)
        d_move, d_close = durations or (b.free_s(distance), b.rest_s((0.25, 0.5)))
        b.leg("transfer", d_move, via, pre, f_via, open_f, finger_window=(0.2, 1.0),
              bump_fraction=0.15, bump_dir=_unit(rng.standard_normal(3)), detected=detected)
        b.leg("closure", d_close, pre, PoseRef(k_next, "start"), open_f,
              FingerRef(contact=k_next, at="start"), finger_window=(0.1, 1.0),
              detected=detected)

    def handle_distance(j0: int, k0_plan: mo.ArticulationPlan, grasp0: Array, j1: int,
                        q1: float, grasp1: Array) -> float:
        """Nominal distance between the held points at the end of one contact and the start
        of the next."""
        qa = np.zeros((len(presets), 1))
        qa[j0] = k0_plan.segments[-1].q1
        qb = qa.copy()
        qb[j1] = q1
        Ta = scene.part_poses(qa)[j0, 0]
        Tb = scene.part_poses(qb)[j1, 0]
        return float(np.linalg.norm((Ta[:3, :3] @ grasp0 + Ta[:3, 3])
                                    - (Tb[:3, :3] @ grasp1 + Tb[:3, 3])))

    dropout = None
    if variant == "sequence":
        j0, j1 = 0, 1
        p0 = presets[0]
        plan0 = mo.plan_strokes(rng, 0.0, (q_ranges[0],), q_ranges[0], strokes[0],
                                first_rest_s=(0.3, 0.8), duration_scale=duration_scale) \
            if p0.joint_type != "rigid" else full_plan(0)
        plan1 = full_plan(j1)
        g0 = np.asarray(presets[j0].grasp, float)
        g1 = np.asarray(presets[j1].grasp, float)
        reach(0)
        b.contact(j0, plan0, first_grasps[j0], g0)
        lift = release(0)
        approach(1, lift, handle_distance(j0, plan0, g0, j1, 0.0, g1), open_f)
        b.contact(j1, plan1, first_grasps[j1], g1)
        withdraw(1, release(1))
    elif variant == "regrasp" or gap == "regrasp":
        plan_a, plan_b = two_plans(0, gap_rest=gap == "regrasp")
        g0 = np.asarray(presets[0].grasp, float)
        if whole:
            reach(0)
        b.contact(0, plan_a, first_grasps[0], g0)
        T_ph, grasp_b = regrasp(0, 0)
        if gap == "regrasp":
            g = rng.uniform(*GAP_S) * duration_scale
            lift = release(0, detected=False, duration=0.2 * g)
            away = PoseRef(0, "end", shift_o=(0.02 + 0.06 * g) * _cone(rng, outward),
                           turn=_turn(rng, (5.0, 20.0)))
            b.leg("away", 0.3 * g, lift, away, open_f, relaxed_f, detected=False)
            approach(1, away, 0.0, relaxed_f, detected=False, durations=(0.3 * g, 0.2 * g))
        else:
            lift = release(0)
            away = PoseRef(0, "end", shift_o=rng.uniform(*RETURN_M) * _cone(rng, outward),
                           turn=_turn(rng, (10.0, 30.0)))
            b.leg("return", b.free_s(float(np.linalg.norm(away.shift_o))), lift, away, open_f,
                  relaxed_f, bump_fraction=0.1, bump_dir=_unit(rng.standard_normal(3)))
            dist = float(np.linalg.norm(away.shift_o)) + handle_distance(
                0, plan_a, g0, 0, plan_a.segments[-1].q1, grasp_b)
            approach(1, away, dist, relaxed_f)
        b.contact(0, plan_b, T_ph, grasp_b)
        if whole:
            withdraw(1, release(1))
    else:
        plan = full_plan(0)
        if whole:
            reach(0)
        k = b.contact(0, plan, first_grasps[0], np.asarray(presets[0].grasp, float))
        if gap == "dropout":
            c = b.contacts[k]
            span = c.t1 - c.t0
            g = min(rng.uniform(*GAP_S) * duration_scale, 0.6 * span)
            centre = c.t0 + rng.uniform(0.25, 0.75) * span
            a0 = float(np.clip(centre - 0.5 * g, c.t0 + 0.1 * span, c.t1 - 0.1 * span - g))
            dropout = (a0, a0 + g)
        if whole:
            withdraw(k, release(k))
    return Timeline(tuple(b.contacts), tuple(b.legs), b.t, dropout, q_ranges)
