"""Table III, harder: perturbed starting models for the key and the window lock, open and closed loop.

The true joint of a synthetic demonstration (participant 3, seed 0) is perturbed: the axis tilted
by ``tilt_deg`` about the axis point nearest the robot's grasp (so a tilt alone does not move the
axis there), then moved by ``offset_mm`` perpendicular to itself; ``n_directions`` evenly spaced
directions per case (the tilt's and the offset's directions, about the true axis, turn together,
the offset a quarter turn ahead). Each perturbed model claims the confidence our estimator
typically publishes (``DIRECTION_STD_DEG``, ``POSITION_STD_M`` at the grasp, P(revolute) = 1):
a wrong model that does not know it is wrong, the hard case. Each runs open loop and closed loop
(:mod:`services.robot_bridge.refinement`) under the bridge's unchanged limits. Success is the
bridge's: no abort and at least ``(1 - success_tolerance)`` of 180 deg reached within 70 N.
"""

from __future__ import annotations

import csv
import math
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import KinematicModel, RevoluteParams
from services.common.se3 import so3_exp
from services.kinematics.filters import tangent_basis
from services.robot_bridge.config import RobotBridgeConfig
from services.robot_bridge.refinement import RefinementConfig

Array = NDArray[np.float64]

CASES: tuple[tuple[float, float], ...] = ((5.0, 0.0), (10.0, 0.0), (20.0, 0.0), (0.0, 5.0),
                                          (0.0, 10.0), (0.0, 20.0), (10.0, 10.0))
OBJECTS = ("key", "window_lock")
DIRECTION_STD_DEG = 2.0
POSITION_STD_M = 0.004


def perturbed_model(obj: object, tilt_deg: float, offset_mm: float, phi_rad: float,
                    grasp: Array) -> KinematicModel:
    """The true revolute joint of ``obj`` (camera frame) perturbed, as a wire model.

    ``grasp`` (3,) the robot's grasp point (camera frame, m); ``phi_rad`` the direction of the
    perturbation about the true axis (module docstring).
    """
    a = np.asarray(obj.axis, float)  # type: ignore[attr-defined]
    c = np.asarray(obj.point, float)  # type: ignore[attr-defined]
    B = tangent_basis(a)
    e1 = B @ np.array([math.cos(phi_rad), math.sin(phi_rad)])
    e2 = np.cross(a, e1)
    foot = c + float((grasp - c) @ a) * a
    a_p = so3_exp(math.radians(tilt_deg) * e1) @ a
    foot_p = foot + offset_mm * 1e-3 * e2
    foot_p = foot_p - float(foot_p @ a_p) * a_p        # closest to the origin, as published
    s = float((grasp - foot_p) @ a_p)
    # Covariance of (b1, b2, point) such that the grasp-position 1-sigma is POSITION_STD_M.
    Bp = tangent_basis(a_p)
    P_perp = np.eye(3) - np.outer(a_p, a_p)
    L = np.zeros((5, 5))
    L[:2, :2] = np.eye(2)
    L[2:, :2] = -s * Bp
    L[2:, 2:] = P_perp
    base = np.diag([math.radians(DIRECTION_STD_DEG) ** 2] * 2 + [POSITION_STD_M ** 2] * 3)
    C = np.zeros((7, 7))
    C[:5, :5] = L @ base @ L.T
    C[5, 5] = C[6, 6] = 1e-4
    probs = {"rigid": 0.0, "prismatic": 0.0, "revolute": 1.0, "disconnected": 0.0}
    return KinematicModel(type="revolute", probabilities=probs, frame_id="camera",
                          revolute=RevoluteParams(axis=a_p, point=foot_p, q=float(
                              obj.demonstrated), dq=0.0, covariance=C))  # type: ignore[attr-defined]


@dataclass(frozen=True)
class PerturbedRow:
    """One perturbed trial: case, loop, outcome, forces, and the final model's error."""

    object: str
    tilt_deg: float
    offset_mm: float
    direction: int
    loop: str                       # "open" or "closed"
    success: bool
    reason: str
    articulated_deg: float
    peak_force_n: float
    mean_force_n: float
    final_axis_error_deg: float     # executed (closed: refined) axis vs truth
    final_position_error_mm: float  # ... its distance from the true axis at the grasp
    # Closed loop, at 90 deg of commanded progress (NaN open loop or when not reached): the
    # refined model (the executed joint's target) and the robot's own estimate, vs truth.
    refined_axis_error_90_deg: float = math.nan
    refined_position_error_90_mm: float = math.nan
    robot_axis_error_90_deg: float = math.nan
    robot_position_error_90_mm: float = math.nan
    engaged_at_s: float = math.nan  # closed loop: when the robot's estimate took over


def _errors(axis: Array, foot: Array, true_axis: Array, true_point: Array,
            grasp: Array) -> tuple[float, float]:
    angle = math.degrees(math.acos(min(1.0, abs(float(axis @ true_axis)))))
    f_true = true_point + float((grasp - true_point) @ true_axis) * true_axis
    f = foot + float((grasp - foot) @ axis) * axis
    d = f - f_true
    return angle, float(np.linalg.norm(d - float(d @ true_axis) * true_axis)) * 1e3


