"""Azure Kinect colour camera and an observation model of a MediaPipe-style landmark detector.

Camera frame ``c``: OpenCV convention, x right, y down, z forward along the optical axis,
metres. Pixels ``(u, v)`` with ``u`` along x. Depth is the z coordinate (Azure Kinect depth maps
store z, registered to the colour image).

Intrinsics
    Colour camera in 1280x720 mode (Microsoft, "Azure Kinect DK hardware specifications":
    16:9, FoV 90 x 59 deg, up to 30 fps). We use fx = fy = 608 px, principal point near the image
    centre: the order of the factory calibrations of this mode (they are per device; the nominal
    FoV gives 2 atan(640/608) = 93 deg). No lens distortion (the detector is assumed to run on an
    undistorted image).

The detector is simulated the way the real pipeline observes a hand (paper section III.A and
docs/detector.md#pipeline): a 2-D landmark per joint (pixel), the registered depth read at that pixel,
back-projection ``X = z K^-1 [u, v, 1]``. Every number below was fixed from the cited sources
before any estimator was run on the data; none is tuned.

1. 2-D localisation error (per landmark type)
   MediaPipe Hands (Zhang et al., "MediaPipe Hands: On-device Real-time Hand Tracking",
   arXiv:2006.10214, 2020, Table 2) reports a mean landmark error of 10.05 % of the palm size for
   the full landmark model (11.83 % lite, 9.82 % heavy); we read that "MSE normalised by palm
   size" as the mean 2-D error norm in palm sizes and take palm size = wrist-to-middle-MCP
   distance. So the mean error norm over the 21 landmarks is ``0.10 * palm_px`` with
   ``palm_px = palm_m * fx / z``. Isotropic Gaussian per landmark, per-axis sigma
   ``sigma_j = f_j * 0.10 * palm_px / (sqrt(pi/2) * mean(f))``. Relative factors ``f_j`` by type
   (our judgement from qualitative findings, not from a per-landmark table, none found):
   wrist 1.6 and thumb CMC 1.4 (large regions with ill-defined joint centres; Pfisterer et al.
   2025 sec. III.A call the wrist the least consistently localised landmark), PIP 1.2 (Sprague et
   al., "Evaluation of Commercial Camera-Based Solutions for Tracking Hand Kinematics", Sensors
   25(18):5716, 2025: MediaPipe's error was substantially greater at the PIP joint), fingertips
   0.8 (distinct appearance, Pfisterer et al. sec. III.A), MCP/DIP/thumb MCP and IP 1.0-1.1.
   Half of the variance is slowly varying (Ornstein-Uhlenbeck, time constant 0.5 s: a tracker
   that crops from the previous frame makes errors persist), half is white per frame (an
   assumption).

2. Depth noise vs distance (Azure Kinect, WFOV 2x2-binned mode: 512x512, 30 fps, operating range
   0.25-2.88 m, which covers the 0.4-1.0 m working distance; the NFOV modes start at 0.5 m)
   Microsoft's depth-camera specification bounds the random error by sigma <= 17 mm and the
   systematic error by < 11 mm + 0.1 % of distance over the full range; Tolgyessy et al.,
   "Evaluation of the Azure Kinect and Its Comparison to Kinect V1 and Kinect V2", Sensors
   21(2):413, 2021, confirm these bounds and measure a much smaller per-pixel temporal standard
   deviation at short range (order of 1 mm below 1 m on a planar target, growing with distance;
   read from their figures, approximate); Kurillo et al., "Evaluating the Accuracy of the Azure
   Kinect and Kinect v2", Sensors 22(7):2469, 2022, report the same growth with distance and
   towards the image edges. Model: ``sigma_z(d) = 1.5 * (0.5 mm + 1.2 mm/m^2 * d^2)`` (the
   bracket is the planar-target precision, ~0.9 mm at 0.5 m and 1.7 mm at 1 m; x1.5 for skin,
   whose 850 nm reflectance is moderate, and for curved, oblique finger surfaces), a per
   demonstration systematic offset N(0, 2 mm), and 1 mm quantisation (depth maps are in mm).
   The depth read at a landmark is the *skin surface*, not the joint centre: ``z_joint - r`` for
   a digit of half-thickness ``r`` (``services.synthetic.hand``), less at the digit's flank
   (cylinder: ``r sqrt(1 - (e_perp / w)^2)``).

3. Depth-edge outliers (background behind thin fingers)
   The depth is read at the *detected* pixel. When the 2-D error moves it off the digit's
   silhouette (perpendicular offset beyond the half-width ``w``, or beyond the fingertip), the
   reading is the background: the object surface 0.5-5 cm behind (probability 0.6) or the scene
   10-60 cm behind. Within one depth pixel of the silhouette edge (2.5 colour pixels: 120 deg over
   512 depth pixels vs 1/608 rad per colour pixel) the ToF pixel mixes foreground and background
   ("flying pixels", Tolgyessy et al. 2021 sec. 3.6; PMD, "flying pixel" FAQ); the Azure depth
   engine invalidates many such pixels (Microsoft depth-camera docs, "Invalidation"): invalid
   (NaN) with probability 0.5, else a uniform mix of the two depths. Silhouette half-widths:
   the digit's half-thickness for finger landmarks, x2.5 for MCPs (the palm continues on both
   sides), x2 for the thumb CMC, x1.5 for the wrist.

4. Occlusion by the object
   Landmark ``j`` is hidden with probability ``pi_j = 0.03 + occ * (b_j + d_j max(0, c) +
   p_j max(0, -c))`` (clipped to 0.95), ``occ`` the object's occlusion level, ``c`` the cosine
   between the back-of-hand normal and the direction to the camera (fingertips curled around the
   object hide behind it when the back of the hand faces the camera; knuckles and thumb base hide
   when the palm, and the object in it, faces the camera). Weights (b, d, p): tip (.35,.6,.1),
   DIP (.25,.45,.1), PIP (.15,.25,.15), MCP (.05,.05,.3), wrist (.02,0,.15), thumb CMC
   (.05,.05,.3), thumb MCP (.1,.15,.2), thumb IP (.2,.3,.15); 0.03 models self-occlusion. Our
   assumptions: no published per-landmark occlusion statistics for grasps were found.
   Occlusions persist: a latent Ornstein-Uhlenbeck process per landmark (time constant 0.3 s)
   is thresholded at the Gaussian quantile of ``pi_j``. A regression detector still outputs a
   hidden landmark (MediaPipe always returns 21): it is *hallucinated* with an extra slowly
   varying 2-D error (sigma 0.15 palm per axis) and the depth read there is the occluder in front
   (0.5-4 cm nearer); the deepest 30 % of occlusions (latent below the quantile of 0.3 pi_j) are
   *missing*: no valid depth (NaN).

5. Visibility scores
   AlphaPose/SimCC-style confidences are poorly calibrated (Pfisterer et al. sec. III.A): visible
   landmarks draw Beta(6, 2) (mean 0.75), hallucinated ones Beta(1.5, 4) (mean 0.27), missing
   ones Beta(1, 12); landmarks outside the image get a tenth of that and NaN points. The hand
   score is 0.95 - 0.25 * (hidden fraction) + N(0, 0.02), clipped to [0, 1].

6. Landmark swaps (rare)
   The detector occasionally labels one finger as its neighbour. Events start at 0.1 per second
   (assumption) and last 2-8 frames; during one, two adjacent finger chains (index/middle,
   middle/ring or ring/pinky) exchange their pixels, depths and visibilities.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

from services.common.protocol import NUM_LANDMARKS
from services.synthetic.hand import CHAINS, LANDMARK_TYPES, PARENT

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the colour camera [px]."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.fx <= 0 or self.fy <= 0 or self.width <= 0 or self.height <= 0:
            raise ValueError(f"invalid intrinsics {self}")

    def matrix(self) -> Array:
        """3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


