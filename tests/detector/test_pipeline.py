"""The whole pipeline with the real models on real photographs (opencv-doc basketball frames)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from services.detector.backproject import project
from services.detector.config import DetectorConfig
from services.detector.palm import PalmDetection
from services.detector.pipeline import STAGES, HandPipeline, square_tiles
from tests.detector.conftest import (
    CATCHER_CROP,
    HAND_REGIONS,
    RAISER_CROP,
    crop,
    intrinsics_for,
)


@pytest.fixture(scope="module")
def pipeline(cpu_config: DetectorConfig) -> HandPipeline:
    return HandPipeline.from_config(cpu_config)


@pytest.mark.parametrize(("name", "box"), list(HAND_REGIONS))
def test_landmarks_land_on_the_hand(pipeline: HandPipeline, opencv_images: dict[str, np.ndarray],
                                    name: str, box: tuple[int, int, int, int]) -> None:
    image = crop(opencv_images[name], box)
    pipeline.reset()
    result = pipeline.process(image, None, 0.001, intrinsics_for(image))
    assert result.palm_ran
    assert len(result.hands) == 1, [h.score for h in result.hands]
    hand = result.hands[0]
    assert hand.score > 0.5
    assert hand.handedness in ("left", "right")
    xmin, ymin, xmax, ymax = HAND_REGIONS[(name, box)]
    px = hand.pixels + np.array(box[:2])  # back to frame pixels
    inside = ((px[:, 0] >= xmin) & (px[:, 0] <= xmax) & (px[:, 1] >= ymin) & (px[:, 1] <= ymax))
    assert inside.all(), px[~inside]
    # a real hand spans some pixels (not a collapsed, degenerate output)
    assert np.ptp(px[:, 0]) > 10 and np.ptp(px[:, 1]) > 10
    # no depth: NaN points, visibility = presence (all in the image)
    assert np.isnan(hand.points).all()
    np.testing.assert_allclose(hand.visibility, hand.score, rtol=1e-6)
    assert set(result.timings_s) == set(STAGES)


def test_tracking_follows_the_hand_without_palm_detection(
        pipeline: HandPipeline, opencv_images: dict[str, np.ndarray]) -> None:
    small = crop(opencv_images["basketball1.png"], CATCHER_CROP)
    image = cv2.resize(small, None, fx=3, fy=3, interpolation=cv2.INTER_CUBIC)  # hand ~80 px
    K = intrinsics_for(image)
    pipeline.reset()
    first = pipeline.process(image, None, 0.001, K)
    for _ in range(3):  # let the tracking ROI settle on the still hand
        settled = pipeline.process(image, None, 0.001, K)
    shift = np.array([12.0, -9.0])
    moved = cv2.warpAffine(image, np.array([[1.0, 0.0, shift[0]], [0.0, 1.0, shift[1]]]),
                           (image.shape[1], image.shape[0]), borderMode=cv2.BORDER_REPLICATE)
    second = pipeline.process(moved, None, 0.001, K)
    assert first.palm_ran and not settled.palm_ran and not second.palm_ran
    assert "palm" not in second.timings_s
    assert len(second.hands) == 1 and second.hands[0].tracked
    assert second.hands[0].score > 0.5
    # once the ROI has caught up with the moved hand, the landmarks moved with it
    third = pipeline.process(moved, None, 0.001, K)
    assert not third.palm_ran and third.hands[0].tracked
    motion = np.median(third.hands[0].pixels - settled.hands[0].pixels, axis=0)
    np.testing.assert_allclose(motion, shift, atol=3.0)


def test_a_lost_hand_is_searched_again_in_the_same_frame(
        pipeline: HandPipeline, opencv_images: dict[str, np.ndarray]) -> None:
    image = crop(opencv_images["basketball1.png"], CATCHER_CROP)
    K = intrinsics_for(image)
    pipeline.reset()
    assert len(pipeline.process(image, None, 0.001, K).hands) == 1
    blank = np.full_like(image, 128)
    gone = pipeline.process(blank, None, 0.001, K)
    assert gone.hands == () and gone.palm_ran  # tracking lost -> palm detection ran again
    back = pipeline.process(image, None, 0.001, K)
    assert len(back.hands) == 1 and back.palm_ran and not back.hands[0].tracked


def test_detection_mode_runs_the_palm_detector_on_every_frame(
        cpu_config: DetectorConfig, opencv_images: dict[str, np.ndarray]) -> None:
    detect_only = HandPipeline.from_config(dataclasses.replace(cpu_config, tracking=False,
                                                   landmark_model="lite", palm_model="lite"))
    image = crop(opencv_images["basketball1.png"], CATCHER_CROP)
    results = [detect_only.process(image, None, 0.001, intrinsics_for(image)) for _ in range(2)]
    assert all(r.palm_ran and "palm" in r.timings_s for r in results)
    assert all(len(r.hands) == 1 and not r.hands[0].tracked for r in results)


def test_depth_gives_3d_points_that_project_onto_the_landmarks(
        pipeline: HandPipeline, opencv_images: dict[str, np.ndarray]) -> None:
    image = crop(opencv_images["basketball1.png"], RAISER_CROP)
    K = intrinsics_for(image)
    depth = np.full(image.shape[:2], 700, np.uint16)  # a flat 0.7 m scene
    pipeline.reset()
    result = pipeline.process(image, depth, 0.001, K)
    hand = result.hands[0]
    np.testing.assert_allclose(hand.points[:, 2], 0.7, atol=1e-9)
    np.testing.assert_allclose(project(hand.points, K), hand.pixels, atol=1e-6)
    assert hand.points.dtype == np.float64


def test_visibility_drops_behind_a_synthetic_occluder(
        pipeline: HandPipeline, opencv_images: dict[str, np.ndarray]) -> None:
    """Depth consistent with the model's hand shape, then an object in front of some landmarks."""
    small = crop(opencv_images["basketball1.png"], RAISER_CROP)
    image = cv2.resize(small, None, fx=4, fy=4, interpolation=cv2.INTER_CUBIC)  # hand ~130 px
    K = intrinsics_for(image, f=900.0)
    pipeline.reset()
    hand = pipeline.process(image, None, 0.001, K).hands[0]
    # depth image: every pixel near the hand gets the depth of its nearest landmark, where the
    # model puts it (0.6 m + the model's relative depth); background 1.5 m
    v, u = np.mgrid[0:image.shape[0], 0:image.shape[1]]
    d2 = (u[..., None] - hand.pixels[:, 0]) ** 2 + (v[..., None] - hand.pixels[:, 1]) ** 2
    nearest = d2.argmin(axis=2)
    z_model = 0.6 + hand.world[:, 2]
    depth_m = np.where(d2.min(axis=2) < 30.0**2, z_model[nearest], 1.5)
    depth = np.rint(depth_m * 1000).astype(np.uint16)
    pipeline.reset()
    clear = pipeline.process(image, depth, 0.001, K).hands[0]
    # an occluder 10 cm in front of the hand over a disc around the index fingertip (8)
    tip = hand.pixels[8]
    disc = (u - tip[0]) ** 2 + (v - tip[1]) ** 2 < 14.0**2
    occluded_depth = depth.copy()
    occluded_depth[disc] = np.rint((z_model[8] - 0.10) * 1000)
    pipeline.reset()
    blocked = pipeline.process(image, occluded_depth, 0.001, K).hands[0]
    np.testing.assert_allclose(blocked.pixels, clear.pixels)  # same image, same landmarks
    behind = np.flatnonzero(np.hypot(*(clear.pixels - tip).T) < 6.0)  # landmarks in the disc
    away = np.flatnonzero(np.hypot(*(clear.pixels - tip).T) > 25.0)
    assert 8 in behind and len(away) >= 10
    assert clear.visibility[behind].min() > 0.5
    assert blocked.visibility[behind].max() < 0.1
    np.testing.assert_allclose(blocked.visibility[away], clear.visibility[away], atol=0.05)
    assert clear.visibility[away].min() > 0.5