def run_case(object_name: str, tilt_deg: float, offset_mm: float, direction: int,
             n_directions: int, closed: bool, config: RobotBridgeConfig | None = None,
             refinement: RefinementConfig | None = None, seed: int = 0
             ) -> tuple[PerturbedRow, object]:
    """One perturbed trial; the row and the :class:`~services.robot_bridge.simulation.
    SimArticulation`."""
    from services.robot_bridge.simulation import (
        articulate_in_simulation,
        grasp_in_camera,
        object_in_camera,
    )
    from services.synthetic.generator import generate

    obj = object_in_camera(generate(object_name, 3, seed))
    grasp = grasp_in_camera(obj)[:3, 3]
    phi = 2.0 * math.pi * direction / n_directions
    model = perturbed_model(obj, tilt_deg, offset_mm, phi, grasp)
    sim = articulate_in_simulation(model, obj, config=config,
                                   refinement=(refinement or RefinementConfig()) if closed
                                   else None)
    r, ex, spec = sim.result, sim.execution, sim.object_base
    angle = dist = math.nan
    at_90 = [math.nan] * 4
    engaged = math.nan
    if spec is not None and sim.plan is not None:
        g = sim.plan.T_base_grasp[:3, 3]
        truth = (np.asarray(spec.axis_base), np.asarray(spec.point_base), g)
        rec = ex.refinement if ex is not None else None
        if rec is not None:
            axis, foot = rec.axis, rec.foot
            for i, belief in enumerate((rec.checkpoint, rec.robot_at_checkpoint)):
                if belief is not None:
                    at_90[2 * i:2 * i + 2] = _errors(belief.axis, belief.foot, *truth)
            engaged = math.nan if rec.engaged_at_s is None else rec.engaged_at_s
        else:
            axis, foot = sim.plan.joint.axis, sim.plan.joint.point
        angle, dist = _errors(axis, foot, *truth)
    row = PerturbedRow(object_name, tilt_deg, offset_mm, direction,
                       "closed" if closed else "open", r.success, r.reason,
                       math.degrees(r.articulated), r.peak_force_n, r.mean_force_n, angle, dist,
                       *at_90, engaged)
    return row, sim


def _row_of_case(object_name: str, tilt_deg: float, offset_mm: float, direction: int,
                 n_directions: int, closed: bool, config: RobotBridgeConfig | None
                 ) -> PerturbedRow:
    """:func:`run_case`'s row alone (what a worker process sends back)."""
    return run_case(object_name, tilt_deg, offset_mm, direction, n_directions, closed, config)[0]


