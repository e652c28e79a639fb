"""A small rigid 21-landmark hand and trajectories for the tracker tests (not the full generator).

Hand frame: wrist at the origin, fingers along +y, palm normal -z; MediaPipe landmark order.
Spread: ~19 cm from the wrist to the middle fingertip, ~8 cm across the knuckles.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.kabsch import weighted_kabsch
from services.common.se3 import se3_exp, se3_inverse, so3_exp, transform_points
from services.tracker.config import TrackerConfig
from services.tracker.tracker import HandBodyEstimate, HandObservation, HandTracker

Array = NDArray[np.float64]
FRAME_NS = 33_333_333  # 30 Hz


def hand_points() -> Array:
    """(21, 3) landmark positions in the hand frame (m)."""
    pts = np.zeros((21, 3))
    thumb = [(0.025, 0.025, -0.012), (0.047, 0.046, -0.022), (0.062, 0.066, -0.031),
             (0.071, 0.086, -0.036)]
    pts[1:5] = thumb
    mcp = [(0.026, 0.090, 0.0), (0.004, 0.095, 0.0), (-0.017, 0.089, 0.0), (-0.035, 0.079, 0.0)]
    lengths = [(0.043, 0.026, 0.021), (0.047, 0.029, 0.022), (0.044, 0.027, 0.021),
               (0.034, 0.020, 0.019)]
    curl = (0.25, 0.35, 0.25)  # flexion per joint (rad), about the hand's x axis
    for f in range(4):
        base = 5 + 4 * f
        pts[base] = mcp[f]
        direction = np.array([0.0, 1.0, 0.0])
        angle = 0.0
        for j in range(3):
            angle += curl[j]
            direction = so3_exp(np.array([-angle, 0.0, 0.0])) @ np.array([0.0, 1.0, 0.0])
            pts[base + j + 1] = pts[base + j] + lengths[f][j] * direction
    return pts


HAND = hand_points()


def smoothstep(x: float) -> float:
    """0 -> 1 with zero first and second derivative at both ends (quintic)."""
    x = min(max(x, 0.0), 1.0)
    return x * x * x * (10.0 - 15.0 * x + 6.0 * x * x)


def revolute_twist(point: Array, axis: Array) -> Array:
    """Unit twist ``(p x u, u)`` of a rotation about the line through ``point`` along ``axis``."""
    u = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return np.concatenate([np.cross(point, u), u])


def pose_error(T_est: Array, T_true: Array) -> tuple[float, float]:
    """(translation error of the frame origin in m, rotation angle error in rad)."""
    R_err = T_true[:3, :3] @ T_est[:3, :3].T
    angle = np.arccos(np.clip(0.5 * (np.trace(R_err) - 1.0), -1.0, 1.0))
    return float(np.linalg.norm(T_true[:3, 3] - T_est[:3, 3])), float(angle)


def landmark_error(T_est: Array, T_true: Array, points_body: Array) -> float:
    """RMS distance (m) between the body points placed by the two poses: the pose error as the
    landmark displacement it implies (comparable with the per-landmark noise)."""
    d = transform_points(T_est, points_body) - transform_points(T_true, points_body)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def noise_matched_config(sigma_m: float, gate: float | None = None, uniform_saliency: bool = True,
                         **overrides: object) -> TrackerConfig:
    """Table I with every covariance (P0, Q, R, loss threshold) scaled by ``c = sigma^2 / r_lm``
    (in SI: ``variance_unit_m2 = 1``; isotropic ``R_lm``, no articulation variance).

    Gains and means are unchanged by the scaling. ``gate=None`` scales the Mahalanobis thresholds
    by ``1/sqrt(c)`` (every gate decision unchanged); a number sets them all (chi-square-like
    gates in units of the matched noise). ``uniform_saliency``: s_k = 1 (the synthetic noise is
    the same for every landmark type).
    """
    base = TrackerConfig()
    c = sigma_m**2 / base.r_lm_m2
    values: dict[str, object] = {}
    for f in dataclasses.fields(base):
        v = getattr(base, f.name)
        if f.name.startswith(("p0_", "q_", "r_lm")) or f.name == "lm_loss_trace_m2":
            values[f.name] = v * c
        elif f.name in ("mahalanobis_lm", "mahalanobis_rb", "ransac_inlier_mahalanobis"):
            values[f.name] = v / np.sqrt(c) if gate is None else gate
        elif f.name.startswith("saliency_") and uniform_saliency:
            values[f.name] = 1.0
    # The values above are SI already (variance_unit_m2 = 1); the test noise is isotropic (no
    # depth anisotropy) and the test hand rigid (no articulation variance).
    values.update(variance_unit_m2=1.0, depth_variance_factor=1.0, articulation_std_rad=0.0)
    values.update(overrides)
    return dataclasses.replace(base, **values)  # type: ignore[arg-type]


def with_outliers(obs: HandObservation, rng: np.random.Generator, fraction: float,
                  low_m: float, high_m: float) -> tuple[HandObservation, NDArray[np.intp]]:
    """``obs`` with ``round(fraction * 21)`` random landmarks moved 5-30 cm (or low..high) in a
    random direction; also returns their indices."""
    idx = rng.choice(21, size=round(fraction * 21), replace=False)
    d = rng.normal(size=(idx.size, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    pts = obs.points.copy()
    pts[idx] += d * rng.uniform(low_m, high_m, size=(idx.size, 1))
    return dataclasses.replace(obs, points=pts), idx


@dataclass
class Scenario:
    """A trajectory ``T_frame_hand(t)`` sampled at 30 Hz, with optional camera motion."""

    T_frame_hand: Callable[[float], Array]
    duration_s: float
    T_world_camera: Callable[[float], Array] | None = None

    def stamps(self) -> list[int]:
        n = round(self.duration_s * 1e9 / FRAME_NS)
        return [1_000_000_000 + k * FRAME_NS for k in range(n)]

    @staticmethod
    def time_of(stamp_ns: int) -> float:
        return (stamp_ns - 1_000_000_000) * 1e-9


def observe(T_frame_hand: Array, rng: np.random.Generator | None = None, noise_std_m: float = 0.0,
            T_world_camera: Array | None = None, handedness: str = "right",
            score: float = 0.9) -> HandObservation:
    """Landmarks of the hand at ``T_frame_hand`` seen by the camera (camera frame), with noise."""
    pts = transform_points(T_frame_hand, HAND)
    if T_world_camera is not None:
        pts = transform_points(se3_inverse(T_world_camera), pts)
    if rng is not None and noise_std_m > 0.0:
        pts = pts + rng.normal(scale=noise_std_m, size=pts.shape)
    return HandObservation(handedness=handedness, score=score, points=pts,
                           visibility=np.ones(21))


@dataclass
class RunLog:
    """Everything a test needs from a run: stamps, truth, estimates (None = no output)."""

    stamps: list[int]
    truth: list[Array]
    estimates: list[HandBodyEstimate | None]

    def initialized(self) -> list[int]:
        """Indices with an initialised estimate."""
        return [k for k, e in enumerate(self.estimates) if e is not None and e.initialized]

    def at(self, k: int) -> HandBodyEstimate:
        """The estimate of frame k (which must exist)."""
        est = self.estimates[k]
        assert est is not None
        return est


def run(tracker: HandTracker, scenario: Scenario,
        make_hands: Callable[[int, Array, Array | None], Sequence[HandObservation]],
        prior: Callable[[int], tuple[Array, Array] | None] | None = None) -> RunLog:
    """Feed the scenario through the tracker; ``make_hands(k, T_frame_hand, T_world_camera)``."""
    log = RunLog([], [], [])
    for k, stamp in enumerate(scenario.stamps()):
        t = Scenario.time_of(stamp)
        T = scenario.T_frame_hand(t)
        T_wc = None if scenario.T_world_camera is None else scenario.T_world_camera(t)
        est = tracker.step(stamp, make_hands(k, T, T_wc), T_world_camera=T_wc,
                           kinematic_prior=prior)
        log.stamps.append(stamp)
        log.truth.append(T)
        log.estimates.append(est)
    return log


def body_alignment(tracker: HandTracker) -> Array:
    """``T_hand_body``: the rigid transform best aligning the tracker's body model to the hand.

    The estimator's body frame is defined by its own (noisy) initialisation; the true pose of that
    frame is ``T_frame_hand(t) @ T_hand_body`` with ``T_hand_body`` from a Kabsch fit of the body
    points onto the true hand points (noise-free: exact).
    """
    pb = tracker.body_points
    assert pb is not None
    have = np.isfinite(pb).all(axis=1)
    R, t = weighted_kabsch(pb[have], HAND[have], np.ones(int(have.sum())))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def pose_at(T0: Array, twist: Array, amount: float) -> Array:
    """``Exp(amount * twist) @ T0``."""
    return se3_exp(amount * np.asarray(twist, dtype=float)) @ T0
