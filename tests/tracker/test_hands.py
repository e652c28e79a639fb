"""The manipulating hand (hands.py and HandTracker's choice), body epochs, covariance guards."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from services.common.protocol import HandBody, ProtocolError, encode_array
from services.common.se3 import se3_exp
from services.evaluation.metrics import axis_angle_error
from services.evaluation.pipeline import demo_tangent_error_deg, joint_estimate, run_pipeline
from services.synthetic.generator import generate
from services.tracker.config import TrackerConfig
from services.tracker.covariance import guarded_cholesky, is_psd, psd_repaired
from services.tracker.hands import rigid_displacement, robust_centre
from services.tracker.service import body_message
from services.tracker.tracker import HandBodyEstimate, HandObservation, HandTracker
from tests.common import samples
from tests.tracker import handgen as hg

NOISE_M = 0.003
T_A = se3_exp(np.array([0.1, -0.05, 0.6, 0.4, -0.3, 0.2]))  # the manipulating hand's rest pose
T_B = se3_exp(np.array([-0.25, 0.1, 0.7, -0.2, 0.5, 0.1]))  # the second hand's, 38 cm away
TURN = hg.revolute_twist(np.array([0.05, 0.12, 0.6]), np.array([0.1, 1.0, 0.2]))
SWAY = hg.revolute_twist(np.array([-0.25, 0.1, 0.7]), np.array([1.0, 0.2, 0.1]))


def turning(start_s: float, end_s: float) -> object:
    """1 rad about TURN, smoothly between ``start_s`` and ``end_s``; at rest before and after."""
    return lambda t: se3_exp(hg.smoothstep((t - start_s) / (end_s - start_s)) * TURN) @ T_A


def swaying(start_s: float) -> object:
    """The second hand: at rest, then swaying +-0.5 rad about SWAY from ``start_s`` on."""
    return lambda t: se3_exp(0.5 * math.sin(2.0 * max(t - start_s, 0.0)) * SWAY) @ T_B


def run_two(tracker: HandTracker, hand_a: object, hand_b: object | None, duration_s: float,
            labels: str = "same", seed: int = 3) -> list[HandBodyEstimate]:
    """Every estimate (held-back frames included, in order) of a run with the manipulating hand
    ``hand_a`` (t -> pose) and, unless None, the second hand ``hand_b``. ``labels``: "same"
    (both "right"), "opposite", or "flipping" (random per frame); the second hand scores higher."""
    rng = np.random.default_rng(seed)
    labelling = np.random.default_rng(seed + 100)
    out: list[HandBodyEstimate] = []
    for stamp in hg.Scenario(lambda t: T_A, duration_s).stamps():
        t = hg.Scenario.time_of(stamp)
        label_a, label_b = "right", "right" if labels == "same" else "left"
        if labels == "flipping":
            label_a, label_b = (str(x) for x in labelling.choice(["left", "right"], size=2))
        hands = [hg.observe(hand_a(t), rng, NOISE_M, handedness=label_a, score=0.7)]  # type: ignore[operator]
        if hand_b is not None:
            noise = np.random.default_rng(seed + 7 + stamp % 1000)  # B's noise: its own stream
            hands.insert(0, hg.observe(hand_b(t), noise, NOISE_M, handedness=label_b,  # type: ignore[operator]
                                       score=0.95))
        result = tracker.step(stamp, hands)
        out += [e for e in (*result.replayed, result.estimate) if e is not None]
    return out


def assert_same_estimates(a: list[HandBodyEstimate], b: list[HandBodyEstimate]) -> None:
    assert [e.stamp_ns for e in a] == [e.stamp_ns for e in b]
    for x, y in zip(a, b, strict=True):
        assert x.initialized == y.initialized and x.motion_model == y.motion_model
        # The same operations on the same inputs (the other hand's filters are separate rows).
        np.testing.assert_array_equal(x.pose, y.pose)
        np.testing.assert_array_equal(x.covariance, y.covariance)


@pytest.mark.parametrize("labels", ["same", "opposite", "flipping"])
def test_an_idle_second_hand_changes_nothing_whatever_its_labels(labels: str) -> None:
    """A second hand resting in view, scoring higher than the manipulating one, labelled the
    same, the opposite or flipping: the tracker follows the hand that moves, by position, and
    publishes exactly the estimates it would without the second hand (the frames it held back
    while choosing come late, in order)."""
    alone = run_two(HandTracker(TrackerConfig()), turning(1.5, 3.5), None, 5.0)
    tracker = HandTracker(TrackerConfig())
    both = run_two(tracker, turning(1.5, 3.5), lambda t: T_B, 5.0, labels)
    assert_same_estimates(alone, both)
    assert tracker.skipped["choosing_hand"] > 0  # it did wait for the first motion
    assert "second_hand_moving" not in tracker.notes and tracker.hand_switches == 0


def test_a_second_hand_moving_too_is_reported_and_ignored() -> None:
    """Both hands move (two hands on two parts: out of scope): the body stays on the hand it
    follows, unchanged, and every such frame is counted."""
    alone = run_two(HandTracker(TrackerConfig()), turning(1.0, 4.0), None, 4.5)
    tracker = HandTracker(TrackerConfig())
    both = run_two(tracker, turning(1.0, 4.0), swaying(3.0), 4.5)
    assert_same_estimates(alone, both)
    assert tracker.notes["second_hand_moving"] > 10 and tracker.hand_switches == 0


def test_the_body_moves_to_the_hand_that_manipulates_next() -> None:
    """The first hand turns, then rests; the second starts manipulating: once the first has not
    moved for hand_switch_idle_s and the second moved hand_switch_moves times, the body follows
    the second hand, in a new body frame (a new epoch), and says so."""
    tracker = HandTracker(TrackerConfig())
    estimates = run_two(tracker, turning(1.5, 3.0), swaying(4.5), 9.0)
    assert tracker.hand_switches == 1 and tracker.notes["hand_switched"] == 1
    epochs = [e.body_epoch for e in estimates if e.initialized]
    assert epochs[0] == 0 and epochs[-1] == 1 and sorted(epochs) == epochs
    last = estimates[-1]
    # Its landmarks are the second hand's now (filtered positions, within the noise).
    b_points = hg.transform_points(swaying(4.5)(9.0), hg.HAND)  # type: ignore[operator]
    seen = np.isfinite(last.landmark_points).all(axis=1)
    assert np.median(np.linalg.norm(last.landmark_points[seen] - b_points[seen], axis=1)) < 0.02


def test_one_hand_reported_twice_is_one_hand() -> None:
    """Two detections of one hand (the detector's duplicate): the second is rejected, and no
    second hand is waited for."""
    tracker = HandTracker(TrackerConfig())
    obs = hg.observe(T_A)
    for k in range(6):
        result = tracker.step(1_000_000_000 + k * hg.FRAME_NS,
                              [obs, dataclasses.replace(obs, handedness="left", score=0.5)])
        assert result.rejected == ("duplicate_hand",) and result.reason is None
    assert result.estimate is not None and result.estimate.initialized


@pytest.mark.parametrize(("obj", "participant"), [
    pytest.param("chain_lock", 3, marks=pytest.mark.xfail(
        strict=True, reason="the tracker waits 1.9 s (56 frames) for one of two still hands to "
                            "move; the bodies it then replays had no kinematic prior (kinematics "
                            "had not seen them), while alone the hand's bodies use it from body "
                            "40: 2.5 vs 3.6 deg tangent error, final axes 5.2 deg apart (with "
                            "the prior off they are identical: the test below)")),
    ("window_lock", 2)])
def test_generated_idle_hands_leave_the_estimate_within_a_degree(obj: str,
                                                                 participant: int) -> None:
    """The generator's idle second hand (the other hand or a second person's, resting in view,
    often scoring higher) with swapped, equal and flipping labels: the final joint is within
    1 deg of the same demonstration without it (tracker -> kinematics, the evaluation's
    pipeline, which feeds every detection)."""
    base_demo = generate(obj, participant, 0)
    base = run_pipeline(base_demo).final
    for mode in ("opposite", "same", "flipping"):
        demo = generate(obj, participant, 0, idle_hand=mode)
        assert demo.second is not None and len(demo.detections(0)) == 2
        final = run_pipeline(demo).final
        assert final.type == base.type
        angle = math.degrees(axis_angle_error(joint_estimate(base), joint_estimate(final)))
        assert angle < 1.0
        assert abs(demo_tangent_error_deg(final, demo)
                   - demo_tangent_error_deg(base, base_demo)) < 1.0


@pytest.mark.parametrize("mode", ["same", "flipping"])
def test_without_the_kinematic_prior_an_idle_hand_changes_nothing(mode: str) -> None:
    """What the idle hand can change at all is the hand choice's wait (bodies replayed without a
    kinematic prior, see the xfail above): with the kinematic motion model off, the final model
    with an idle hand is the one without it, to the last bit."""
    from services.evaluation.pipeline import no_kinematic_prior_config

    config = no_kinematic_prior_config()
    alone = run_pipeline(generate("chain_lock", 3, 0), config).final
    beside = run_pipeline(generate("chain_lock", 3, 0, idle_hand=mode), config).final
    assert beside.type == alone.type == "prismatic"
    assert beside.updates == alone.updates
    assert np.array_equal(beside.prismatic.axis, alone.prismatic.axis)  # type: ignore[union-attr]


# --- identity primitives ---------------------------------------------------------------------------

def test_robust_centre_and_rigid_displacement() -> None:
    points = hg.transform_points(T_A, hg.HAND)
    spoiled = points.copy()
    spoiled[[3, 8]] += [0.0, 0.0, 0.4]  # two depth outliers
    spoiled[12] = np.nan
    centre = robust_centre(spoiled)
    assert centre is not None
    assert np.linalg.norm(centre - np.median(points, axis=0)) < 0.01
    assert robust_centre(np.full((21, 3), np.nan)) is None
    moved = hg.transform_points(se3_exp(np.array([0.03, 0.0, 0.0, 0.0, 0.0, 0.0])), spoiled)
    d = rigid_displacement(spoiled, moved)
    assert d is not None and d == pytest.approx(0.03, abs=1e-9)  # outliers trimmed, exact
    assert rigid_displacement(spoiled, spoiled) == pytest.approx(0.0, abs=1e-12)
    few = np.full((21, 3), np.nan)
    few[:5] = points[:5]
    assert rigid_displacement(few, few) is None


# --- body epochs -------------------------------------------------------------------------------------

def test_body_epoch_changes_exactly_with_a_new_body_frame() -> None:
    obs = hg.observe(T_A)
    tracker = HandTracker(TrackerConfig(reacquire_body_frame=False))
    stamp = 1_000_000_000

    def feed(n: int, hands: list[HandObservation]) -> HandBodyEstimate | None:
        nonlocal stamp
        est = None
        for _ in range(n):
            est = tracker.step(stamp, hands).estimate or est
            stamp += hg.FRAME_NS
        return est

    first = feed(10, [obs])
    assert first is not None and first.initialized and first.body_epoch == 0
    feed(20, [])  # gone for 0.67 s: the body is dropped
    again = feed(10, [obs])
    assert again is not None and again.initialized and again.body_epoch == 1
    tracker.reset()  # a reset's next body frame is a new one too: the epoch survives reset
    stamp = 1_000_000_000
    after = feed(10, [obs])
    assert after is not None and after.body_epoch == 2
    # Re-acquired body frames keep their epoch, also across a restart with the remembered model.
    keeper = HandTracker(TrackerConfig())
    assert keeper.remember_body("camera", hg.HAND - hg.HAND[1:].mean(axis=0), body_epoch=7)
    assert not keeper.remember_body("camera", hg.HAND, body_epoch=-1)
    tracker = keeper
    stamp = 1_000_000_000
    est = feed(10, [obs])
    assert est is not None and keeper.reacquisitions == 1 and est.body_epoch == 7


def wire_map(doc: dict[str, object]) -> dict[str, object]:
    """A message dict as it is on the wire (arrays as codec maps)."""
    return {k: wire_map(v) if isinstance(v, dict)  # type: ignore[arg-type]
            else encode_array(v) if isinstance(v, np.ndarray) else v for k, v in doc.items()}


def test_body_epoch_on_the_wire_is_additive() -> None:
    body = samples.hand_body()
    assert body.body_epoch == 0
    epoch = dataclasses.replace(body, body_epoch=5)
    assert HandBody.from_msgpack(epoch.to_msgpack()).body_epoch == 5
    doc = wire_map(body.to_dict())
    del doc["body_epoch"]  # an older tracker's message
    old = HandBody.from_obj(doc)
    assert old.body_epoch == 0
    for bad in (-1, "1", 1.5, True):
        doc["body_epoch"] = bad
        with pytest.raises(ProtocolError, match="body_epoch"):
            HandBody.from_obj(doc)
    tracker = HandTracker(TrackerConfig())
    for k in range(6):
        est = tracker.step(1_000_000_000 + k * hg.FRAME_NS, [hg.observe(T_A)]).estimate
    assert est is not None
    assert body_message(dataclasses.replace(est, body_epoch=3), seq=1).body_epoch == 3


# --- covariance guards -------------------------------------------------------------------------------

def test_covariance_guards() -> None:
    rng = np.random.default_rng(1)
    A = rng.normal(size=(12, 12))
    P = A @ A.T + 1e-3 * np.eye(12)
    assert is_psd(P) and is_psd(np.zeros((6, 6)) + 1e-300 * np.eye(6))
    w, V = np.linalg.eigh(P)
    w[0] = -1e-6 * w[-1]
    bad = (V * w) @ V.T
    bad = 0.5 * (bad + bad.T)
    assert not is_psd(bad)
    for poison in (np.nan, np.inf):
        spoiled = P.copy()
        spoiled[7, 2] = spoiled[2, 7] = poison
        assert not is_psd(spoiled) and psd_repaired(spoiled) is None
        assert guarded_cholesky(spoiled) is None
    fixed = psd_repaired(bad)
    assert fixed is not None and is_psd(fixed) and np.linalg.eigvalsh(fixed).min() > 0.0
    np.testing.assert_allclose(fixed, bad, atol=2e-6 * w[-1])  # only the broken eigenvalue moved
    L, repaired = guarded_cholesky(P)  # type: ignore[misc]
    assert not repaired
    np.testing.assert_allclose(L @ L.T, P, rtol=1e-12, atol=1e-12 * w[-1])
    result = guarded_cholesky(bad)
    assert result is not None and result[1]


def test_a_flood_of_frames_microseconds_apart_never_publishes_a_bad_covariance() -> None:
    """Issue 13: 5,000 valid frames per second made merge_pose raise and a negative variance go
    out. Frames 0.2 ms apart (process noise ~1e-2 of a 30 Hz frame's), noisy, with outliers:
    every published covariance is positive semi-definite, and nothing raises."""
    rng = np.random.default_rng(11)
    tracker = HandTracker(TrackerConfig())
    published = 0
    for k in range(1500):
        t = k * 2e-4
        T = se3_exp(0.3 * math.sin(3.0 * t) * TURN) @ T_A
        obs = hg.observe(T, rng, NOISE_M)
        if k % 7 == 0:
            obs, _ = hg.with_outliers(obs, rng, 0.2, 0.05, 0.3)
        est = tracker.step(1_000_000_000 + k * 200_000, [obs]).estimate
        if est is not None and est.initialized:
            published += 1
            C = est.covariance
            assert np.isfinite(C).all() and np.allclose(C, C.T, atol=1e-12)
            assert np.linalg.eigvalsh(C).min() >= -1e-9 * np.trace(C)
    assert published > 1000
    assert set(tracker.covariance_repairs) <= {"merge_pose", "posterior", "window_fit",
                                               "linalg_error"}


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # the NaN case
def test_a_broken_filter_covariance_is_repaired_counted_and_never_published() -> None:
    """Round-off damage to the body filter's covariance (a negative eigenvalue, as the issue-13
    flood produced): the next correction repairs what it adopts, counts it, and every published
    covariance is positive semi-definite. A covariance that is not even finite skips the frame
    (bad_covariance) and drops the body rather than publishing it."""
    rng = np.random.default_rng(4)
    tracker = HandTracker(TrackerConfig())
    stamp = 1_000_000_000
    for _ in range(8):
        tracker.step(stamp, [hg.observe(T_A, rng, NOISE_M)])
        stamp += hg.FRAME_NS
    ekf = tracker._ekf  # the filter's state, damaged on purpose
    assert ekf is not None
    # A negative angular-velocity variance: the landmarks observe the twist only through its
    # correlation with the pose, so no correction heals it by itself.
    ekf.P[9, 9] = -ekf.P[9, 9] - 1.0
    for _ in range(5):
        result = tracker.step(stamp, [hg.observe(T_A, rng, NOISE_M)])
        stamp += hg.FRAME_NS
        if result.estimate is not None:
            C = result.estimate.covariance
            assert np.linalg.eigvalsh(C).min() >= -1e-9 * np.trace(C)
    assert sum(tracker.covariance_repairs.values()) >= 1
    assert tracker.notes["covariance_repaired"] == sum(tracker.covariance_repairs.values())
    ekf = tracker._ekf
    assert ekf is not None
    ekf.P = np.full((12, 12), np.nan)
    result = tracker.step(stamp, [hg.observe(T_A, rng, NOISE_M)])
    assert result.estimate is None and result.reason == "bad_covariance"
    assert tracker._ekf is None  # dropped: a new body is initialised from the next frames


@pytest.mark.parametrize(("obj", "participant", "seed"), [("kitchen_drawer", 5, 3),
                                                          ("cabinet_door", 5, 3)])
def test_a_household_joint_survives_a_second_long_regrasp_gap(obj: str, participant: int,
                                                               seed: int) -> None:
    """The hand lets go, is out of sight for more than a second and grasps the handle again
    (the generator's ``gap="regrasp"``; tuning participant): through the tracker and the
    kinematics estimator the final joint is still the right type, and about as good as without
    the gap (measured: drawer 0.6 vs 0.7 deg, door 2.1 vs 2.0 deg)."""
    demo = generate(obj, participant, seed, gap="regrasp")
    undetected = [len(demo.detections(i)) == 0 for i in range(len(demo.stamps_ns))]
    first = undetected.index(True)
    last = len(undetected) - 1 - undetected[::-1].index(True)
    assert 1.0 <= (demo.stamps_ns[last + 1] - demo.stamps_ns[first]) * 1e-9 <= 1.5
    final = run_pipeline(demo).final
    assert final.type == demo.truth.joint.type
    plain = generate(obj, participant, seed)
    assert demo_tangent_error_deg(final, demo) < demo_tangent_error_deg(
        run_pipeline(plain).final, plain) + 5.0
