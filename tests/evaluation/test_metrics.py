"""Properties of the tangent error and its companion metrics (docs/evaluation.md#tangent-error)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from services.common.se3 import se3_exp
from services.evaluation.metrics import (
    JointEstimate,
    axis_angle_error,
    axis_line_distance,
    gt_path_samples,
    joint_twist,
    tangent_cosines,
    tangent_error,
    tangent_error_from_cosines,
    tangent_error_from_twists,
    tangent_errors_over_time,
    tangent_similarity,
    time_to_converge,
    time_to_converge_estimates,
    type_accuracy,
)


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def arc(centre: np.ndarray, axis: np.ndarray, radius: float, a0: float, a1: float,
        n: int = 50, axial: float = 0.0) -> np.ndarray:
    """Points on a circular arc about ``axis`` through ``centre`` from angle a0 to a1."""
    axis = unit(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = unit(np.cross(axis, helper))
    e2 = np.cross(axis, e1)
    a = np.linspace(a0, a1, n)
    return (centre + radius * (np.outer(np.cos(a), e1) + np.outer(np.sin(a), e2))
            + axial * axis)


vectors = st.tuples(*[st.floats(-1.0, 1.0) for _ in range(3)]).map(np.array).filter(
    lambda v: np.linalg.norm(v) > 0.1)


@settings(max_examples=40, deadline=None)
@given(a=vectors, b=vectors)
def test_prismatic_tangent_error_equals_axis_angle(a: np.ndarray, b: np.ndarray) -> None:
    gt = JointEstimate("prismatic", a, np.zeros(3))
    est = JointEstimate("prismatic", b, np.array([0.3, -0.2, 0.5]))
    pos = np.outer(np.linspace(0.0, 0.1, 20), unit(a)) + np.array([0.1, 0.0, 0.7])
    assert tangent_error(gt, est, pos) == pytest.approx(axis_angle_error(gt, est), abs=1e-7)
    assert 0.0 <= axis_angle_error(gt, est) <= math.pi / 2 + 1e-12


@settings(max_examples=40, deadline=None)
@given(axis=vectors, point=vectors, est_axis=vectors, est_point=vectors,
       scale=st.floats(0.01, 100.0), sign=st.sampled_from([-1.0, 1.0]))
def test_invariant_to_axis_sign_and_twist_scale(axis: np.ndarray, point: np.ndarray,
                                                est_axis: np.ndarray, est_point: np.ndarray,
                                                scale: float, sign: float) -> None:
    gt = JointEstimate("revolute", axis, point)
    pos = arc(gt.point, gt.axis, 0.08, 0.2, 1.4)
    est = JointEstimate("revolute", est_axis, est_point * 0.1 + gt.point)
    xg, xe = joint_twist(gt), joint_twist(est)
    # The "at least half negative" rule is sign-asymmetric only at an exact tie.
    assume(np.count_nonzero(tangent_cosines(xg, xe, pos) < 0) != 50)
    ref = tangent_error_from_twists(xg, xe, pos)[0]
    # arccos near 1 turns rounding (1e-16) into ~1e-8 rad, hence the tolerance.
    assert tangent_error_from_twists(xg, sign * scale * xe, pos)[0] == pytest.approx(ref, abs=1e-6)
    assert tangent_error_from_twists(sign * scale * xg, xe, pos)[0] == pytest.approx(ref,
                                                                                     abs=1e-6)
    flipped = JointEstimate("revolute", -est.axis, est.point)
    assert tangent_error(gt, flipped, pos) == pytest.approx(ref, abs=1e-6)
    assert 0.0 <= ref < math.pi


def test_exact_estimate_has_zero_error() -> None:
    gt = JointEstimate("revolute", np.array([0.0, 1.0, 0.0]), np.array([0.1, 0.0, 0.6]))
    pos = arc(gt.point, gt.axis, 0.05, 0.0, 2.0)
    assert tangent_error(gt, gt, pos) == pytest.approx(0.0, abs=1e-7)
    assert tangent_similarity(gt, gt, pos) == pytest.approx(1.0)


def test_rigid_or_missing_estimate_gives_half_pi() -> None:
    gt = JointEstimate("prismatic", np.array([1.0, 0.0, 0.0]), np.zeros(3))
    pos = np.outer(np.linspace(0, 0.1, 10), [1.0, 0.0, 0.0])
    assert tangent_error(gt, JointEstimate.rigid(), pos) == pytest.approx(math.pi / 2)
    assert tangent_error(gt, None, pos) == pytest.approx(math.pi / 2)
    assert tangent_similarity(gt, JointEstimate.rigid(), pos) == 0.0
    assert tangent_error_from_twists(joint_twist(gt), np.zeros(6), pos) == (math.pi / 2, 0.0)


def test_wrong_type_is_penalised_smoothly() -> None:
    # GT prismatic along x through the grasp; estimate revolute about z at distance R in -y:
    # its tangent along the path tends to x as R grows.
    gt = JointEstimate("prismatic", np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.7]))
    pos = np.array([0.0, 0.0, 0.7]) + np.outer(np.linspace(-0.05, 0.05, 30), [1.0, 0.0, 0.0])
    radii = np.geomspace(0.01, 100.0, 60)
    errs = np.array([
        tangent_error(gt, JointEstimate("revolute", np.array([0.0, 0.0, 1.0]),
                                        np.array([0.0, -r, 0.7])), pos)
        for r in radii])
    assert np.all(np.diff(errs) < 1e-12)          # monotone in the lever arm
    assert np.max(np.abs(np.diff(errs))) < 0.2    # no jumps
    assert errs[0] > np.deg2rad(45) and errs[-1] < np.deg2rad(0.05)
    # A revolute GT against prismatic estimates: also finite and between 0 and pi/2.
    gt_r = JointEstimate("revolute", np.array([0.0, 0.0, 1.0]), np.zeros(3))
    pos_r = arc(np.zeros(3), gt_r.axis, 0.1, 0.0, 1.0)
    e = tangent_error(gt_r, JointEstimate("prismatic", np.array([0.0, 1.0, 0.0]), np.zeros(3)),
                      pos_r)
    assert 0.0 < e < math.pi / 2


def test_revolute_error_mixes_direction_and_location() -> None:
    axis = np.array([0.0, 1.0, 0.0])
    c = np.array([0.05, 0.0, 0.6])
    gt = JointEstimate("revolute", axis, c)
    near = arc(c, axis, 0.03, 0.0, 1.5)
    far = arc(c, axis, 0.15, 0.0, 1.5)
    # Location error only: larger shift, larger error; longer lever arm, smaller error.
    shift = np.array([1.0, 0.0, 0.0])
    e1 = tangent_error(gt, JointEstimate("revolute", axis, c + 0.005 * shift), near)
    e2 = tangent_error(gt, JointEstimate("revolute", axis, c + 0.01 * shift), near)
    e3 = tangent_error(gt, JointEstimate("revolute", axis, c + 0.01 * shift), far)
    assert 0.0 < e1 < e2 and e3 < e2
    assert axis_angle_error(gt, JointEstimate("revolute", axis, c + 0.01 * shift)) == 0.0
    # Direction error only (axis through the same point): non-zero as well.
    tilted = unit(axis + np.array([0.0, 0.0, 0.1]))
    e4 = tangent_error(gt, JointEstimate("revolute", tilted, c), far)
    assert e4 > np.deg2rad(1.0)
    assert axis_line_distance(gt, JointEstimate("revolute", tilted, c)) == pytest.approx(0.0,
                                                                                         abs=1e-12)


def test_range_comes_from_the_demonstration_across_the_angle_wrap() -> None:
    axis = np.array([0.0, 0.0, 1.0])
    c = np.array([0.0, 0.0, 0.5])
    gt = JointEstimate("revolute", axis, c)
    rng = np.random.default_rng(0)
    pos = arc(c, axis, 0.1, 2.8, 3.6, n=40, axial=0.02)[rng.permutation(40)]
    xs = gt_path_samples(joint_twist(gt), pos, 100)
    # Samples run from the observed minimum to maximum angle (0.8 rad), not around the circle.
    ang = np.unwrap(np.arctan2(xs[:, 1], xs[:, 0]))
    assert ang[-1] - ang[0] == pytest.approx(0.8, abs=1e-9)
    np.testing.assert_allclose(np.linalg.norm(xs[:, :2], axis=1), 0.1, atol=1e-12)
    np.testing.assert_allclose(xs[:, 2], 0.52, atol=1e-12)
    # Prismatic: from the lowest to the highest projection, through the mean offset.
    gt_p = JointEstimate("prismatic", np.array([1.0, 0.0, 0.0]), np.zeros(3))
    pos_p = np.array([[0.3, 0.1, 0.5], [0.1, 0.0, 0.5], [0.2, -0.1, 0.6]])
    xs_p = gt_path_samples(joint_twist(gt_p), pos_p, 5)
    np.testing.assert_allclose(xs_p[0], [0.1, 0.0, 0.5333333333333333])
    np.testing.assert_allclose(xs_p[-1], [0.3, 0.0, 0.5333333333333333])


def test_path_samples_follow_the_exponential_map() -> None:
    rng = np.random.default_rng(5)
    xi = rng.normal(size=6)  # a general screw with non-zero pitch
    pos = rng.normal(size=(30, 3))
    xs = gt_path_samples(xi, pos, 7)
    wn = np.linalg.norm(xi[3:])
    a = xi[3:] / wn
    c = np.cross(xi[3:], xi[:3]) / wn**2
    r0, r1 = xs[0] - c, xs[1] - c
    r0 -= (r0 @ a) * a
    r1 -= (r1 @ a) * a
    step = np.arctan2(np.cross(r0, r1) @ a, r0 @ r1) % (2 * np.pi)
    # Uniform steps of the unit twist: x_i = exp(i * step * xi / |w|) x_0.
    for i in range(7):
        T = se3_exp(i * step * xi / wn)
        np.testing.assert_allclose(T[:3, :3] @ xs[0] + T[:3, 3], xs[i], atol=1e-12)


def test_exact_tie_follows_the_literal_rule() -> None:
    s = np.array([0.5, -0.5, 0.2, -0.9])
    err, sim = tangent_error_from_cosines(s)  # two of four negative -> flipped
    assert err == pytest.approx(np.mean(np.arccos(-s)))
    assert sim == pytest.approx(np.mean(-s))


def test_sign_flip_when_half_are_negative() -> None:
    gt = JointEstimate("prismatic", np.array([1.0, 0.0, 0.0]), np.zeros(3))
    pos = np.outer(np.linspace(0, 0.1, 10), [1.0, 0.0, 0.0])
    est = JointEstimate("prismatic", np.array([-1.0, 0.0, 0.0]), np.zeros(3))
    assert tangent_error(gt, est, pos) == pytest.approx(0.0, abs=1e-7)
    assert tangent_similarity(gt, est, pos) == pytest.approx(1.0)


def test_axis_angle_is_folded() -> None:
    a = JointEstimate("revolute", np.array([1.0, 0.0, 0.0]), np.zeros(3))
    b = JointEstimate("revolute", unit(np.array([-1.0, 0.1, 0.0])), np.zeros(3))
    assert axis_angle_error(a, b) == pytest.approx(math.atan(0.1))
    assert axis_angle_error(a, JointEstimate.rigid()) == pytest.approx(math.pi / 2)


def test_axis_line_distance() -> None:
    x = np.array([1.0, 0.0, 0.0])
    a = JointEstimate("revolute", x, np.array([0.0, 0.0, 0.0]))
    b = JointEstimate("revolute", -x, np.array([5.0, 0.03, 0.04]))
    assert axis_line_distance(a, b) == pytest.approx(0.05)
    # Skew lines: compare with a brute-force minimum over points on both lines.
    rng = np.random.default_rng(3)
    for _ in range(5):
        c = JointEstimate("revolute", rng.normal(size=3), rng.normal(size=3))
        d = JointEstimate("revolute", rng.normal(size=3), rng.normal(size=3))
        A = np.column_stack([c.axis, -d.axis])
        s, *_ = np.linalg.lstsq(A, d.point - c.point, rcond=None)
        brute = np.linalg.norm(c.point + s[0] * c.axis - d.point - s[1] * d.axis)
        assert axis_line_distance(c, d) == pytest.approx(brute, rel=1e-9)
    assert math.isnan(axis_line_distance(a, JointEstimate("prismatic", x, np.zeros(3))))


def test_type_accuracy() -> None:
    assert type_accuracy(["revolute", "prismatic"], ["revolute", None]) == 0.5
    with pytest.raises(ValueError):
        type_accuracy(["revolute"], [])


def test_time_to_converge() -> None:
    stamps = np.arange(6, dtype=np.int64) * 100_000_000 + 5
    big, small = np.deg2rad(30.0), np.deg2rad(5.0)
    assert time_to_converge(stamps, [big, small, big, small, small, small]) == pytest.approx(0.3)
    assert time_to_converge(stamps, [small] * 6) == 0.0
    assert time_to_converge(stamps, [small] * 5 + [big]) is None
    gt = JointEstimate("prismatic", np.array([1.0, 0.0, 0.0]), np.zeros(3))
    pos = np.outer(np.linspace(0, 0.1, 10), [1.0, 0.0, 0.0])
    good = JointEstimate("prismatic", unit(np.array([1.0, 0.05, 0.0])), np.zeros(3))
    bad = JointEstimate("prismatic", np.array([0.0, 1.0, 0.0]), np.zeros(3))
    ests = [None, bad, good, good, good, good]
    errs = tangent_errors_over_time(gt, ests, pos)
    assert errs[0] == pytest.approx(math.pi / 2) and errs[2] == pytest.approx(math.atan(0.05))
    assert time_to_converge_estimates(stamps, ests, gt, pos) == pytest.approx(0.2)


def test_joint_estimate_validation_and_twists() -> None:
    with pytest.raises(ValueError):
        JointEstimate("screw", np.ones(3), np.zeros(3))
    with pytest.raises(ValueError):
        JointEstimate("revolute", np.zeros(3), np.zeros(3))
    j = JointEstimate("revolute", np.array([0.0, 0.0, 2.0]), np.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(j.axis, [0.0, 0.0, 1.0])
    back = JointEstimate.from_twist(3.0 * j.to_twist())
    assert back.type == "revolute"
    np.testing.assert_allclose(back.axis, j.axis)
    np.testing.assert_allclose(back.point, [0.1, 0.2, 0.0], atol=1e-12)
    p = JointEstimate.from_twist(np.array([0.0, 2.0, 0.0, 0.0, 0.0, 1e-5]))
    assert p.type == "prismatic"
    assert JointEstimate.from_twist(np.zeros(6)).type == "rigid"
