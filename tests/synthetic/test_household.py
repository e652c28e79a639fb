"""The household split: every object generates with plausible ground truth; splits; left hands."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.se3 import se3_exp, se3_inverse, transform_points
from services.synthetic import postures as ps
from services.synthetic import splits
from services.synthetic.demonstration import Demonstration
from services.synthetic.generator import generate
from services.synthetic.household import HOUSEHOLD_OBJECTS, HOUSEHOLD_PRESETS

MIRROR = np.diag([-1.0, 1.0, 1.0])


@pytest.fixture(scope="module")
def demos() -> dict[str, Demonstration]:
    return {o: generate(o, 6, 0) for o in HOUSEHOLD_OBJECTS}


def _radius(demo: Demonstration) -> float:
    j = demo.truth.joint
    rel = demo.truth.grasp_points[0] - j.point
    return float(np.linalg.norm(rel - (rel @ j.axis) * j.axis))


def _stroke(demo: Demonstration) -> float:
    q = demo.truth.joint.q
    span = float(q.max() - q.min())
    return span * _radius(demo) if demo.truth.joint.type == "revolute" else span


@pytest.mark.parametrize("name", HOUSEHOLD_OBJECTS)
def test_truth_is_consistent(demos: dict[str, Demonstration], name: str) -> None:
    d = demos[name]
    tr = d.truth
    j = tr.joint
    assert j.type == HOUSEHOLD_PRESETS[name].joint_type
    assert j.q[0] == 0.0 and j.q.shape == (len(d),)
    np.testing.assert_allclose(tr.T_camera_part[0], tr.T_camera_object, atol=1e-12)
    for k in range(0, len(d), 7):
        np.testing.assert_allclose(tr.T_camera_part[k], se3_exp(j.q[k] * j.twist())
                                   @ tr.T_camera_part[0], atol=1e-9)
        np.testing.assert_allclose(tr.T_camera_hand[k], tr.T_camera_part[k] @ tr.T_part_hand[k],
                                   atol=1e-9)
        np.testing.assert_allclose(transform_points(tr.T_camera_hand[k], tr.landmarks_hand[k]),
                                   tr.landmarks_true[k], atol=1e-9)
    g = tr.grasp_points
    if j.type == "revolute":
        rel = g - j.point
        radial = np.linalg.norm(rel - np.outer(rel @ j.axis, j.axis), axis=1)
        np.testing.assert_allclose(radial, radial[0], atol=1e-9)
        np.testing.assert_allclose(rel @ j.axis, rel[0] @ j.axis, atol=1e-9)
    elif j.type == "prismatic":
        np.testing.assert_allclose(g, j.point + np.outer(j.q, j.axis), atol=1e-9)
    else:
        np.testing.assert_allclose(g, np.broadcast_to(g[0], g.shape), atol=1e-12)
        assert not j.axis.any()
    # The hand stays on the handle: its pose on the part only slips (and trembles).
    rel = se3_inverse(tr.T_part_hand[0])[None] @ tr.T_part_hand
    assert np.abs(rel[:, :3, 3]).max() < 0.02
    angles = np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert angles.max() < np.deg2rad(8.0)
    # Stream format as for the paper split.
    assert d.points.shape == (len(d), 21, 3) and d.points.dtype == np.float32
    assert np.all(np.diff(d.stamps_ns) > 0)
    assert d.present is not None and d.present.all()
    nan = np.isnan(d.points)
    assert np.array_equal(nan.any(axis=2), nan.all(axis=2))


@pytest.mark.parametrize("name", HOUSEHOLD_OBJECTS)
def test_radius_and_stroke_within_the_documented_ranges(name: str) -> None:
    p = HOUSEHOLD_PRESETS[name]
    for participant, seed in ((4, 0), (6, 1), (7, 2)):
        d = generate(name, participant, seed)
        if p.joint_type == "revolute":
            assert 0.005 - 1e-9 <= _radius(d) <= 0.40
        if p.joint_type != "rigid":
            assert 0.01 <= _stroke(d) <= 0.50


def test_the_split_covers_what_was_asked(demos: dict[str, Demonstration]) -> None:
    revolute = [d for d in demos.values() if d.truth.joint.type == "revolute"]
    radii = [_radius(d) for d in revolute]
    assert min(radii) <= 0.006 and max(radii) >= 0.35
    strokes = [_stroke(d) for d in demos.values() if d.truth.joint.type != "rigid"]
    assert min(strokes) <= 0.015 and max(strokes) >= 0.35
    assert {HOUSEHOLD_PRESETS[o].grasp_type for o in HOUSEHOLD_OBJECTS} >= {
        "power", "pinch", "hook"}
    assert {d.handedness for d in demos.values()} == {"left", "right"}
    assert set(splits.STILL_HOLDS) == {"hold_handle", "hold_knob"}

    def ray_cos(d: Demonstration) -> float:
        ray = d.truth.grasp_points[0] / np.linalg.norm(d.truth.grasp_points[0])
        return abs(float(d.truth.joint.axis @ ray))

    # Knobs and dials turn about an axis near the viewing direction.
    for o in ("stove_knob", "small_dial", "round_dial"):
        assert ray_cos(demos[o]) > np.cos(np.deg2rad(35.0))
    # Drawers move along the viewing direction (towards the camera).
    assert ray_cos(demos["kitchen_drawer"]) > 0.7
    d = demos["kitchen_drawer"]
    depth = d.truth.grasp_points[:, 2]
    assert depth[int(np.argmax(d.truth.joint.q))] < depth[0] - 0.2


def test_hand_speeds_reach_but_do_not_exceed_about_one_metre_per_second() -> None:
    fastest = 0.0
    for o in HOUSEHOLD_OBJECTS:
        for participant, variant in ((4, "cut"), (6, "cut"), (4, "whole")):
            d = generate(o, participant, 1, variant=variant)
            t = (d.stamps_ns - d.stamps_ns[0]) * 1e-9
            palm = d.truth.landmarks_true[:, [0, 5, 9, 13, 17]].mean(axis=1)
            speed = np.linalg.norm(np.diff(palm, axis=0), axis=1) / np.diff(t)
            fastest = max(fastest, float(speed.max()))
            assert speed.max() < 1.35, (o, variant)
    assert fastest > 0.8


def test_still_holds_tremble_but_do_not_move() -> None:
    for o in splits.STILL_HOLDS:
        d = generate(o, 6, 3)
        tr = d.truth
        assert tr.joint.type == "rigid" and not tr.joint.q.any()
        duration = (d.stamps_ns[-1] - d.stamps_ns[0]) * 1e-9
        assert 2.9 <= duration <= 5.1
        np.testing.assert_allclose(tr.T_camera_part, tr.T_camera_part[:1].repeat(len(d), 0))
        wrist = tr.T_camera_hand[:, :3, 3]
        wander = np.linalg.norm(wrist - wrist.mean(axis=0), axis=1)
        assert 1e-4 < wander.max() < 0.01


@pytest.mark.parametrize("name", ["cabinet_door", "kitchen_drawer", "stove_knob", "hold_knob"])
def test_left_hands_are_the_mirror_image(name: str) -> None:
    right = generate(name, 6, 4, hand="right", variant="whole")
    left = generate(name, 6, 4, hand="left", variant="whole")
    assert (right.handedness, left.handedness) == ("right", "left")
    assert left.truth.hand_side == "left" and set(left.labels.tolist()) == {"left"}
    np.testing.assert_allclose(left.truth.landmarks_true, right.truth.landmarks_true @ MIRROR,
                               atol=1e-9)
    np.testing.assert_allclose(left.truth.grasp_points, right.truth.grasp_points @ MIRROR,
                               atol=1e-9)
    jl, jr = left.truth.joint, right.truth.joint
    np.testing.assert_allclose(jl.point, MIRROR @ jr.point, atol=1e-12)
    sign = -1.0 if jr.type == "revolute" else 1.0  # an axis of rotation is a pseudovector
    np.testing.assert_allclose(jl.axis, sign * MIRROR @ jr.axis, atol=1e-12)
    for d in (left, right):  # the poses stay rigid transforms
        R = d.truth.T_camera_hand[:, :3, :3]
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    # Chirality from the landmarks alone, in contact (curled fingers).
    contact = right.truth.phase == "contact"
    assert np.all(ps.chirality(right.truth.landmarks_true[contact]) == 1)
    assert np.all(ps.chirality(left.truth.landmarks_true[contact]) == -1)
    assert np.all(ps.chirality(left.truth.landmarks_hand[contact]) == -1)


def test_partitions_are_disjoint_by_participant() -> None:
    for split in splits.SPLITS:
        tuning = set(splits.TUNING_BY_SPLIT[split])
        evaluation = set(splits.EVALUATION_BY_SPLIT[split])
        assert tuning and evaluation
        assert not {p for _, p in tuning} & {p for _, p in evaluation}
        assert {o for o, _ in evaluation} == set(splits.OBJECTS_BY_SPLIT[split])
    assert splits.TUNING_BY_SPLIT["paper"] == [
        (o, p) for o in ("valve", "tension_belt", "window_lock", "flap_latch") for p in (1, 2)]
    specs = splits.demo_specs("household", "evaluation", seeds=2, variant="sequence")
    assert {s.object_name for s in specs} == set(splits.SEQUENCE_OBJECTS["household"])
    assert len(specs) == 2 * 2 * len(splits.SEQUENCE_OBJECTS["household"])
    gaps = splits.demo_specs("household", "tuning", 1, "whole", "regrasp_gap")
    assert gaps and all(s.gap == "regrasp" for s in gaps)
    assert splits.demo_specs("paper", "evaluation", 1, "regrasp", "dropout") == []
    spec = splits.demo_specs("household", "tuning", 1, "cut", "idle_same")[0]
    assert generate(**spec.kwargs()).second is not None  # type: ignore[arg-type]
    assert len(splits.demo_specs("free", "evaluation", 3)) == 6


def test_bad_requests_name_what_is_wrong() -> None:
    with pytest.raises(ValueError, match="unknown object 'door'"):
        generate("door", 6)
    with pytest.raises(ValueError, match="no variant 'sequence'"):
        generate("desk_drawer", 6, variant="sequence")
    with pytest.raises(ValueError, match="gap applies"):
        generate("kitchen_drawer", 6, variant="regrasp", gap="dropout")
    with pytest.raises(ValueError, match="idle_hand"):
        generate("kitchen_drawer", 6, idle_hand="both")
    with pytest.raises(ValueError, match="hand must be"):
        generate("kitchen_drawer", 6, hand="third")
    assert splits.split_of("oven_door") == "household" and splits.split_of("key") == "paper"
    assert splits.variants_of("bolt") == ("cut", "whole", "sequence", "regrasp")
