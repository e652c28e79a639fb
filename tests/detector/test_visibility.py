"""Per-landmark visibility: the depth-consistency heuristic and the SimCC (RTMPose) path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from services.detector.backproject import landmark_depths
from services.detector.runtime import CPU
from services.detector.visibility import (
    SimccKeypointModel,
    box_affine,
    depth_consistency,
    heuristic_visibility,
    in_image_factor,
)


def _synthetic_hand(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """21 landmark pixels on a 30 px grid and the hand model's relative depths (m)."""
    grid = np.array([(x, y) for y in range(5) for x in range(5)][:21], float)
    pixels = np.array([300.0, 200.0]) + 30.0 * grid
    z_rel = rng.uniform(-0.04, 0.04, 21)  # fingers curled towards / away from the camera
    return pixels, z_rel


def _depth_image(pixels: np.ndarray, z: np.ndarray, background_m: float = 1.5) -> np.ndarray:
    depth = np.full((720, 1280), round(background_m * 1000), np.uint16)
    for (u, v), zi in zip(np.rint(pixels).astype(int), z, strict=True):
        depth[v - 6:v + 7, u - 6:u + 7] = round(zi * 1000)
    return depth


def test_landmarks_behind_an_occluder_lose_visibility() -> None:
    rng = np.random.default_rng(3)
    pixels, z_rel = _synthetic_hand(rng)
    hand_depth = 0.7 + z_rel
    depth = _depth_image(pixels, hand_depth)
    occluded = [8, 12, 13, 17]  # an object 8 cm in front of these (e.g. fingertips round a handle)
    for i in occluded:
        u, v = np.rint(pixels[i]).astype(int)
        depth[v - 6:v + 7, u - 6:u + 7] = round((hand_depth[i] - 0.08) * 1000)
    z = landmark_depths(depth, 0.001, pixels, (1280, 720))
    visibility = heuristic_visibility(0.95, pixels, z, z_rel, (1280, 720))
    assert visibility.dtype == np.float32 and visibility.shape == (21,)
    visible = np.setdiff1d(np.arange(21), occluded)
    assert visibility[occluded].max() < 0.05
    assert visibility[visible].min() > 0.9
    assert visibility.max() <= 0.95  # scaled by the hand presence


def test_depth_consistency_margins() -> None:
    z_rel = np.zeros(21)
    z = np.full(21, 0.6)
    z[0] = 0.6 - 0.015  # 1.5 cm nearer: within the margin, still visible
    z[1] = 0.6 - 0.06  # 6 cm nearer: occluded
    z[2] = 0.6 + 0.03  # 3 cm farther: visible (thick knuckle, skin vs joint)
    z[3] = 0.6 + 0.2  # 20 cm farther: the depth missed the finger (background)
    z[4] = np.nan  # no depth: not judged
    factor, offset = depth_consistency(z, z_rel)
    assert offset == pytest.approx(0.6)
    assert factor[0] > 0.85 and factor[2] > 0.95 and factor[4] == 1.0
    assert factor[1] < 0.05 and factor[3] < 0.05
    none, offset = depth_consistency(np.full(21, np.nan), z_rel)
    assert (none == 1.0).all() and np.isnan(offset)


def test_in_image_factor_fades_at_the_border() -> None:
    f = in_image_factor(np.array([[100.0, 100.0], [0.0, 100.0], [-5.0, 100.0], [639.0, 10.0]]),
                        640, 480, 2.0)
    np.testing.assert_allclose(f, [1.0, 0.25, 0.0, 0.25])


def _fake_simcc_model(path: Path, peaks_x: np.ndarray, peaks_y: np.ndarray,
                      heights: np.ndarray) -> None:
    """A [1,3,256,256] -> simcc_x/simcc_y [1,21,512] ONNX model with fixed peaks (input used
    through a zero-weighted mean so the graph depends on it)."""
    sx = np.zeros((1, 21, 512), np.float32)
    sy = np.zeros((1, 21, 512), np.float32)
    sx[0, np.arange(21), peaks_x] = heights
    sy[0, np.arange(21), peaks_y] = heights
    nodes = [helper.make_node("ReduceMean", ["input"], ["m"], keepdims=0),
             helper.make_node("Mul", ["m", "zero"], ["z"]),
             helper.make_node("Add", ["cx", "z"], ["simcc_x"]),
             helper.make_node("Add", ["cy", "z"], ["simcc_y"])]
    graph = helper.make_graph(
        nodes, "fake_rtmpose",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, 3, 256, 256])],
        [helper.make_tensor_value_info("simcc_x", TensorProto.FLOAT, [1, 21, 512]),
         helper.make_tensor_value_info("simcc_y", TensorProto.FLOAT, [1, 21, 512])],
        [numpy_helper.from_array(sx, "cx"), numpy_helper.from_array(sy, "cy"),
         numpy_helper.from_array(np.zeros((), np.float32), "zero")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    path.write_bytes(model.SerializeToString())


def test_simcc_scores_become_visibility_and_keypoints_map_to_the_image(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    peaks_x = rng.integers(50, 460, 21)
    peaks_y = rng.integers(50, 460, 21)
    heights = np.linspace(0.1, 0.95, 21).astype(np.float32)
    _fake_simcc_model(tmp_path / "rtm.onnx", peaks_x, peaks_y, heights)
    model = SimccKeypointModel(ort.InferenceSession(str(tmp_path / "rtm.onnx"), providers=[CPU]))
    pixels = np.array([[400.0, 300.0], [480.0, 340.0]])  # hand box 80 x 40
    image = np.zeros((720, 1280, 3), np.uint8)
    keypoints, scores = model(image, pixels)
    np.testing.assert_allclose(scores, heights, atol=1e-6)
    # the box is padded 1.25x and made square (the input's aspect): side 100 px around (440, 320)
    M = box_affine(pixels, 256, 256, 1.25)
    assert M[0, 0] == pytest.approx(2.56)
    expected = np.column_stack([440.0 + (peaks_x / 2.0 - 128.0) / 2.56,
                                320.0 + (peaks_y / 2.0 - 128.0) / 2.56])
    np.testing.assert_allclose(keypoints, expected, atol=1e-6)