def run_perturbed(objects: Sequence[str] = OBJECTS,
                  cases: Sequence[tuple[float, float]] = CASES, n_directions: int = 10,
                  config: RobotBridgeConfig | None = None, jobs: int = 1) -> list[PerturbedRow]:
    """Every object x case x direction, open and closed loop; rows in that order. ``jobs`` > 1
    runs them in worker processes. Shows the trials as they finish and how many are left."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from services.common.progress import Progress

    t0 = time.monotonic()
    tasks = [(name, tilt, off, k, n_directions, closed, config) for name in objects
             for tilt, off in cases for k in range(n_directions) for closed in (False, True)]
    rows: list[PerturbedRow | None] = [None] * len(tasks)
    with Progress(len(tasks)) as progress:
        def finished(i: int, r: PerturbedRow) -> None:
            rows[i] = r
            progress.advance(f"{r.object} {r.tilt_deg:g} deg {r.offset_mm:g} mm #{r.direction} "
                             f"{r.loop}: {'ok' if r.success else r.reason} at "
                             f"{r.articulated_deg:.1f} deg, peak {r.peak_force_n:.1f} N")

        if jobs <= 1:
            for i, t in enumerate(tasks):
                finished(i, _row_of_case(*t))
        else:
            with ProcessPoolExecutor(jobs) as pool:
                futures = {pool.submit(_row_of_case, *t): i for i, t in enumerate(tasks)}
                for future in as_completed(futures):
                    finished(futures[future], future.result())
        progress.done(f"{len(tasks)} perturbed trials in {time.monotonic() - t0:.1f} s")
    return [r for r in rows if r is not None]


def table_markdown(rows: Sequence[PerturbedRow], title: str = "",
                   machine: str | None = None) -> str:
    """Success, peak/mean force, final model error and failure reasons per object, case and
    loop; under ``title`` and the ``machine`` sentence when given."""
    out = []
    if title:
        out += [f"# {title}", ""]
    if machine:
        out += [machine, ""]
    out += ["| object | tilt deg | offset mm | loop | success | peak F (N) | mean F (N) | "
            "final axis err (deg) | final pos err (mm) | refined at 90 deg (deg, mm) | "
            "robot's own at 90 deg (deg, mm) | failures |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    keys = sorted({(r.object, r.tilt_deg, r.offset_mm, r.loop) for r in rows})
    for obj, tilt, off, loop in keys:
        rs = [r for r in rows if (r.object, r.tilt_deg, r.offset_mm, r.loop) == (obj, tilt, off,
                                                                                loop)]
        ok = sum(r.success for r in rs)
        ran = [r for r in rs if math.isfinite(r.final_axis_error_deg)]
        reasons = Counter(r.reason for r in rs if not r.success)
        failures = ", ".join(f"{k} x{n}" for k, n in sorted(reasons.items())) or "-"
        axis_err = f"{np.mean([r.final_axis_error_deg for r in ran]):.2f}" if ran else "-"
        pos_err = f"{np.mean([r.final_position_error_mm for r in ran]):.2f}" if ran else "-"
        out.append(f"| {obj} | {tilt:g} | {off:g} | {loop} | {ok}/{len(rs)} | "
                   f"{max(r.peak_force_n for r in rs):.1f} | "
                   f"{np.mean([r.mean_force_n for r in rs]):.1f} | {axis_err} | {pos_err} | "
                   f"{_worst(rs, 'refined')} | {_worst(rs, 'robot')} | {failures} |")
    out += ["", "Peak and mean force over every trial of the row (a trial refused before it "
            "moved counts 0 N); final model errors: mean over the trials that ran (closed loop: "
            "the executed, refined axis at the end; open loop: the perturbed one), at the grasp, "
            "base frame. At 90 deg of commanded progress (closed loop): the worst over the row of "
            "the refined model (what the executed joint moves toward: the starting model until "
            "the robot's estimate is confident enough to take over) and of the robot's own "
            "estimate."]
    return "\n".join(out) + "\n"


def _worst(rows: Sequence[PerturbedRow], which: str) -> str:
    """``"deg, mm"``: the largest errors at 90 deg over ``rows`` (``which``: refined, robot)."""
    deg = [getattr(r, f"{which}_axis_error_90_deg") for r in rows]
    mm = [getattr(r, f"{which}_position_error_90_mm") for r in rows]
    deg = [x for x in deg if math.isfinite(x)]
    mm = [x for x in mm if math.isfinite(x)]
    return f"{max(deg):.2f}, {max(mm):.2f}" if deg and mm else "-"


CSV_FILE = "perturbed.csv"
TABLE_FILE = "perturbed.md"


def write_report(rows: Sequence[PerturbedRow], out: Path, title: str,
                 machine: str | None = None) -> tuple[Path, Path]:
    """``perturbed.md`` (:func:`table_markdown`) and ``perturbed.csv`` (one row per trial)."""
    out.mkdir(parents=True, exist_ok=True)
    table = out / TABLE_FILE
    table.write_text(table_markdown(rows, title, machine))
    path = out / CSV_FILE
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=[x.name for x in fields(PerturbedRow)])
        w.writeheader()
        for r in rows:
            w.writerow(asdict(r))
    return table, path


def read_rows(path: Path) -> list[PerturbedRow]:
    """The rows of a ``perturbed.csv`` written by :func:`write_report`."""
    kinds = {x.name: x.type for x in fields(PerturbedRow)}
    rows = []
    with open(path, newline="") as f:
        for d in csv.DictReader(f):
            rows.append(PerturbedRow(**{k: _parse(v, kinds[k]) for k, v in d.items()}))
    return rows


def _parse(text: str, kind: object) -> object:
    if kind in (bool, "bool"):
        return text == "True"
    if kind in (int, "int"):
        return int(text)
    if kind in (float, "float"):
        return float(text)
    return text


def parse_cases(text: str) -> tuple[tuple[float, float], ...]:
    """``"10:10,20:0"`` -> ((10.0, 10.0), (20.0, 0.0)): tilt deg : offset mm per case."""
    cases = []
    for item in text.split(","):
        if not item.strip():
            continue
        try:
            tilt, off = (float(x) for x in item.split(":"))
        except ValueError:
            raise ValueError(f"a perturbed case is TILT_DEG:OFFSET_MM (e.g. 10:10), got "
                             f"{item.strip()!r}") from None
        if not (math.isfinite(tilt) and math.isfinite(off) and tilt >= 0.0 and off >= 0.0):
            raise ValueError(f"a perturbed case needs a finite tilt and offset >= 0, got "
                             f"{item.strip()!r}")
        cases.append((tilt, off))
    if not cases:
        raise ValueError("no perturbed case given (e.g. --cases 10:10)")
    return tuple(cases)


def describe_machine() -> str:
    """One sentence on the machine that ran the trials (as bench/results/README.md does)."""
    from bench.common import machine

    m = machine()
    return (f"Machine: {m['cpu']}, {m['cores']} cores, {m['memory_gib']} GiB, {m['os']}, "
            f"Python {m['python']}, MuJoCo {m['packages'].get('mujoco', '?')}, commit "
            f"{m['commit']}, {m['date']}, load average {m['load_avg_1_5_15']} (1/5/15 min) when "
            "the results were written.")
