"""Object presets, the hand model and the motion/timing model."""

from __future__ import annotations

import numpy as np
import pytest

from services.synthetic import hand as hd
from services.synthetic import motion as mo
from services.synthetic.objects import OBJECTS, PRESETS, preset


def _line_distance(point: np.ndarray, axis_point: np.ndarray, axis: np.ndarray) -> float:
    d = point - axis_point
    return float(np.linalg.norm(d - (d @ axis) * axis))


def test_ten_objects_four_prismatic_six_revolute() -> None:
    assert len(OBJECTS) == 10 and set(OBJECTS) == set(PRESETS)
    types = [PRESETS[o].joint_type for o in OBJECTS]
    assert types[:4] == ["prismatic"] * 4 and types[4:] == ["revolute"] * 6


@pytest.mark.parametrize("name", OBJECTS)
def test_preset_geometry(name: str) -> None:
    p = preset(name)
    R = p.hand_rotation_object()
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    xi = p.twist_object()
    assert np.linalg.norm(xi[3:]) == pytest.approx(1.0 if p.joint_type == "revolute" else 0.0)
    if p.joint_type == "prismatic":
        # The prismatic line passes through the grasp.
        assert _line_distance(np.array(p.grasp), np.array(p.point), np.array(p.axis)) < 1e-12


def test_key_axis_passes_near_the_grasp() -> None:
    k = preset("key")
    d = _line_distance(np.array(k.grasp), np.array(k.point), np.array(k.axis))
    assert 0.0 < d <= 0.012


def test_unknown_object_is_rejected() -> None:
    with pytest.raises(ValueError, match="unknown object"):
        preset("door")


def test_bone_lengths_follow_buchholz_and_stay_constant_while_flexing() -> None:
    part = hd.participant(2)
    hl = part.shape.hand_length_m
    rng = np.random.default_rng(0)
    t = np.arange(200) / 30.0
    angles = hd.flexion_trajectory(rng, hd.participant_posture(part, "power"), t,
                                   np.linspace(0, 1, 200), part.flex_amplitude_rad)
    lm = hd.landmarks_from_angles(part.shape, angles)
    assert lm.shape == (200, 21, 3)
    expected = {}
    for f, chain in enumerate(hd.CHAINS[1:]):
        for s in range(3):
            expected[(chain[s], chain[s + 1])] = hd.FINGER_SEGMENTS[f][s + 1] * hl
    for s in range(3):
        expected[(hd.CHAINS[0][s], hd.CHAINS[0][s + 1])] = hd.THUMB_SEGMENTS[s] * hl
    for (a, b), length in expected.items():
        np.testing.assert_allclose(np.linalg.norm(lm[:, b] - lm[:, a], axis=1), length,
                                   rtol=1e-12)
    # The hand is not rigid: fingertips move relative to the palm.
    assert np.ptp(lm[:, 8], axis=0).max() > 1e-3
    np.testing.assert_allclose(np.ptp(lm[:, 5], axis=0), 0.0, atol=1e-15)


def test_participants_are_deterministic_and_differ() -> None:
    a, b = hd.participant(1), hd.participant(1)
    assert a == b
    sizes = {round(hd.participant(i).shape.hand_length_m, 6) for i in (1, 2, 3)}
    assert len(sizes) == 3
    for i in range(1, 30):
        assert 0.165 <= hd.participant(i).shape.hand_length_m <= 0.21
    with pytest.raises(ValueError):
        hd.participant(0)


@pytest.mark.parametrize("grasp", ["pinch", "tripod", "key_pinch", "power"])
def test_thumb_reaches_its_contact_target(grasp: str) -> None:
    part = hd.participant(3)
    angles = hd.participant_posture(part, grasp)  # type: ignore[arg-type]
    lm = hd.landmarks_from_angles(part.shape, angles)
    target = hd.thumb_target(lm, grasp, part.shape)  # type: ignore[arg-type]
    assert np.linalg.norm(lm[4] - target) < 2e-3
    if grasp == "pinch":
        assert np.linalg.norm(lm[4] - lm[8]) < 0.025


def test_minimum_jerk_boundary_conditions() -> None:
    tau = np.array([0.0, 0.5, 1.0, -1.0, 2.0])
    np.testing.assert_allclose(mo.minimum_jerk(tau), [0.0, 0.5, 1.0, 0.0, 1.0])
    np.testing.assert_allclose(mo.minimum_jerk_rate(np.array([0.0, 1.0])), 0.0)
    assert mo.minimum_jerk_rate(np.array([0.5]))[0] == pytest.approx(1.875)


def test_plan_starts_at_rest_and_reaches_the_range() -> None:
    for seed in range(20):
        rng = np.random.default_rng(seed)
        plan = mo.plan_articulation(rng, 1.3, 1.5)
        t = np.linspace(0.0, plan.duration_s, 2000)
        q, dq = plan.evaluate(t)
        assert q[0] == 0.0 and dq[0] == 0.0
        assert q.max() == pytest.approx(1.3)
        assert np.all(q >= -1e-12)
        # Rests exist: at least 0.4 s at the start with q == 0.
        assert np.all(q[t < 0.4] == 0.0)
        # dq is the derivative of q.
        np.testing.assert_allclose(np.gradient(q, t), dq, atol=0.05)


def test_frame_timing_jitter_and_drops() -> None:
    rng = np.random.default_rng(1)
    ft = mo.sample_frame_times(rng, 2000.0)
    assert ft.frame_index[0] == 0 and ft.t[0] == 0.0
    assert np.all(np.diff(ft.frame_index) >= 1) and np.all(np.diff(ft.t) > 0)
    jitter = ft.t[1:] - ft.frame_index[1:] / mo.FRAME_RATE_HZ
    assert np.std(jitter) == pytest.approx(mo.JITTER_STD_S, rel=0.1)
    assert np.abs(jitter).max() <= mo.JITTER_CLIP_S + 1e-12
    dropped = 1.0 - len(ft.frame_index) / ft.n_nominal
    mean_burst = 0.5 * (mo.BURST_LENGTH[0] + mo.BURST_LENGTH[1])
    expected = mo.DROP_PROBABILITY + mo.BURST_PROBABILITY * mean_burst
    assert dropped == pytest.approx(expected, rel=0.25)
