"""Whole demonstrations, sequences, re-grasps, gaps and the free stream: their ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.se3 import se3_inverse, transform_points
from services.synthetic import postures as ps
from services.synthetic import splits
from services.synthetic.demonstration import Demonstration
from services.synthetic.generator import generate
from services.synthetic.household import SEQUENCE_PARTNERS


def _hand_grasp_point(d: Demonstration, segment: int) -> np.ndarray:
    """The hand-frame point (3,) that holds the handle in contact phase ``segment``."""
    tr = d.truth
    s = tr.segments[segment]
    held = tr.segment_grasp_points(segment)[0]
    return transform_points(se3_inverse(tr.T_camera_hand[s.start]), held[None])[0]


def _hand_to_handle(d: Demonstration, segment: int) -> np.ndarray:
    """Distance (N,) of the hand's holding point from the handle of ``segment``, every frame."""
    tr = d.truth
    s = tr.segments[segment]
    g_h = _hand_grasp_point(d, segment)
    hand = np.einsum("nij,j->ni", tr.T_camera_hand[:, :3, :3], g_h) + tr.T_camera_hand[:, :3, 3]
    T = tr.T_camera_parts[s.joint]
    held = np.einsum("nij,j->ni", T[:, :3, :3], s.grasp_part) + T[:, :3, 3]
    return np.linalg.norm(hand - held, axis=1)


def _check_phases(d: Demonstration) -> None:
    tr = d.truth
    contact = tr.phase == "contact"
    assert np.array_equal(contact, tr.segment_index >= 0)
    for i, s in enumerate(tr.segments):
        assert np.all(tr.segment_index[s.start:s.end + 1] == i)
        assert (s.start_ns, s.end_ns) == (d.stamps_ns[s.start], d.stamps_ns[s.end])
        assert s.onset_ns <= s.start_ns < s.onset_ns + 0.25e9
        assert s.end_ns <= s.release_ns < s.end_ns + 0.25e9
    assert contact.sum() == sum(s.end - s.start + 1 for s in tr.segments)
    # A part moves only while a hand holds it.
    for j in tr.joints:
        still = ~contact[1:] | ~contact[:-1]
        np.testing.assert_array_equal(np.diff(j.q)[still], 0.0)


@pytest.mark.parametrize("name", [*splits.OBJECTS_BY_SPLIT["paper"],
                                  *splits.OBJECTS_BY_SPLIT["household"]])
def test_whole_demonstration_reaches_grasps_manipulates_releases_withdraws(name: str) -> None:
    d = generate(name, 6, 2, variant="whole")
    tr = d.truth
    _check_phases(d)
    assert len(tr.segments) == 1
    s = tr.segments[0]
    assert tr.phase[0] == "free" and tr.phase[-1] == "free" and s.start > 15
    # Reach from 10-30 cm (holding point), then on the handle for the whole contact.
    dist = _hand_to_handle(d, 0)
    assert 0.08 <= dist[0] <= 0.34
    assert dist[s.start:s.end + 1].max() < 0.02
    assert dist[-1] > 0.07
    # Fingers open on the way in and out, closed in contact.
    ap = ps.aperture(tr.landmarks_hand)
    closed = ap[s.start:s.end + 1].mean()
    assert ap[:s.start].max() > closed + 0.02 and ap[s.end + 1:].max() > closed + 0.02
    assert ap[s.start:s.end + 1].max() < ap[:s.start].max()
    # The stream around the contact is the same kind of stream.
    assert d.present.all() and d.variant == "whole"


@pytest.mark.parametrize("name", sorted(SEQUENCE_PARTNERS))
def test_sequence_manipulates_two_joints_with_a_transfer(name: str) -> None:
    d = generate(name, 7, 1, variant="sequence")
    tr = d.truth
    _check_phases(d)
    assert [s.joint for s in tr.segments] == [0, 1] and len(tr.joints) == 2
    assert tr.joint is tr.joints[1]
    first, second = tr.segments
    assert first.end < second.start - 5  # free frames between: release, transfer, closure
    assert np.all(tr.phase[first.end + 1:second.start] == "free")
    # The lock is done before the second joint moves; the second never moved before.
    q0, q1 = tr.joints[0].q, tr.joints[1].q
    assert q0[first.end] > 0 and np.all(q0[first.end:] == q0[first.end])
    assert np.all(q1[:second.start] == 0.0) and np.abs(q1).max() > 0
    # Each contact's held point is on its own joint's path (the joint is described during it).
    for i, s in enumerate(tr.segments):
        j = tr.segment_joint(i)
        g = tr.segment_grasp_points(i)
        qs = j.q[s.start:s.end + 1]
        if j.type == "prismatic":
            np.testing.assert_allclose(g - g[0], np.outer(qs - qs[0], j.axis), atol=1e-9)
        else:
            rel = g - j.point
            radial = np.linalg.norm(rel - np.outer(rel @ j.axis, j.axis), axis=1)
            np.testing.assert_allclose(radial, radial[0], atol=1e-9)
        assert _hand_to_handle(d, i)[s.start:s.end + 1].max() < 0.02
    # A lock mounted on the moving part travels with it afterwards.
    partner = SEQUENCE_PARTNERS[name]
    T_lock = tr.T_camera_parts[0]
    moved = np.linalg.norm(T_lock[-1, :3, 3] - T_lock[first.end, :3, 3])
    assert (moved > 1e-3) == partner.mounted


