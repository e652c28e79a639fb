"""The observation model produces the statistics its docstring documents."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.synthetic import hand as hd
from services.synthetic.camera import (
    AZURE_KINECT_COLOR_720P,
    ObservationModel,
    back_project,
    observe_landmarks,
    project,
)

K = AZURE_KINECT_COLOR_720P
N = 3000


def _static_hand(z: float = 0.7) -> tuple[np.ndarray, np.ndarray, hd.Participant]:
    """A pinching hand 0.7 m in front of the camera, back of the hand facing the camera."""
    part = hd.participant(1)
    lm_h = hd.landmarks_from_angles(part.shape, hd.participant_posture(part, "pinch"))
    R = np.diag([1.0, -1.0, -1.0])  # hand z (dorsal) points at the camera (-z of the camera)
    centre = lm_h.mean(axis=0)
    lm_c = (lm_h - centre) @ R.T + np.array([0.0, 0.0, z])
    return np.broadcast_to(lm_c, (N, 21, 3)).copy(), np.broadcast_to(R, (N, 3, 3)).copy(), part


def _observe(model: ObservationModel, occlusion: float = 0.0, seed: int = 0, z: float = 0.7):
    lm, R, part = _static_hand(z)
    t = np.arange(N) / 30.0
    obs = observe_landmarks(np.random.default_rng(seed), lm, R, t, occlusion,
                            part.shape.radii(), part.shape.palm_length(), K, model)
    return obs, lm, part


def test_projection_round_trip() -> None:
    rng = np.random.default_rng(0)
    p = rng.uniform([-0.3, -0.2, 0.4], [0.3, 0.2, 1.0], (50, 3))
    np.testing.assert_allclose(back_project(project(p, K), p[:, 2], K), p, atol=1e-12)


def test_pixel_error_per_landmark_type_matches_the_model() -> None:
    model = dataclasses.replace(ObservationModel(), swap_rate_per_s=0.0, self_occlusion=0.0)
    obs, lm, part = _observe(model)
    err = obs.pixels.astype(float) - project(lm, K)
    palm_px = part.shape.palm_length() * K.fx / lm[0, :, 2].mean()
    sigma = model.pixel_sigma(np.array(palm_px))
    # Per landmark, per axis standard deviation (OU part is correlated over ~15 frames, so the
    # estimate over 3000 frames is good to a few per cent).
    std = err.std(axis=0).mean(axis=1)
    np.testing.assert_allclose(std, sigma, rtol=0.12)
    # Wrist noisier than fingertips, as documented.
    assert sigma[0] > sigma[8]
    # Mean 2-D error norm over all landmarks is 10 % of the palm size (MediaPipe Hands).
    mean_norm = np.linalg.norm(err, axis=-1).mean()
    assert mean_norm == pytest.approx(0.10 * palm_px, rel=0.06)


@pytest.mark.parametrize("z", [0.45, 0.95])
def test_depth_noise_vs_distance_matches_the_model(z: float) -> None:
    model = dataclasses.replace(ObservationModel(), pixel_error_palm_fraction=0.0,
                                swap_rate_per_s=0.0, self_occlusion=0.0)
    obs, lm, part = _observe(model, z=z)
    assert not obs.depth_outlier.any() and not np.isnan(obs.points).any()
    surface = lm[..., 2] - part.shape.radii()  # skin surface in front of the joint centre
    resid = obs.points[..., 2].astype(float) - surface
    resid -= resid.mean()  # the per-demonstration systematic offset
    expected = np.sqrt(model.depth_sigma(surface[0]) ** 2 + model.depth_quantum_m**2 / 12.0)
    np.testing.assert_allclose(resid.std(axis=0), expected, rtol=0.1)


def test_depth_edge_outliers_occur_at_the_documented_rate() -> None:
    model = dataclasses.replace(ObservationModel(), swap_rate_per_s=0.0, self_occlusion=0.0)
    obs, lm, part = _observe(model)
    # Recompute the documented rule from the actual pixel errors.
    err = obs.pixels.astype(float) - project(lm, K)
    px = project(lm, K)
    parent = np.array(hd.PARENT)
    parent[0] = 9
    d = px - px[:, parent]
    d[:, 0] = -d[:, 0]
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    along = np.einsum("nji,nji->nj", err, d)
    perp = np.linalg.norm(err - along[..., None] * d, axis=-1)
    sil = np.array([model.silhouette_factor[t] for t in hd.LANDMARK_TYPES])
    w = part.shape.radii() * sil * K.fx / lm[..., 2]
    tip = np.array([t == "tip" for t in hd.LANDMARK_TYPES])
    off = (perp > w) | (tip & (along > 0.8 * w))
    mixed = ~off & (perp > w - model.depth_pixel_in_colour_px)
    np.testing.assert_array_equal(obs.depth_outlier, off | mixed)
    # Off-silhouette readings are behind the finger (background), never in front of it.
    z_err = obs.points[..., 2].astype(float) - lm[..., 2]
    assert np.nanmin(z_err[off]) > -0.02
    assert np.nanmedian(z_err[off]) > 0.0
    # About half the mixed pixels are invalidated.
    invalid = np.isnan(obs.points[..., 2])
    assert invalid[mixed].mean() == pytest.approx(model.mixed_invalid_probability, abs=0.05)
    # Thin fingertips lose their depth more often than the broad palm (MCPs).
    assert (off | mixed)[:, 8].mean() > 2 * (off | mixed)[:, 5].mean()


def test_occlusion_rates_visibility_and_missing() -> None:
    model = dataclasses.replace(ObservationModel(), swap_rate_per_s=0.0)
    level = 0.6
    obs, lm, _ = _observe(model, occlusion=level)
    # Back of the hand faces the camera: cos = 1.
    p = model.occlusion_probability(level, np.array(1.0))
    rate = obs.occluded.mean(axis=0)
    np.testing.assert_allclose(rate, p, atol=0.08)
    assert abs(rate.mean() - p.mean()) < 0.03
    assert obs.missing.mean() == pytest.approx(model.missing_fraction * p.mean(), abs=0.03)
    assert np.all(obs.occluded[obs.missing])
    assert np.isnan(obs.points[obs.missing]).all()
    # Occlusions persist over several frames.
    changes = np.count_nonzero(np.diff(obs.occluded.astype(int), axis=0))
    assert changes < 0.5 * obs.occluded.sum()
    vis = obs.visibility.astype(float)
    a, b = model.visibility_visible
    assert vis[~obs.occluded].mean() == pytest.approx(a / (a + b), abs=0.02)
    a, b = model.visibility_hallucinated
    assert vis[obs.occluded & ~obs.missing].mean() == pytest.approx(a / (a + b), abs=0.03)
    # Hallucinated landmarks read the occluder in front of the hand.
    halluc = obs.occluded & ~obs.missing
    z_err = obs.points[..., 2].astype(float) - lm[..., 2]
    assert np.nanmedian(z_err[halluc]) < -0.01


def test_swaps_exchange_adjacent_fingers_at_the_documented_rate() -> None:
    model = dataclasses.replace(ObservationModel(), self_occlusion=0.0, swap_rate_per_s=1.0)
    obs, lm, _ = _observe(model)
    frames = obs.swapped.any(axis=1)
    starts = np.count_nonzero(np.diff(frames.astype(int)) == 1) + int(frames[0])
    expected = model.swap_rate_per_s * N / 30.0
    assert starts == pytest.approx(expected, rel=0.3)  # overlapping events merge
    # Swapped rows carry the neighbour's pixels.
    k = int(np.flatnonzero(obs.swapped[:, 8] & obs.swapped[:, 12])[0])
    px = project(lm[k], K)
    assert np.linalg.norm(obs.pixels[k, 8] - px[12]) < np.linalg.norm(obs.pixels[k, 8] - px[8])


def test_no_swaps_or_occlusion_when_disabled() -> None:
    model = dataclasses.replace(ObservationModel(), swap_rate_per_s=0.0, self_occlusion=0.0)
    obs, _, _ = _observe(model, occlusion=0.0)
    assert not obs.swapped.any() and not obs.occluded.any()
