"""The hand's own contact cues: the finger aperture, the contact detector and its config."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.common.protocol import pack_document, unpack_document
from services.common.se3 import se3_exp
from services.common.snapshot import SnapshotError
from services.kinematics.contact import (
    DISTAL_LANDMARKS,
    ApertureCue,
    ContactDetector,
    SegmentationConfig,
)
from services.synthetic import hand as hd
from services.synthetic import postures as ps
from services.synthetic.generator import generate


def _landmarks(posture: str, participant: int = 3) -> np.ndarray:
    part = hd.participant(participant)
    angles = (ps.free_posture(posture, part) if posture in ps.FREE_POSTURES
              else hd.participant_posture(part, posture))  # type: ignore[arg-type]
    return np.asarray(ps.landmarks_for_side(part.shape, angles, "right"))


def _aperture(points: np.ndarray) -> float:
    value = ApertureCue(1.0).update(points)
    assert value is not None
    return value


def test_the_aperture_of_an_open_hand_exceeds_a_grasps_whatever_the_pose_and_size() -> None:
    rng = np.random.default_rng(0)
    open_hand, relaxed, power = (_landmarks(p) for p in ("open", "relaxed", "power"))
    assert _aperture(open_hand) > _aperture(relaxed) > _aperture(power)
    assert _aperture(open_hand) > SegmentationConfig().open_aperture
    assert _aperture(power) < SegmentationConfig().closed_aperture
    for _ in range(5):
        T = se3_exp(np.concatenate([rng.normal(0, 0.5, 3), rng.normal(0, 1.0, 3)]))
        moved = 1.2 * open_hand @ T[:3, :3].T + T[:3, 3]  # another pose, a larger hand
        assert math.isclose(_aperture(moved), _aperture(open_hand), rel_tol=1e-9)


def test_a_lost_or_displaced_landmark_barely_moves_the_aperture() -> None:
    points = _landmarks("power")
    cue = ApertureCue(1.0)
    base = cue.update(points)
    assert base is not None
    lost = points.copy()
    lost[8] = np.nan  # the index tip is untracked: its last distance stands in
    assert cue.update(lost) == pytest.approx(base)
    displaced = points.copy()
    displaced[12] += [0.0, 0.0, 0.06]  # a depth error of 6 cm on one tip
    assert abs(ApertureCue(1.0).update(displaced) - base) < 0.03  # type: ignore[operator]


def test_no_aperture_until_every_distal_landmark_was_seen() -> None:
    points = _landmarks("relaxed")
    partial = points.copy()
    partial[list(DISTAL_LANDMARKS[:3])] = np.nan
    cue = ApertureCue(1.0)
    assert cue.update(partial) is None
    assert cue.update(points) is not None
    assert not ApertureCue.provided(np.zeros((21, 3)))
    assert not ApertureCue.provided(np.full((21, 3), np.nan))
    assert not ApertureCue.provided(None)
    assert ApertureCue.provided(points)


@pytest.mark.parametrize(("field", "value"), [
    ("aperture_smoothing", 0.0), ("closure_drop", -0.1), ("max_lag_s", 0.0),
    ("settle_frames", 0), ("opening_margin", -1.0), ("still_speed_m_per_s", math.nan),
    ("confirm_still_frames", 0), ("same_joint_fraction", 0.0)])
def test_the_config_names_a_bad_value(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        SegmentationConfig(**{field: value})


def _detector_frames(name: str, participant: int, variant: str):  # type: ignore[no-untyped-def]
    demo = generate(name, participant, 0, variant=variant)
    tr = demo.truth
    return demo, [(int(s), tr.T_camera_hand[i][:3, 3], tr.landmarks_true[i])
                  for i, s in enumerate(demo.stamps_ns)]


def test_the_detector_dates_onset_and_release_and_decides_within_the_lag() -> None:
    demo, frames = _detector_frames("cabinet_door", 6, "whole")
    config = SegmentationConfig()
    detector = ContactDetector(config)
    events = [(e, stamp) for stamp, position, points in frames
              if (e := detector.update(stamp, position, points)) is not None]
    truth = demo.truth.segments[0]
    assert [e.kind for e, _ in events] == ["onset", "release"]
    (onset, found_onset), (release, found_release) = events
    assert abs(onset.stamp_ns - truth.onset_ns) < 0.1e9
    assert abs(release.stamp_ns - truth.release_ns) < 0.1e9
    lag_ns = config.max_lag_s * 1e9
    assert 0 <= found_onset - onset.stamp_ns <= lag_ns
    assert 0 <= found_release - release.stamp_ns <= lag_ns
    assert not release.moving and not onset.initial


def test_a_restored_detector_decides_as_the_original() -> None:
    _, frames = _detector_frames("valve", 3, "whole")
    config = SegmentationConfig()
    original = ContactDetector(config)
    half = len(frames) // 2
    for stamp, position, points in frames[:half]:
        original.update(stamp, position, points)
    state = unpack_document(pack_document(original.to_state()))
    restored = ContactDetector.from_state(state, config)
    for stamp, position, points in frames[half:]:
        assert original.update(stamp, position, points) == restored.update(stamp, position,
                                                                           points)
    bad = dict(state, phase="holding")
    with pytest.raises(SnapshotError, match=r"detector\.phase"):
        ContactDetector.from_state(bad, config)