AZURE_KINECT_COLOR_720P = Intrinsics(fx=608.0, fy=608.0, cx=638.5, cy=367.5, width=1280,
                                     height=720)


def project(points_c: Array, K: Intrinsics) -> Array:
    """Pixels (..., 2) of camera-frame points (..., 3) [m]."""
    z = points_c[..., 2]
    return np.stack([K.fx * points_c[..., 0] / z + K.cx, K.fy * points_c[..., 1] / z + K.cy],
                    axis=-1)


def back_project(pixels: Array, depth: Array, K: Intrinsics) -> Array:
    """Camera-frame points (..., 3) [m] of pixels (..., 2) with depth z (...) [m]."""
    x = (pixels[..., 0] - K.cx) / K.fx * depth
    y = (pixels[..., 1] - K.cy) / K.fy * depth
    return np.stack([x, y, depth], axis=-1)


def _per_type(values: dict[str, float]) -> Array:
    return np.array([values[t] for t in LANDMARK_TYPES])


def _per_type3(values: dict[str, tuple[float, float, float]]) -> Array:
    return np.array([values[t] for t in LANDMARK_TYPES])


@dataclass(frozen=True)
class ObservationModel:
    """Parameters of the landmark observation model (module docstring; SI units)."""

    # 1. 2-D error: mean error norm as a fraction of the palm size (MediaPipe Hands, full model).
    pixel_error_palm_fraction: float = 0.10
    # Relative 2-D error per landmark type.
    type_factor: dict[str, float] = field(default_factory=lambda: {
        "wrist": 1.6, "thumb_cmc": 1.4, "thumb_mcp": 1.1, "thumb_ip": 1.1,
        "mcp": 1.0, "pip": 1.2, "dip": 1.0, "tip": 0.8})
    slow_variance_fraction: float = 0.5
    slow_time_constant_s: float = 0.5
    # 2. Depth: sigma_z(d) = skin_factor * (a + b d^2), offset, quantisation.
    depth_sigma_a_m: float = 0.0005
    depth_sigma_b_per_m: float = 0.0012
    skin_factor: float = 1.5
    depth_offset_std_m: float = 0.002
    depth_quantum_m: float = 0.001
    min_range_m: float = 0.25
    # 3. Depth edges.
    silhouette_factor: dict[str, float] = field(default_factory=lambda: {
        "wrist": 1.5, "thumb_cmc": 2.0, "thumb_mcp": 1.0, "thumb_ip": 1.0,
        "mcp": 2.5, "pip": 1.0, "dip": 1.0, "tip": 1.0})
    depth_pixel_in_colour_px: float = 2.5
    mixed_invalid_probability: float = 0.5
    background_near_probability: float = 0.6
    background_near_m: tuple[float, float] = (0.005, 0.05)
    background_far_m: tuple[float, float] = (0.10, 0.60)
    # 4. Occlusion: (base, back-of-hand-to-camera, palm-to-camera) weights per type.
    occlusion_weights: dict[str, tuple[float, float, float]] = field(default_factory=lambda: {
        "tip": (0.35, 0.6, 0.1), "dip": (0.25, 0.45, 0.1), "pip": (0.15, 0.25, 0.15),
        "mcp": (0.05, 0.05, 0.3), "wrist": (0.02, 0.0, 0.15), "thumb_cmc": (0.05, 0.05, 0.3),
        "thumb_mcp": (0.1, 0.15, 0.2), "thumb_ip": (0.2, 0.3, 0.15)})
    self_occlusion: float = 0.03
    max_occlusion_probability: float = 0.95
    occlusion_time_constant_s: float = 0.3
    missing_fraction: float = 0.3
    hallucination_palm_fraction: float = 0.15
    occluder_in_front_m: tuple[float, float] = (0.005, 0.04)
    # 5. Visibility Beta parameters.
    visibility_visible: tuple[float, float] = (6.0, 2.0)
    visibility_hallucinated: tuple[float, float] = (1.5, 4.0)
    visibility_missing: tuple[float, float] = (1.0, 12.0)
    # 6. Swaps.
    swap_rate_per_s: float = 0.1
    swap_duration_frames: tuple[int, int] = (2, 8)

    def __post_init__(self) -> None:
        if self.pixel_error_palm_fraction < 0 or not 0 <= self.slow_variance_fraction <= 1:
            raise ValueError("invalid 2-D error parameters")
        if self.depth_sigma_a_m < 0 or self.depth_sigma_b_per_m < 0 or self.skin_factor <= 0:
            raise ValueError("invalid depth noise parameters")
        if not 0 <= self.missing_fraction <= 1 or self.swap_rate_per_s < 0:
            raise ValueError("invalid occlusion/swap parameters")

    def type_factors(self) -> Array:
        """Relative 2-D error factor per landmark (21,)."""
        return _per_type(self.type_factor)

    def pixel_sigma(self, palm_px: Array) -> Array:
        """Per-axis 2-D error sigma (..., 21) [px] for palm sizes ``palm_px`` (...) [px]."""
        f = self.type_factors()
        scale = self.pixel_error_palm_fraction / (np.sqrt(np.pi / 2.0) * f.mean())
        return np.asarray(palm_px)[..., None] * scale * f

    def depth_sigma(self, z: Array) -> Array:
        """Random depth error sigma [m] at depth ``z`` [m] (any shape)."""
        z = np.asarray(z, dtype=float)
        return self.skin_factor * (self.depth_sigma_a_m + self.depth_sigma_b_per_m * z * z)

    def occlusion_probability(self, level: float | Array, cos_dorsal: Array) -> Array:
        """Marginal probability (..., 21) that each landmark is hidden.

        ``level`` is the object's occlusion level (a scalar, or one per frame (...)),
        ``cos_dorsal`` (...) the cosine between the back-of-hand normal and the direction from
        the hand to the camera.
        """
        w = _per_type3(self.occlusion_weights)
        c = np.asarray(cos_dorsal, dtype=float)[..., None]
        lv = np.asarray(level, dtype=float)
        if lv.ndim:
            lv = lv[..., None]
        p = self.self_occlusion + lv * (w[:, 0] + w[:, 1] * np.maximum(c, 0.0)
                                        + w[:, 2] * np.maximum(-c, 0.0))
        return np.clip(p, 0.0, self.max_occlusion_probability)