class _KnownPalms:
    """Palm stage replaced by given detections (the real palm model, run on each crop alone:
    the 192-px detector misses hands under ~13 % of a composite's long side)."""

    def __init__(self, palms: list[PalmDetection]) -> None:
        self.palms = palms

    def infer(self, tensor: np.ndarray) -> tuple[None, None]:
        return None, None

    def postprocess(self, *_args: object) -> list[PalmDetection]:
        return list(self.palms)


def test_two_hands_are_tracked_and_duplicates_merged(
        pipeline: HandPipeline, cpu_config: DetectorConfig,
        opencv_images: dict[str, np.ndarray]) -> None:
    image = opencv_images["basketball1.png"]
    left, right = crop(image, CATCHER_CROP), crop(image, RAISER_CROP)  # 160 and 180 px tall
    padded = cv2.copyMakeBorder(left, 0, 20, 0, 0, cv2.BORDER_REPLICATE)
    composite = np.ascontiguousarray(np.concatenate([padded, right], axis=1))
    palms = []
    for part, dx in ((left, 0.0), (right, 160.0)):
        p = pipeline.palm(part)[0]
        shift = np.array([dx, 0.0])
        palms.append(PalmDetection(p.score, p.box + np.tile(shift, 2), p.keypoints + shift))
    duplicate = PalmDetection(0.6, palms[0].box + 1.0, palms[0].keypoints + 1.0)
    two = HandPipeline(cpu_config, _KnownPalms([*palms, duplicate]),  # type: ignore[arg-type]
                       pipeline.landmarks)
    K = intrinsics_for(composite)
    first = two.process(composite, None, 0.001, K)
    assert len(first.hands) == 2  # the duplicate palm is the first hand again
    centres = sorted(h.pixels.mean(axis=0)[0] for h in first.hands)
    assert centres[0] < 160.0 < centres[1]
    second = two.process(composite, None, 0.001, K)
    assert not second.palm_ran and [h.tracked for h in second.hands] == [True, True]
    one = HandPipeline(dataclasses.replace(cpu_config, max_hands=1),
                       _KnownPalms(palms), pipeline.landmarks)  # type: ignore[arg-type]
    assert len(one.process(composite, None, 0.001, K).hands) == 1


