"""generate(): determinism, ground-truth consistency, stream format, splits, caching."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.common.se3 import se3_exp, se3_inverse, transform_points
from services.synthetic.camera import project
from services.synthetic.generator import (
    CAMERA_DISTANCE_M,
    EVALUATION_SPLIT,
    OBJECTS,
    TUNING_SPLIT,
    Demonstration,
    generate,
    load_npz,
    save_npz,
)


@pytest.fixture(scope="module")
def demos() -> dict[str, Demonstration]:
    return {o: generate(o, 3, 0) for o in OBJECTS}


def _assert_same(a: Demonstration, b: Demonstration) -> None:
    for name in ("stamps_ns", "points", "visibility", "pixels", "score"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in ("T_camera_hand", "landmarks_true", "grasp_points", "frame_index", "occluded"):
        np.testing.assert_array_equal(getattr(a.truth, name), getattr(b.truth, name))
    np.testing.assert_array_equal(a.truth.joint.q, b.truth.joint.q)
    np.testing.assert_array_equal(a.truth.joint.axis, b.truth.joint.axis)


def test_deterministic_by_seed() -> None:
    a = generate("valve", 1, seed=7)
    b = generate("valve", 1, seed=7)
    _assert_same(a, b)
    c = generate("valve", 1, seed=8)
    assert len(c) != len(a) or not np.array_equal(c.pixels, a.pixels)
    d = generate("valve", 2, seed=7)
    assert not np.array_equal(d.truth.landmarks_hand[0], a.truth.landmarks_hand[0])


@pytest.mark.parametrize("name", OBJECTS)
def test_truth_is_consistent(demos: dict[str, Demonstration], name: str) -> None:
    d = demos[name]
    tr = d.truth
    n = len(d)
    j = tr.joint
    xi = j.twist()
    assert np.linalg.norm(j.axis) == pytest.approx(1.0, abs=1e-12)
    assert j.q[0] == 0.0 and j.q.shape == (n,)
    np.testing.assert_allclose(tr.T_camera_part[0], tr.T_camera_object, atol=1e-12)
    for k in range(n):
        # The part moves exactly by the joint motion ...
        np.testing.assert_allclose(tr.T_camera_part[k],
                                   se3_exp((j.q[k] - j.q[0]) * xi) @ tr.T_camera_part[0],
                                   atol=1e-9)
        # ... the hand pose is the part pose times the (slipping) grasp ...
        np.testing.assert_allclose(tr.T_camera_hand[k] @ se3_inverse(tr.T_part_hand[k]),
                                   tr.T_camera_part[k], atol=1e-9)
        # ... and the noise-free landmarks are the hand-frame landmarks in the camera frame.
        np.testing.assert_allclose(transform_points(tr.T_camera_hand[k], tr.landmarks_hand[k]),
                                   tr.landmarks_true[k], atol=1e-9)
    # The grasp point moves on the joint path.
    g = tr.grasp_points
    if j.type == "revolute":
        assert abs(j.point @ j.axis) < 1e-9  # closest point to the camera origin
        rel = g - j.point
        radial = rel - np.outer(rel @ j.axis, j.axis)
        np.testing.assert_allclose(np.linalg.norm(radial, axis=1),
                                   np.linalg.norm(radial[0]), atol=1e-9)
        np.testing.assert_allclose(rel @ j.axis, rel[0] @ j.axis, atol=1e-9)
    else:
        np.testing.assert_allclose(g[0], j.point, atol=1e-12)
        np.testing.assert_allclose(g, j.point + np.outer(j.q, j.axis), atol=1e-9)


@pytest.mark.parametrize("name", OBJECTS)
def test_slip_is_small(demos: dict[str, Demonstration], name: str) -> None:
    tr = demos[name].truth
    rel = se3_inverse(tr.T_part_hand[0])[None] @ tr.T_part_hand
    assert np.abs(rel[:, :3, 3]).max() < 0.02
    angles = np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert angles.max() < np.deg2rad(8.0)


@pytest.mark.parametrize("name", OBJECTS)
def test_stream_format(demos: dict[str, Demonstration], name: str) -> None:
    d = demos[name]
    n = len(d)
    assert n > 30
    assert d.stamps_ns.dtype == np.int64 and np.all(np.diff(d.stamps_ns) > 0)
    assert d.points.shape == (n, 21, 3) and d.points.dtype == np.float32
    assert d.pixels.shape == (n, 21, 2) and d.pixels.dtype == np.float32
    assert d.visibility.shape == (n, 21) and d.visibility.dtype == np.float32
    assert d.score.shape == (n,) and d.score.dtype == np.float32
    assert np.all((d.visibility >= 0) & (d.visibility <= 1))
    assert np.all((d.score >= 0) & (d.score <= 1))
    assert d.handedness == "right"
    assert d.truth.landmarks_true.dtype == np.float64
    assert d.truth.T_camera_hand.shape == (n, 4, 4)
    # Frames are stamped on the 30 Hz grid with jitter, with gaps where frames were dropped.
    dt_ns = (d.stamps_ns - d.stamps_ns[0]) - d.truth.frame_index * (1e9 / 30.0)
    assert np.abs(dt_ns).max() <= 3.0e6 + 1
    # NaN points exactly where the detector had no valid depth; whole rows.
    nan = np.isnan(d.points)
    assert np.array_equal(nan.any(axis=2), nan.all(axis=2))
    assert np.all(nan[d.truth.missing])
    dist = np.linalg.norm(d.truth.T_camera_object[:3, 3])
    assert CAMERA_DISTANCE_M[0] - 1e-9 <= dist <= CAMERA_DISTANCE_M[1] + 1e-9
    px = project(d.truth.landmarks_true, d.intrinsics)
    inside = ((px[..., 0] >= 0) & (px[..., 0] < 1280) & (px[..., 1] >= 0) & (px[..., 1] < 720))
    assert inside.mean() > 0.95


def test_duration_scale_stretches_the_demonstration() -> None:
    a = generate("key", 1, 3)
    b = generate("key", 1, 3, duration_scale=2.0)
    assert len(b) > 1.6 * len(a)
    assert b.truth.joint.q.max() == pytest.approx(a.truth.joint.q.max())
    with pytest.raises(ValueError):
        generate("key", 1, 3, duration_scale=0.0)


def test_splits_follow_the_paper() -> None:
    assert sorted(TUNING_SPLIT) == sorted(
        (o, p) for o in ("valve", "tension_belt", "window_lock", "flap_latch") for p in (1, 2))
    assert [(o, 3) for o in OBJECTS] == EVALUATION_SPLIT
    assert not set(TUNING_SPLIT) & set(EVALUATION_SPLIT)


def test_npz_round_trip(tmp_path: Path) -> None:
    d = generate("bolt", 2, 5)
    path = tmp_path / "bolt.npz"
    save_npz(d, path)
    e = load_npz(path)
    assert (e.object_name, e.participant, e.seed, e.handedness) == ("bolt", 2, 5, "right")
    assert e.intrinsics == d.intrinsics
    assert e.truth.joint.type == d.truth.joint.type
    _assert_same(d, e)
    np.testing.assert_array_equal(e.truth.T_part_hand, d.truth.T_part_hand)