@dataclass(frozen=True, eq=False)
class Observation:
    """What the detector delivers for N frames (camera frame ``c``) plus what really happened."""

    points: NDArray[np.float32]      # (N, 21, 3) [m], NaN where no valid depth
    pixels: NDArray[np.float32]      # (N, 21, 2) [px]
    visibility: NDArray[np.float32]  # (N, 21) in [0, 1]
    score: NDArray[np.float32]       # (N,) in [0, 1]
    # Per delivered row (after swaps, so row j describes the data reported as landmark j):
    occluded: BoolArray              # (N, 21) hidden by the object (hallucinated or missing)
    missing: BoolArray               # (N, 21) hidden and without valid depth
    depth_outlier: BoolArray         # (N, 21) depth read off the digit (background/mixed/occluder)
    swapped: BoolArray               # (N, 21) row carries the neighbouring finger's detection


def ornstein_uhlenbeck(rng: np.random.Generator, t: Array, time_constant_s: float,
                       shape: tuple[int, ...]) -> Array:
    """Stationary unit-variance OU samples (len(t), *shape) at increasing times ``t`` [s]."""
    n = len(t)
    out = np.empty((n, *shape))
    eps = rng.standard_normal((n, *shape))
    x = eps[0] if n else np.zeros(shape)
    if n:
        out[0] = x
    for k in range(1, n):
        phi = np.exp(-(t[k] - t[k - 1]) / time_constant_s)
        x = phi * x + np.sqrt(1.0 - phi * phi) * eps[k]
        out[k] = x
    return out


