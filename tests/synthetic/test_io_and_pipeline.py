"""Extended demonstrations survive an npz round trip and run through the in-process pipeline."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.evaluation.pipeline import run_pipeline
from services.synthetic.demonstration import Demonstration
from services.synthetic.generator import generate, load_npz, save_npz


def _assert_same(a: Demonstration, b: Demonstration) -> None:
    for name in ("stamps_ns", "points", "visibility", "pixels", "score", "present", "labels"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in ("T_camera_hand", "T_camera_parts", "landmarks_true", "grasp_points", "phase",
                 "segment_index", "undetected", "finger_angles"):
        np.testing.assert_array_equal(getattr(a.truth, name), getattr(b.truth, name))
    assert [j.name for j in a.truth.joints] == [j.name for j in b.truth.joints]
    for ja, jb in zip(a.truth.joints, b.truth.joints, strict=True):
        assert ja.type == jb.type
        np.testing.assert_array_equal(ja.q, jb.q)
        np.testing.assert_array_equal(ja.axis, jb.axis)
    assert b.truth.joint is b.truth.joints[a.truth.joints.index(a.truth.joint)]
    for sa, sb in zip(a.truth.segments, b.truth.segments, strict=True):
        assert (sa.joint, sa.start, sa.end, sa.onset_ns, sa.release_ns) == (
            sb.joint, sb.start, sb.end, sb.onset_ns, sb.release_ns)
        np.testing.assert_array_equal(sa.grasp_part, sb.grasp_part)
    assert (a.variant, a.handedness, a.truth.hand_side, a.truth.gap) == (
        b.variant, b.handedness, b.truth.hand_side, b.truth.gap)


def test_npz_round_trip_of_a_sequence_with_an_idle_hand(tmp_path: Path) -> None:
    d = generate("cabinet_door", 7, 3, variant="sequence", idle_hand="flipping")
    save_npz(d, tmp_path / "seq.npz")
    e = load_npz(tmp_path / "seq.npz")
    _assert_same(d, e)
    assert e.second is not None and d.second is not None
    np.testing.assert_array_equal(e.second.points, d.second.points)
    np.testing.assert_array_equal(e.second.labels, d.second.labels)
    assert e.truth.second_hand is not None and d.truth.second_hand is not None
    assert e.truth.second_hand.label_mode == "flipping"
    np.testing.assert_array_equal(e.truth.second_hand.T_camera_hand,
                                  d.truth.second_hand.T_camera_hand)


def test_npz_round_trip_of_a_gap_and_a_paper_cut(tmp_path: Path) -> None:
    for i, d in enumerate((generate("sash_window", 4, 0, gap="regrasp"), generate("key", 3, 1))):
        save_npz(d, tmp_path / f"{i}.npz")
        e = load_npz(tmp_path / f"{i}.npz")
        _assert_same(d, e)
        assert e.second is None


def test_pipeline_runs_on_a_household_demonstration() -> None:
    # Only that the estimators accept the stream; accuracy is the evaluation's business.
    d = generate("kitchen_drawer", 6, 0)
    result = run_pipeline(d)
    assert len(result.history) == len(d)
    assert result.final.type in ("unknown", "rigid", "prismatic", "revolute", "disconnected")
    assert result.final.updates > 0
