"""TrackerConfig: Table-I defaults, TOML-friendly fields, checks."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest

from services.tracker.config import TrackerConfig
from services.tracker.landmarks import LandmarkFilterBank

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def test_defaults_are_table_one() -> None:
    c = TrackerConfig()
    assert (c.p0_lm_position_m2, c.p0_lm_velocity_m2ps2) == (0.09, 0.06)
    assert (c.q_lm_position_m2, c.q_lm_velocity_m2ps2) == (0.13, 0.05)
    assert c.r_lm_m2 == 0.05
    assert c.lm_loss_trace_m2 == 0.3
    assert c.visibility_threshold == 0.006
    assert (c.mahalanobis_lm, c.mahalanobis_rb) == (0.19, 0.25)
    assert (c.p0_rb_position_m2, c.p0_rb_rotation_rad2, c.p0_rb_linear_velocity_m2ps2,
            c.p0_rb_angular_velocity_rad2ps2) == (0.05, 0.2, 0.1, 0.2)
    assert (c.q_rb_position_m2, c.q_rb_rotation_rad2, c.q_rb_linear_velocity_m2ps2,
            c.q_rb_angular_velocity_rad2ps2) == (0.75, 3.0, 2.4, 4.8)
    assert c.nominal_dt_s == pytest.approx(1.0 / 30.0)
    assert c.use_uncertainty_models is True


def test_saliency_factors_follow_mediapipe_order() -> None:
    s = TrackerConfig().saliency_factors()
    assert len(s) == 21
    assert s[1:5] == (1.5,) * 4  # thumb CMC, MCP, IP, tip
    for base in (5, 9, 13, 17):  # MCP, PIP, DIP, tip of each finger
        assert s[base:base + 4] == (1.5, 1.0, 1.5, 0.5)


def test_fields_are_plain_and_round_trip_through_toml() -> None:
    c = TrackerConfig()
    lines = []
    for f in dataclasses.fields(c):
        v = getattr(c, f.name)
        assert type(v) in (float, int, bool, str), f.name
        if isinstance(v, bool):
            lines.append(f"{f.name} = {'true' if v else 'false'}")
        elif isinstance(v, str):
            lines.append(f'{f.name} = "{v}"')
        else:
            lines.append(f"{f.name} = {v!r}")
    assert TrackerConfig(**tomllib.loads("\n".join(lines))) == c


@pytest.mark.parametrize("change", [
    {"r_lm_m2": 0.0}, {"q_rb_rotation_rad2": -1.0}, {"mahalanobis_lm": float("nan")},
    {"hand_selection": "both"}, {"min_inliers": 2}, {"init_window_frames": 0},
    {"p0_lm_position_m2": -0.1}, {"visibility_threshold": 1.5}, {"ransac_iterations": 0},
    {"seed": -1}, {"nominal_dt_s": float("inf")},
])
def test_bad_values_are_refused(change: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        TrackerConfig(**change)  # type: ignore[arg-type]


def test_table_one_thresholds_mean_what_the_docstring_says() -> None:
    """Steady state of one landmark filter at 30 Hz under Table I (config docstring numbers)."""
    c = TrackerConfig()
    bank = LandmarkFilterBank(1, c)
    z = np.zeros((1, 3))
    bank.update(z, c.r_lm_m2)
    for _ in range(300):
        bank.predict(c.nominal_dt_s)
        bank.update(z, c.r_lm_m2)
    bank.predict(c.nominal_dt_s)
    innovation_var = bank.pp[0] + c.r_lm_m2
    gate_m = c.mahalanobis_lm * np.sqrt(innovation_var)
    assert innovation_var == pytest.approx(0.223, abs=2e-3)  # S per axis
    assert bank.pp[0] / innovation_var == pytest.approx(0.776, abs=2e-3)  # Kalman gain
    assert gate_m == pytest.approx(0.09, abs=3e-3)  # a ~9 cm gate
    bank.update(z, c.r_lm_m2)
    assert 3 * bank.pp[0] == pytest.approx(0.116, abs=2e-3)  # steady posterior trace
    bank.predict(c.nominal_dt_s)  # one skipped correction ...
    assert 3 * bank.pp[0] >= c.lm_loss_trace_m2  # ... reaches the loss threshold


def test_internal_config_is_table_one_in_physical_units() -> None:
    """``internal()`` multiplies every Table-I covariance by the variance unit and divides every
    Table-I gate by its square root: the Kalman gain and the gate distance in standard deviations
    are unchanged, the covariances are in m^2."""
    c = TrackerConfig()
    u = c.variance_unit_m2
    i = c.internal()
    assert i.variance_unit_m2 == 1.0 and i.internal() is i
    assert i.r_lm_m2 == pytest.approx(0.05 * u) and i.q_rb_rotation_rad2 == pytest.approx(3.0 * u)
    assert i.lm_loss_trace_m2 == pytest.approx(0.3 * u)
    assert i.mahalanobis_lm == pytest.approx(0.19 / np.sqrt(u))
    assert i.ransac_inlier_mahalanobis == pytest.approx(0.25 / np.sqrt(u))
    assert (i.articulation_std_rad, i.depth_variance_factor) == (c.articulation_std_rad,
                                                                 c.depth_variance_factor)
    gains = []
    for cfg in (c, i):
        bank = LandmarkFilterBank(1, cfg)
        z = np.zeros((1, 3))
        bank.update(z, cfg.r_lm_m2)
        for _ in range(100):
            bank.predict(cfg.nominal_dt_s)
            bank.update(z, cfg.r_lm_m2)
        bank.predict(cfg.nominal_dt_s)
        gains.append(bank.pp[0] / (bank.pp[0] + cfg.r_lm_m2))
    # Scale-free in exact arithmetic; the stable recursion keeps round-off at ~eps per step.
    assert gains[0] == pytest.approx(gains[1], rel=1e-12)
    # The unit reading: R_lm is the detector's lateral noise, ~7 mm per axis.
    assert np.sqrt(i.r_lm_m2) == pytest.approx(0.0071, abs=2e-4)


@pytest.mark.parametrize("change", [
    {"variance_unit_m2": 0.0}, {"depth_variance_factor": -1.0}, {"articulation_std_rad": -0.1},
    {"max_correlation_factor": 0.5}, {"template_memory_frames": -1},
    {"template_candidate_frames": -2},
])
def test_bad_physical_terms_are_refused(change: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        TrackerConfig(**change)  # type: ignore[arg-type]


def test_gates_are_the_sigmas_the_docstrings_state() -> None:
    """Every Table-I gate in sigma of the physical innovation it tests (config docstring, "Gates
    in sigma"), and the landmark gate acting exactly there: a measurement 5.9 sigma from the
    prediction is corrected, one at 6.1 sigma is an outlier."""
    c = TrackerConfig()
    sigmas = c.gate_sigmas()
    assert sigmas["mahalanobis_lm"] == pytest.approx(6.0, abs=0.01)
    assert sigmas["mahalanobis_rb"] == pytest.approx(7.9, abs=0.01)
    assert sigmas["ransac_inlier_mahalanobis"] == pytest.approx(7.9, abs=0.01)
    i = c.internal()
    for n_sigma, outlier in ((5.9, False), (6.1, True)):
        bank = LandmarkFilterBank(1, i)
        z = np.zeros((1, 3))
        bank.update(z, i.r_lm_m2)
        for _ in range(100):
            bank.predict(i.nominal_dt_s)
            bank.update(z, i.r_lm_m2)
        bank.predict(i.nominal_dt_s)
        sigma = np.sqrt(bank.pp[0] + i.r_lm_m2)  # per axis, isotropic S
        upd = bank.update(np.array([[n_sigma * sigma, 0.0, 0.0]]), i.r_lm_m2)
        assert upd.mahalanobis[0] == pytest.approx(n_sigma, rel=1e-9)
        assert bool(upd.rejected[0]) is outlier
    assert n_sigma * sigma == pytest.approx(0.091, abs=2e-3)  # ~9 cm at 30 Hz
