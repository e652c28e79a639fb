"""Segmentation quality: estimated contact phases against the true ones
(docs/evaluation.md#segmentation-quality).

Input is a per-frame phase decision, ``contact`` (N,) bool (True = the hand is judged to be in
contact at that frame), on the stamps ``stamps_ns`` (N,) int [ns] of the stream it was made
on; the truth is the list of contact phases as ``(onset_ns, release_ns)`` (the fingers closed,
the fingers start to open; ``GroundTruth.segments``). Errors are in milliseconds, signed
(estimate minus truth: a positive onset error is a late onset, a positive release error a late
release).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


def contact_intervals(contact: ArrayLike) -> list[tuple[int, int]]:
    """Runs of True in ``contact`` (N,) as ``(first, last)`` row pairs, inclusive, in order."""
    c = np.asarray(contact, dtype=bool).reshape(-1)
    if len(c) == 0:
        return []
    edges = np.diff(np.concatenate([[False], c, [False]]).astype(np.int8))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1
    return [(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]


def as_contact(phases: ArrayLike) -> np.ndarray:
    """A pipeline's per-frame phase decision as bool (N,): "contact"/"free" strings, or bool."""
    p = np.asarray(phases)
    if p.dtype.kind in ("U", "S", "O"):
        values = {str(v) for v in np.unique(p)}
        unknown = values - {"contact", "free"}
        if unknown:
            raise ValueError(f"phases must be 'contact' or 'free', got {sorted(unknown)}")
        return np.asarray(p == "contact", dtype=bool)
    if p.dtype.kind != "b":
        raise ValueError(f"phases must be strings or bools, got dtype {p.dtype}")
    return p.astype(bool)


@dataclass(frozen=True)
class PhaseScore:
    """The phases of one stream against the truth.

    ``onset_errors_ms``/``release_errors_ms``: one per true phase that was found (in the order
    of the true phases), signed; ``missed``: true phases no estimated phase overlaps;
    ``extra``: estimated phases matched to no true phase (false phases, and the extra pieces of
    a true phase split in several); ``duration_s``: the stream's length; ``free_s``: the time
    the truth is free (the stream minus the true phases).
    """

    onset_errors_ms: tuple[float, ...]
    release_errors_ms: tuple[float, ...]
    missed: int
    extra: int
    duration_s: float
    free_s: float

    @property
    def extra_per_minute_free(self) -> float:
        """Estimated phases matched to no true phase per minute of true free motion (NaN when
        the stream has none)."""
        return self.extra / (self.free_s / 60.0) if self.free_s > 0.0 else math.nan


def match_intervals(truth: Sequence[tuple[int, int]], est: Sequence[tuple[int, int]]
                    ) -> list[int | None]:
    """For each true interval ``(start, end)`` the index of the estimated interval that
    overlaps it longest, or None.

    Each estimated interval serves at most one true interval: the one it overlaps longest (ties:
    the earlier); a true interval then takes the longest of the estimated ones it was given
    (ties: the earlier). Intervals that only touch (a one-sample interval at the edge) match as
    a last resort. Units are the caller's (stamps in ns here).
    """
    overlap = np.zeros((len(truth), len(est)))
    for i, (onset, release) in enumerate(truth):
        if release < onset:
            raise ValueError(f"true interval {i} ends before it starts")
        for j, (a, b) in enumerate(est):
            overlap[i, j] = max(0, min(release, b) - max(onset, a))
            if overlap[i, j] == 0 and a <= release and b >= onset:
                overlap[i, j] = 0.5  # touches
    owner = [int(np.argmax(overlap[:, j])) if len(truth) and overlap[:, j].max() > 0 else -1
             for j in range(len(est))]
    out: list[int | None] = []
    for i in range(len(truth)):
        mine = [j for j in range(len(est)) if owner[j] == i]
        out.append(max(mine, key=lambda k: (overlap[i, k], -k)) if mine else None)
    return out


def score_phases(stamps_ns: ArrayLike, contact: ArrayLike,
                 truth: Sequence[tuple[int, int]]) -> PhaseScore:
    """Match the estimated contact phases of ``contact`` with the true ``(onset_ns,
    release_ns)`` phases (:func:`match_intervals`) and measure onset and release errors
    (module docstring). An estimated phase runs from the stamp of its first contact frame to
    the stamp of its last.
    """
    st = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    c = np.asarray(contact, dtype=bool).reshape(-1)
    if st.shape != c.shape or len(st) == 0:
        raise ValueError("stamps and phases must be non-empty and of equal length")
    est = [(int(st[a]), int(st[b])) for a, b in contact_intervals(c)]
    matched = match_intervals(truth, est)
    onsets = [(est[j][0] - onset) * 1e-6 for (onset, _), j in zip(truth, matched, strict=True)
              if j is not None]
    releases = [(est[j][1] - release) * 1e-6
                for (_, release), j in zip(truth, matched, strict=True) if j is not None]
    found = sum(j is not None for j in matched)
    duration = float(st[-1] - st[0]) * 1e-9
    in_truth = sum(max(0, min(r, int(st[-1])) - max(o, int(st[0]))) for o, r in truth) * 1e-9
    return PhaseScore(onset_errors_ms=tuple(onsets), release_errors_ms=tuple(releases),
                      missed=len(truth) - found, extra=len(est) - found, duration_s=duration,
                      free_s=max(0.0, duration - in_truth))


@dataclass(frozen=True)
class PhaseSummary:
    """Segmentation quality over streams: absolute onset and release errors [ms] (median, 90th
    percentile; NaN without any), phases found / true, extra phases per minute of free motion."""

    onset_median_ms: float
    onset_p90_ms: float
    release_median_ms: float
    release_p90_ms: float
    found: int
    true: int
    extra: int
    extra_per_minute_free: float


def summarise_phases(scores: Sequence[PhaseScore]) -> PhaseSummary:
    """:class:`PhaseSummary` of several streams (errors pooled over their phases)."""
    onset = np.abs([e for s in scores for e in s.onset_errors_ms])
    release = np.abs([e for s in scores for e in s.release_errors_ms])

    def stats(v: np.ndarray) -> tuple[float, float]:
        return ((float(np.median(v)), float(np.percentile(v, 90))) if len(v)
                else (math.nan, math.nan))

    found = sum(len(s.onset_errors_ms) for s in scores)
    free_min = sum(s.free_s for s in scores) / 60.0
    extra = sum(s.extra for s in scores)
    return PhaseSummary(*stats(onset), *stats(release), found=found,
                        true=found + sum(s.missed for s in scores), extra=extra,
                        extra_per_minute_free=extra / free_min if free_min > 0 else math.nan)
