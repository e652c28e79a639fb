"""Free hand motion: minimum-jerk legs between hand poses, and tremor of a still hand.

Poses are 4x4 ``T_o_hand`` in a static frame ``o`` (metres). A leg moves the hand from ``T0`` to
``T1``: the **grasp point** ``g_h`` (hand frame) travels on a straight line plus a sideways bump
``b sin(pi s)`` (human reaches curve slightly), the orientation turns on the geodesic
``R0 Exp(s log(R0' R1))``, both with the minimum-jerk progress ``s(tau)`` of
:func:`services.synthetic.motion.minimum_jerk` (Flash & Hogan 1985), so the speed is bell-shaped
and the hand decelerates into the end pose.

Leg durations follow distance: ``(0.25 s + 1.2 s/m * d) * U(0.8, 1.25) * participant factor``,
never faster than a peak grasp-point speed of ``MAX_HAND_SPEED_M_S`` (1 m/s; a min-jerk leg peaks
at ``1.875 d / T``). Our choice: it gives 0.4-0.8 s for reaches of 10-30 cm, the range of
everyday reaching.

Tremor (still hands)
    A hand held still shows a slow postural drift and physiological tremor at 8-12 Hz. Holding a
    fixed handle: drift 1 mm / 0.5 deg (per axis, Ornstein-Uhlenbeck, time constant 1 s) and
    tremor 0.2 mm / 0.15 deg; an unsupported hand at rest: drift 2.5 mm / 1.2 deg and tremor
    0.4 mm / 0.3 deg. Orders of magnitude of postural tremor and sway (assumptions, not fitted
    to a data set); the tracker's noise at 0.5-1 m is larger either way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from services.common.se3 import so3_exp, so3_log
from services.synthetic.hand import smooth_noise
from services.synthetic.motion import minimum_jerk

Array = NDArray[np.float64]

MAX_HAND_SPEED_M_S = 1.0
PEAK_SPEED_FACTOR = 1.875  # max ds/dtau of the minimum-jerk profile


@dataclass(frozen=True)
class TremorLevel:
    """Standard deviations per axis of drift and tremor (metres, radians)."""

    drift_m: float
    drift_rad: float
    tremor_m: float
    tremor_rad: float


HOLD_TREMOR = TremorLevel(drift_m=0.001, drift_rad=np.deg2rad(0.5), tremor_m=0.0002,
                          tremor_rad=np.deg2rad(0.15))
REST_TREMOR = TremorLevel(drift_m=0.0025, drift_rad=np.deg2rad(1.2), tremor_m=0.0004,
                          tremor_rad=np.deg2rad(0.3))


def leg_duration(rng: np.random.Generator, distance_m: float, duration_factor: float) -> float:
    """Duration [s] of a free leg over ``distance_m`` (module docstring)."""
    d = (0.25 + 1.2 * distance_m) * rng.uniform(0.8, 1.25) * duration_factor
    return max(d, PEAK_SPEED_FACTOR * distance_m / MAX_HAND_SPEED_M_S)


def with_grasp_point(R: Array, c: Array, g_h: Array) -> Array:
    """Pose (4, 4) with rotation ``R`` whose hand-frame point ``g_h`` lies at ``c``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ g_h
    return T


def leg_poses(T0: Array, T1: Array, s: Array, g_h: Array, bump: Array) -> Array:
    """Poses (N, 4, 4) along a leg at progress ``s`` (N,) in [0, 1] (module docstring).

    ``bump`` (3,): the sideways offset of the grasp point at mid-leg [m] (0 for a straight leg).
    """
    c0 = T0[:3, :3] @ g_h + T0[:3, 3]
    c1 = T1[:3, :3] @ g_h + T1[:3, 3]
    w = so3_log(T0[:3, :3].T @ T1[:3, :3])
    s = np.asarray(s, dtype=float)
    R = T0[:3, :3][None] @ so3_exp(s[:, None] * w[None])
    c = c0[None] + s[:, None] * (c1 - c0)[None] + np.sin(np.pi * s)[:, None] * bump[None]
    out = np.tile(np.eye(4), (len(s), 1, 1))
    out[:, :3, :3] = R
    out[:, :3, 3] = c - np.einsum("nij,j->ni", R, g_h)
    return out


def progress(t: Array, t0: float, t1: float) -> Array:
    """Minimum-jerk progress (N,) of times ``t`` on the leg [t0, t1]."""
    return minimum_jerk((np.asarray(t, dtype=float) - t0) / (t1 - t0))


def tremor(rng: np.random.Generator, t: Array, level: TremorLevel) -> Array:
    """Pose perturbations (N, 6) ``[rotation vector, translation]`` of a still hand at ``t``.

    Drift: unit OU (time constant 1 s) scaled by the drift level; tremor: a cosine at a frequency
    drawn in 8-12 Hz with a random phase and a slowly varying (OU, 0.5 s) amplitude per axis,
    unit RMS before scaling by the tremor level.
    """
    t = np.asarray(t, dtype=float)
    drift = smooth_noise(rng, t, 1.0, 6)
    f = rng.uniform(8.0, 12.0)
    phase = rng.uniform(0.0, 2.0 * np.pi, 6)
    amp = np.sqrt(2.0) * np.abs(smooth_noise(rng, t, 0.5, 6))  # unit RMS of amp * cos
    osc = amp * np.cos(2.0 * np.pi * f * t[:, None] + phase[None])
    scale_drift = np.array([level.drift_rad] * 3 + [level.drift_m] * 3)
    scale_tremor = np.array([level.tremor_rad] * 3 + [level.tremor_m] * 3)
    out: Array = drift * scale_drift + osc * scale_tremor
    return out


def perturbed(T: Array, pert: Array, g_h: Array) -> Array:
    """Poses (N, 4, 4): ``T`` (N, 4, 4) moved by ``pert`` (N, 6) about the hand point ``g_h``.

    The rotation part turns the hand about its grasp point; the translation is in the frame of
    ``T`` (the hand frame), so a fixed handle stays inside the fist.
    """
    R = so3_exp(pert[:, :3])
    local = np.tile(np.eye(4), (len(pert), 1, 1))
    local[:, :3, :3] = R
    local[:, :3, 3] = g_h[None] - np.einsum("nij,j->ni", R, g_h) + pert[:, 3:]
    out: Array = T @ local
    return out