def test_small_hands_in_a_wide_frame_are_found_in_its_end_squares(
        cpu_config: DetectorConfig, opencv_images: dict[str, np.ndarray]) -> None:
    """A 1280x720 view in which the catcher's hand is ~6 % of the width (as at ~1.3 m from an
    Azure Kinect): too small for the palm detector on the whole frame."""
    assert square_tiles(1280, 720) == [(0, 0, 720), (560, 0, 720)]
    assert square_tiles(480, 640) == [(0, 0, 480), (0, 160, 480)]
    assert square_tiles(640, 600) == []
    M = np.array([[3.2, 0.0, 0.0], [0.0, 3.2, 0.0]])  # the top-left 400x225 of basketball1
    frame = cv2.warpAffine(opencv_images["basketball1.png"], M, (1280, 720),
                           flags=cv2.INTER_LINEAR)
    K = intrinsics_for(frame, f=608.0)
    whole = HandPipeline.from_config(dataclasses.replace(cpu_config, palm_tiles=False))
    assert whole.process(frame, None, 0.001, K).hands == ()
    tiled = HandPipeline.from_config(cpu_config)
    hands = tiled.process(frame, None, 0.001, K).hands
    assert len(hands) == 1 and hands[0].score > 0.5
    xmin, ymin, xmax, ymax = HAND_REGIONS[("basketball1.png", CATCHER_CROP)]
    px = hands[0].pixels / 3.2
    assert ((px >= [xmin, ymin]) & (px <= [xmax, ymax])).all()