def _bone_directions(pixels_true: Array) -> Array:
    """Unit image direction (N, 21, 2) of the bone ending at each landmark (wrist: to MCP 9)."""
    parent = np.array(PARENT)
    parent[0] = 9
    d = pixels_true - pixels_true[:, parent]
    d[:, 0] = -d[:, 0]
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    return d / np.maximum(n, 1e-9)


def observe_landmarks(rng: np.random.Generator, landmarks_c: Array, R_c_hand: Array, t: Array,
                      occlusion_level: float | Array, radii: Array, palm_length_m: float,
                      K: Intrinsics = AZURE_KINECT_COLOR_720P,
                      model: ObservationModel | None = None) -> Observation:
    """Simulate the detector on true landmarks (module docstring, steps 1-6).

    Parameters
    ----------
    landmarks_c : (N, 21, 3) true landmark (joint centre) positions in the camera frame [m].
    R_c_hand : (N, 3, 3) hand orientation in the camera frame (column 2 = back-of-hand normal).
    t : (N,) capture times [s], increasing.
    occlusion_level : the object's occlusion level in [0, 1], or (N,) one per frame (a free
        hand away from the object is hidden less).
    radii : (21,) half-thickness of the digit at each landmark [m].
    palm_length_m : wrist-to-middle-MCP distance of this hand [m].
    """
    m = model if model is not None else ObservationModel()
    n = landmarks_c.shape[0]
    types = LANDMARK_TYPES
    z_true = landmarks_c[..., 2]
    px_true = project(landmarks_c, K)

    # 1. 2-D errors.
    palm_px = palm_length_m * K.fx / z_true.mean(axis=1)
    sigma = m.pixel_sigma(palm_px)                                     # (N, 21)
    slow = ornstein_uhlenbeck(rng, t, m.slow_time_constant_s, (NUM_LANDMARKS, 2))
    white = rng.standard_normal((n, NUM_LANDMARKS, 2))
    err = sigma[..., None] * (np.sqrt(m.slow_variance_fraction) * slow
                              + np.sqrt(1.0 - m.slow_variance_fraction) * white)

    # 4. Occlusion (latent OU thresholded at the marginal probability).
    centre = landmarks_c.mean(axis=1)
    to_cam = -centre / np.linalg.norm(centre, axis=-1, keepdims=True)
    cos_dorsal = np.einsum("ni,ni->n", R_c_hand[:, :, 2], to_cam)
    p_occ = m.occlusion_probability(occlusion_level, cos_dorsal)        # (N, 21)
    latent = ndtr(ornstein_uhlenbeck(rng, t, m.occlusion_time_constant_s, (NUM_LANDMARKS,)))
    occluded = latent < p_occ
    missing = latent < m.missing_fraction * p_occ
    halluc = ornstein_uhlenbeck(rng, t, m.slow_time_constant_s, (NUM_LANDMARKS, 2))
    err = err + np.where(occluded[..., None],
                         m.hallucination_palm_fraction * palm_px[:, None, None] * halluc, 0.0)
    pixels = px_true + err

    # 2./3. Depth read at the detected pixel.
    d_img = _bone_directions(px_true)
    e_along = np.einsum("nji,nji->nj", err, d_img)
    e_perp = np.linalg.norm(err - e_along[..., None] * d_img, axis=-1)
    sil = _per_type(m.silhouette_factor)
    w_px = radii * sil * K.fx / z_true                                  # (N, 21)
    is_tip = np.array([ty == "tip" for ty in types])
    off = (e_perp > w_px) | (is_tip & (e_along > 0.8 * w_px))
    mixed = ~off & (e_perp > w_px - m.depth_pixel_in_colour_px)
    frac = np.clip(e_perp / w_px, 0.0, 1.0)
    z_fg = z_true - radii * np.sqrt(1.0 - frac * frac)
    near = rng.random((n, NUM_LANDMARKS)) < m.background_near_probability
    z_bg = z_true + np.where(near, rng.uniform(*m.background_near_m, (n, NUM_LANDMARKS)),
                             rng.uniform(*m.background_far_m, (n, NUM_LANDMARKS)))
    alpha = rng.random((n, NUM_LANDMARKS))
    z_read = np.where(off, z_bg, np.where(mixed, alpha * z_fg + (1.0 - alpha) * z_bg, z_fg))
    invalid = mixed & (rng.random((n, NUM_LANDMARKS)) < m.mixed_invalid_probability)
    z_read = np.where(occluded, z_true - rng.uniform(*m.occluder_in_front_m, (n, NUM_LANDMARKS)),
                      z_read)
    invalid = np.where(occluded, missing, invalid)
    depth_outlier = occluded | off | mixed
    offset = rng.normal(0.0, m.depth_offset_std_m)
    z_obs = z_read + offset + m.depth_sigma(z_read) * rng.standard_normal((n, NUM_LANDMARKS))
    if m.depth_quantum_m > 0:
        z_obs = np.round(z_obs / m.depth_quantum_m) * m.depth_quantum_m
    in_image = ((pixels[..., 0] >= 0) & (pixels[..., 0] <= K.width - 1)
                & (pixels[..., 1] >= 0) & (pixels[..., 1] <= K.height - 1))
    valid = ~invalid & in_image & (z_obs >= m.min_range_m)
    points = back_project(pixels, z_obs, K)
    points[~valid] = np.nan

    # 5. Visibility and hand score.
    vis = np.where(occluded, rng.beta(*m.visibility_hallucinated, (n, NUM_LANDMARKS)),
                   rng.beta(*m.visibility_visible, (n, NUM_LANDMARKS)))
    vis = np.where(missing, rng.beta(*m.visibility_missing, (n, NUM_LANDMARKS)), vis)
    vis = np.where(in_image, vis, 0.1 * vis)
    score = np.clip(0.95 - 0.25 * occluded.mean(axis=1) + rng.normal(0.0, 0.02, n), 0.0, 1.0)

    # 6. Swaps of adjacent finger chains.
    swapped = np.zeros((n, NUM_LANDMARKS), dtype=bool)
    p_start = m.swap_rate_per_s / 30.0
    starts = np.flatnonzero(rng.random(n) < p_start)
    lo, hi = m.swap_duration_frames
    for s in starts:
        f = int(rng.integers(1, 4))  # pairs (1,2), (2,3), (3,4) of CHAINS
        a, b = list(CHAINS[f]), list(CHAINS[f + 1])
        sl = slice(int(s), int(s) + int(rng.integers(lo, hi + 1)))
        for arr in (points, pixels, vis, occluded, missing, depth_outlier):
            tmp = arr[sl, a].copy()
            arr[sl, a] = arr[sl, b]
            arr[sl, b] = tmp
        swapped[sl, a + b] = True

    return Observation(
        points=points.astype(np.float32), pixels=pixels.astype(np.float32),
        visibility=vis.astype(np.float32), score=score.astype(np.float32),
        occluded=occluded, missing=missing, depth_outlier=depth_outlier, swapped=swapped)
