"""Segmentation quality on synthetic per-frame phase decisions
(docs/evaluation.md#segmentation-quality)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.evaluation.phase_metrics import (
    as_contact,
    contact_intervals,
    match_intervals,
    score_phases,
    summarise_phases,
)

FRAME_NS = 33_333_333


def _stream(n: int) -> np.ndarray:
    return np.arange(n, dtype=np.int64) * FRAME_NS + 10**9


def _phase(stamps: np.ndarray, first: int, last: int) -> np.ndarray:
    c = np.zeros(len(stamps), dtype=bool)
    c[first:last + 1] = True
    return c


def test_contact_intervals() -> None:
    assert contact_intervals([]) == []
    assert contact_intervals([0, 0, 0]) == []
    assert contact_intervals([1, 1, 0, 1, 0, 0, 1]) == [(0, 1), (3, 3), (6, 6)]


def test_late_onset_and_early_release_in_milliseconds() -> None:
    st = _stream(300)
    truth = [(int(st[60]), int(st[200]))]
    contact = _phase(st, 63, 198)  # found 3 frames late, let go 2 frames early
    s = score_phases(st, contact, truth)
    assert s.onset_errors_ms == pytest.approx((3 * FRAME_NS * 1e-6,))
    assert s.release_errors_ms == pytest.approx((-2 * FRAME_NS * 1e-6,))
    assert (s.missed, s.extra) == (0, 0)
    assert s.free_s == pytest.approx(s.duration_s - 140 * FRAME_NS * 1e-9)


def test_false_split_and_missed_phases() -> None:
    st = _stream(600)
    truth = [(int(st[100]), int(st[200])), (int(st[300]), int(st[400]))]
    contact = _phase(st, 100, 140) | _phase(st, 150, 200) | _phase(st, 500, 520)
    s = score_phases(st, contact, truth)
    # the first phase is split: the longer piece matches, the other is extra; the second is
    # missed; the phase in free motion is extra
    assert s.onset_errors_ms == pytest.approx((50 * FRAME_NS * 1e-6,))
    assert s.release_errors_ms == pytest.approx((0.0,))
    assert (s.missed, s.extra) == (1, 2)
    summary = summarise_phases([s])
    assert (summary.found, summary.true, summary.extra) == (1, 2, 2)
    assert summary.extra_per_minute_free == pytest.approx(2 / (s.free_s / 60.0))


def test_free_stream_counts_every_phase_as_false() -> None:
    st = _stream(1800)  # 60 s
    contact = _phase(st, 10, 20) | _phase(st, 900, 950)
    s = score_phases(st, contact, [])
    assert (s.missed, s.extra) == (0, 2) and s.onset_errors_ms == ()
    assert s.free_s == pytest.approx(s.duration_s)
    assert s.extra_per_minute_free == pytest.approx(2.0 / (s.duration_s / 60.0))
    quiet = score_phases(st, np.zeros(1800, bool), [])
    assert quiet.extra == 0 and quiet.extra_per_minute_free == 0.0


def test_summary_pools_absolute_errors() -> None:
    st = _stream(300)
    truth = [(int(st[50]), int(st[150]))]
    scores = [score_phases(st, _phase(st, 50 + d, 150 - d), truth) for d in (-3, 0, 3, 6)]
    s = summarise_phases(scores)
    frame_ms = FRAME_NS * 1e-6
    assert s.onset_median_ms == pytest.approx(3 * frame_ms)  # |-3|, 0, 3, 6 -> median 3
    assert s.release_median_ms == pytest.approx(3 * frame_ms)
    assert s.onset_p90_ms == pytest.approx(np.percentile([3, 0, 3, 6], 90) * frame_ms)
    empty = summarise_phases([])
    assert math.isnan(empty.onset_median_ms) and math.isnan(empty.extra_per_minute_free)


def test_match_intervals_gives_each_estimate_to_one_truth() -> None:
    # one long estimate over two true phases serves the one it overlaps longest
    assert match_intervals([(0, 10), (12, 40)], [(5, 39)]) == [None, 0]
    assert match_intervals([(0, 10)], [(10, 10)]) == [0]  # touching counts, as a last resort
    with pytest.raises(ValueError, match="ends before"):
        match_intervals([(5, 1)], [])


def test_as_contact() -> None:
    np.testing.assert_array_equal(as_contact(np.array(["free", "contact", "free"])),
                                  [False, True, False])
    np.testing.assert_array_equal(as_contact(np.array([True, False])), [True, False])
    with pytest.raises(ValueError, match="'contact' or 'free'"):
        as_contact(np.array(["free", "touch"]))
    with pytest.raises(ValueError, match="dtype"):
        as_contact(np.array([0.5, 1.0]))