@pytest.mark.parametrize("name", ["stove_knob", "valve", "kitchen_drawer", "hold_handle"])
def test_regrasp_is_two_strokes_of_one_joint(name: str) -> None:
    d = generate(name, 6, 5, variant="regrasp")
    tr = d.truth
    _check_phases(d)
    a, b = tr.segments
    assert a.joint == b.joint == 0 and len(tr.joints) == 1
    q = tr.joint.q
    assert q[b.start] == q[a.end]  # nothing moves between the strokes
    if tr.joint.type != "rigid":
        assert 0 < q[a.end] < q[b.start:].max()
    assert _hand_to_handle(d, 0)[a.end + 1:b.start].max() > 0.04  # the hand really let go
    ratchet = name in ("stove_knob", "valve")
    assert (not np.allclose(a.grasp_part, b.grasp_part)) == ratchet
    if ratchet:  # grasped again where the first grasp was, on the same circle
        j = tr.joint
        g_a, g_b = tr.segment_grasp_points(0)[0], tr.segment_grasp_points(1)[0]
        radial = [np.linalg.norm((g - j.point) - ((g - j.point) @ j.axis) * j.axis)
                  for g in (g_a, g_b)]
        assert radial[0] == pytest.approx(radial[1], abs=1e-9)
        assert np.linalg.norm(g_a - g_b) < 0.01


@pytest.mark.parametrize("variant", ["cut", "whole"])
def test_gaps(variant: str) -> None:
    d = generate("kitchen_drawer", 6, 3, variant=variant, gap="dropout")
    tr = d.truth
    assert len(tr.segments) == 1 and tr.gap == "dropout"
    missing = np.flatnonzero(~d.present)
    assert np.array_equal(missing, np.flatnonzero(tr.undetected))
    assert np.all(np.diff(missing) == 1)  # one interval
    gap_s = (d.stamps_ns[missing[-1] + 1] - d.stamps_ns[missing[0] - 1]) * 1e-9
    assert 0.3 <= gap_s <= 1.6
    assert np.all(tr.phase[missing] == "contact")
    assert np.isnan(d.points[missing]).all() and not d.score[missing].any()

    d = generate("cabinet_door", 7, 3, variant=variant, gap="regrasp")
    tr = d.truth
    _check_phases(d)
    a, b = tr.segments
    assert a.joint == b.joint
    between = np.arange(a.end + 1, b.start)
    assert np.array_equal(np.flatnonzero(tr.undetected), between)
    assert not d.present[between].any() and d.present[tr.phase == "contact"].all()
    assert 0.3 <= (b.onset_ns - a.release_ns) * 1e-9 <= 1.5 + 1e-6
    assert tr.joint.q[b.start] == tr.joint.q[a.end]


