"""Human articulation motion and camera frame timing.

Articulation
    A demonstration is a sequence of segments, each either a rest (``q`` constant) or a
    minimum-jerk stroke ``q(t) = q0 + (q1 - q0) s(tau)``, ``s = 10 tau^3 - 15 tau^4 + 6 tau^5``,
    ``tau = (t - t0) / T`` (Flash & Hogan, "The coordination of arm movements: an experimentally
    confirmed mathematical model", J. Neurosci. 5(7), 1985: point-to-point human reaching
    minimises jerk). The plan: rest 0.4-1.0 s; the opening stroke to the demonstrated range
    (split into two strokes with a 0.2-0.6 s pause with probability 0.35: humans re-adjust on long
    turns); rest 0.3-0.8 s; with probability 0.5 a return stroke of 30-100 % of the range and a
    final rest. Durations scale with the participant, a per-stroke factor U(0.85, 1.2) and the
    caller's ``duration_scale``. ``q(0) = 0``.

Frame timing
    The Azure Kinect streams colour at 30 fps (Microsoft, "Azure Kinect DK hardware
    specifications": 1280x720 at up to 30 fps). Frame ``k`` is exposed at ``k / 30 s`` plus a
    capture jitter N(0, 1 ms) clipped to +-3 ms (an assumption: device timestamps are
    microsecond-resolution, the residual models exposure/host scheduling); stamps are that
    capture time, so the truth is evaluated at the exact stamp. Frames are dropped (absent from
    the stream: USB/processing hiccups or no hand detected) independently with probability 0.01,
    and in bursts of 2-6 frames starting with probability 0.004 per frame (assumptions; no
    published rate for this pipeline).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

FRAME_RATE_HZ = 30.0
JITTER_STD_S = 1.0e-3
JITTER_CLIP_S = 3.0e-3
DROP_PROBABILITY = 0.01
BURST_PROBABILITY = 0.004
BURST_LENGTH = (2, 6)


def minimum_jerk(tau: Array) -> Array:
    """Minimum-jerk position profile ``s(tau)`` (same shape as ``tau``), clipped to [0, 1]."""
    x = np.clip(tau, 0.0, 1.0)
    return x * x * x * (10.0 - 15.0 * x + 6.0 * x * x)


def minimum_jerk_rate(tau: Array) -> Array:
    """Derivative ``ds/dtau`` of :func:`minimum_jerk`; zero outside [0, 1]."""
    x = np.clip(tau, 0.0, 1.0)
    return 30.0 * x * x * (1.0 - x) ** 2


@dataclass(frozen=True)
class Segment:
    """``q`` goes from ``q0`` to ``q1`` on [t0, t1] [s] (a rest when q0 == q1)."""

    t0: float
    t1: float
    q0: float
    q1: float


@dataclass(frozen=True)
class ArticulationPlan:
    """Piecewise rest / minimum-jerk articulation, ``q`` in rad or m."""

    segments: tuple[Segment, ...]

    @property
    def duration_s(self) -> float:
        """End time of the last segment [s]."""
        return self.segments[-1].t1

    def evaluate(self, t: Array) -> tuple[Array, Array]:
        """Joint value ``q`` (N,) and rate ``dq/dt`` (N,) at times ``t`` (N,) [s]."""
        t = np.asarray(t, dtype=float)
        q = np.full(t.shape, self.segments[0].q0)
        dq = np.zeros(t.shape)
        for s in self.segments:
            mask = t >= s.t0
            span = s.t1 - s.t0
            tau = (t[mask] - s.t0) / span
            q[mask] = s.q0 + (s.q1 - s.q0) * minimum_jerk(tau)
            dq[mask] = (s.q1 - s.q0) / span * minimum_jerk_rate(tau)
        return q, dq


def plan_articulation(rng: np.random.Generator, q_range: float, stroke_duration_s: float,
                      duration_scale: float = 1.0) -> ArticulationPlan:
    """Draw a rest/stroke plan covering ``q`` in [0, q_range] (module docstring)."""
    if q_range <= 0.0 or stroke_duration_s <= 0.0 or duration_scale <= 0.0:
        raise ValueError("range, stroke duration and duration scale must be positive")
    segs: list[Segment] = []
    t = 0.0
    q = 0.0

    def rest(lo: float, hi: float) -> None:
        nonlocal t
        d = rng.uniform(lo, hi) * duration_scale
        segs.append(Segment(t, t + d, q, q))
        t += d

    def stroke(target: float) -> None:
        nonlocal t, q
        frac = abs(target - q) / q_range
        d = stroke_duration_s * (0.35 + 0.65 * frac) * rng.uniform(0.85, 1.2) * duration_scale
        segs.append(Segment(t, t + d, q, target))
        t += d
        q = target

    rest(0.4, 1.0)
    if rng.random() < 0.35:
        stroke(q_range * rng.uniform(0.4, 0.7))
        rest(0.2, 0.6)
    stroke(q_range)
    rest(0.3, 0.8)
    if rng.random() < 0.5:
        stroke(q_range * (1.0 - rng.uniform(0.3, 1.0)))
        rest(0.3, 0.6)
    return ArticulationPlan(tuple(segs))


@dataclass(frozen=True, eq=False)
class FrameTimes:
    """Delivered camera frames of a stream of ``n_nominal`` frames at 30 Hz."""

    # Index of each delivered frame on the nominal 30 Hz grid (M,), increasing.
    frame_index: NDArray[np.int64]
    # Capture time of each delivered frame (M,) [s] from the start of the demonstration.
    t: Array
    n_nominal: int


def sample_frame_times(rng: np.random.Generator, duration_s: float,
                       rate_hz: float = FRAME_RATE_HZ) -> FrameTimes:
    """Frame grid over [0, duration_s] with capture jitter and dropped frames (module docstring).

    The first frame is never dropped, so the stream starts at the rest pose ``q = 0``.
    """
    n = int(np.floor(duration_s * rate_hz)) + 1
    t = np.arange(n) / rate_hz
    t = t + np.clip(rng.normal(0.0, JITTER_STD_S, n), -JITTER_CLIP_S, JITTER_CLIP_S)
    t[0] = 0.0
    keep = rng.random(n) >= DROP_PROBABILITY
    starts = np.flatnonzero(rng.random(n) < BURST_PROBABILITY)
    for s in starts:
        length = int(rng.integers(BURST_LENGTH[0], BURST_LENGTH[1] + 1))
        keep[s:s + length] = False
    keep[0] = True
    idx = np.flatnonzero(keep).astype(np.int64)
    return FrameTimes(frame_index=idx, t=t[idx], n_nominal=n)


def shifted(plan: ArticulationPlan, dt_s: float) -> ArticulationPlan:
    """``plan`` delayed by ``dt_s`` [s] (same joint values)."""
    return ArticulationPlan(tuple(Segment(s.t0 + dt_s, s.t1 + dt_s, s.q0, s.q1)
                                  for s in plan.segments))


def plan_strokes(rng: np.random.Generator, q_start: float, targets: tuple[float, ...],
                 q_range: float, stroke_duration_s: float, *,
                 first_rest_s: tuple[float, float] = (0.4, 1.0),
                 between_rest_s: tuple[float, float] = (0.2, 0.6),
                 last_rest_s: tuple[float, float] = (0.3, 0.8),
                 duration_scale: float = 1.0) -> ArticulationPlan:
    """A rest, min-jerk strokes from ``q_start`` through ``targets`` with rests between, a rest.

    Strokes last as in :func:`plan_articulation` (``stroke_duration_s`` for a full ``q_range``,
    shorter for shorter strokes, times U(0.85, 1.2) and ``duration_scale``). Starts at t = 0.
    """
    if q_range <= 0.0 or stroke_duration_s <= 0.0 or duration_scale <= 0.0:
        raise ValueError("range, stroke duration and duration scale must be positive")
    segs: list[Segment] = []
    t = 0.0
    q = q_start

    def rest(bounds: tuple[float, float]) -> None:
        nonlocal t
        d = rng.uniform(*bounds) * duration_scale
        segs.append(Segment(t, t + d, q, q))
        t += d

    rest(first_rest_s)
    for i, target in enumerate(targets):
        if i:
            rest(between_rest_s)
        frac = abs(target - q) / q_range
        d = stroke_duration_s * (0.35 + 0.65 * frac) * rng.uniform(0.85, 1.2) * duration_scale
        segs.append(Segment(t, t + d, q, target))
        t += d
        q = target
    rest(last_rest_s)
    return ArticulationPlan(tuple(segs))


def rest_plan(q: float, duration_s: float) -> ArticulationPlan:
    """``q`` held for ``duration_s`` [s] from t = 0 (a still hold)."""
    return ArticulationPlan((Segment(0.0, duration_s, q, q),))