def test_new_variants_are_deterministic() -> None:
    for kw in ({"variant": "whole"}, {"variant": "sequence"}, {"gap": "regrasp"},
               {"idle_hand": "flipping"}):
        a = generate("box_lid", 4, 9, **kw)  # type: ignore[arg-type]
        b = generate("box_lid", 4, 9, **kw)  # type: ignore[arg-type]
        for name in ("stamps_ns", "points", "visibility", "pixels", "score", "labels"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        np.testing.assert_array_equal(a.truth.landmarks_true, b.truth.landmarks_true)
        c = generate("box_lid", 4, 10, **kw)  # type: ignore[arg-type]
        assert len(c) != len(a) or not np.array_equal(c.truth.landmarks_true,
                                                      a.truth.landmarks_true)


@pytest.mark.parametrize("mode", splits.IDLE_HAND_LABELS)
def test_idle_second_hand(mode: str) -> None:
    plain = generate("round_dial", 6, 1, variant="whole")
    d = generate("round_dial", 6, 1, variant="whole", idle_hand=mode)
    # The manipulating hand's stream is exactly the one without the idle hand.
    for name in ("stamps_ns", "points", "visibility", "pixels", "score", "present"):
        np.testing.assert_array_equal(getattr(d, name), getattr(plain, name))
    assert d.second is not None and d.truth.second_hand is not None
    sh = d.truth.second_hand
    # It never moves, stays away from the manipulating hand, and is detected every frame.
    np.testing.assert_array_equal(sh.T_camera_hand, np.broadcast_to(sh.T_camera_hand[0],
                                                                     sh.T_camera_hand.shape))
    np.testing.assert_array_equal(sh.landmarks_true, np.broadcast_to(sh.landmarks_true[0],
                                                                     sh.landmarks_true.shape))
    gap = np.linalg.norm(d.truth.landmarks_true[:, :, None] - sh.landmarks_true[:, None], axis=-1)
    assert gap.min() >= 0.12
    assert d.second.present.all()
    assert np.all(ps.chirality(sh.landmarks_hand[None]) == (1 if sh.side == "right" else -1))
    # Its score is sometimes the higher one.
    higher = (d.second.score > d.score).mean()
    assert higher > 0.05
    same = d.labels == d.second.labels
    if mode == "same":
        assert same.all() and np.all(d.labels == plain.labels)
    elif mode == "opposite":
        assert not same.any() and np.all(d.labels == plain.labels)
    else:
        assert 0.05 < same.mean() < 0.8
        assert 0.05 < (d.labels != plain.labels).mean() < 0.5
    # The frame's detections: both hands, highest score first, sources told apart.
    for i in (0, len(d) // 2):
        hands = d.detections(i)
        assert [h.score for h in hands] == sorted((h.score for h in hands), reverse=True)
        assert sorted(h.source for h in hands) == [0, 1]


def test_idle_hand_is_the_only_detection_during_a_dropout() -> None:
    d = generate("sash_window", 7, 0, gap="dropout", idle_hand="same")
    gone = np.flatnonzero(~d.present)
    assert len(gone) > 5
    assert [h.source for h in d.detections(int(gone[0]))] == [1]


def test_free_stream_never_touches_anything() -> None:
    d = generate("free", 6, 0)
    tr = d.truth
    duration = (d.stamps_ns[-1] - d.stamps_ns[0]) * 1e-9
    assert 59.8 <= duration <= 60.01
    assert tr.segments == () and np.all(tr.phase == "free") and np.all(tr.segment_index == -1)
    assert d.present.mean() > 0.95 and d.variant == "free"
    t = (d.stamps_ns - d.stamps_ns[0]) * 1e-9
    palm = tr.landmarks_true[:, [0, 5, 9, 13, 17]].mean(axis=1)
    speed = np.linalg.norm(np.diff(palm, axis=0), axis=1) / np.diff(t)
    assert np.ptp(palm, axis=0).max() > 0.2 and speed.max() > 0.3
    assert (speed < 0.05).mean() > 0.2  # resting (tremor only)
    ap = ps.aperture(tr.landmarks_hand)
    assert np.ptp(ap) > 0.02  # the fingers change posture
    with pytest.raises(ValueError, match="free stream"):
        generate("free", 6, 0, idle_hand="same")


def test_cut_to_segment_is_the_contact_of_the_same_demonstration() -> None:
    from services.synthetic.demonstration import cut_to_segment

    d = generate("cabinet_door", 6, 4, variant="sequence", idle_hand="same")
    for i, s in enumerate(d.truth.segments):
        c = cut_to_segment(d, i)
        rows = slice(s.start, s.end + 1)
        assert len(c) == s.end - s.start + 1 and c.variant == "cut"
        np.testing.assert_array_equal(c.points, d.points[rows])
        np.testing.assert_array_equal(c.stamps_ns, d.stamps_ns[rows])
        assert c.truth.joint.name == d.truth.segment_joint(i).name
        np.testing.assert_allclose(c.truth.grasp_points, d.truth.segment_grasp_points(i))
        np.testing.assert_allclose(c.truth.T_camera_hand, c.truth.T_camera_part
                                   @ c.truth.T_part_hand, atol=1e-9)
        assert np.all(c.truth.phase == "contact") and len(c.truth.segments) == 1
        assert c.second is not None and len(c.detections(0)) == 2
