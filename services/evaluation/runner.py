"""Run every method on every demonstration of a split and collect one row per (demo, method).

Methods, all fed the same synthetic landmark stream:
``regal`` (Regal-style single-landmark screw fit), ``screwmimic_faithful`` and
``screwmimic_fair`` (ScrewMimic-style fits to per-frame Kabsch hand poses), ``ours_no_unc``
(our pipeline with the tracker's uncertainty models and outlier rejection off) and ``ours``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from services.common.protocol import KinematicModel
from services.evaluation import baselines, metrics
from services.evaluation.metrics import JointEstimate
from services.evaluation.pipeline import ablation_config, joint_estimate, run_pipeline
from services.kinematics.config import KinematicsConfig
from services.synthetic.generator import (
    EVALUATION_SPLIT,
    TUNING_SPLIT,
    Demonstration,
    generate,
)
from services.tracker.config import TrackerConfig

METHODS = ("regal", "screwmimic_faithful", "screwmimic_fair", "ours_no_unc", "ours")
LABELS = {
    "regal": "Regal et al. (style)",
    "screwmimic_faithful": "ScrewMimic (faithful)",
    "screwmimic_fair": "ScrewMimic (fair)",
    "ours_no_unc": "Ours w/o unc. models",
    "ours": "Ours",
}
SPLITS = {"evaluation": EVALUATION_SPLIT, "tuning": TUNING_SPLIT,
          "all": sorted(set(EVALUATION_SPLIT) | set(TUNING_SPLIT))}
CONVERGED_DEG = 10.0


@dataclass(frozen=True)
class Row:
    """One method on one demonstration. Angles in degrees, distances in metres."""

    object: str
    participant: int
    seed: int
    method: str
    type_true: str
    type_est: str
    tangent_error_deg: float
    axis_angle_deg: float
    line_distance_m: float
    converge_s: float
    runtime_s: float


@dataclass(frozen=True)
class Settings:
    tracker: TrackerConfig
    kinematics: KinematicsConfig


def _row(demo: Demonstration, method: str, est: JointEstimate, runtime: float,
         converge_s: float = math.nan) -> Row:
    truth = JointEstimate.from_joint(demo.truth.joint)
    positions = demo.truth.grasp_points
    line = (metrics.axis_line_distance(truth, est)
            if truth.type == "revolute" and est.type == "revolute" else math.nan)
    axis = (math.degrees(metrics.axis_angle_error(truth, est))
            if est.type in ("prismatic", "revolute") else math.nan)
    return Row(object=demo.object_name, participant=demo.participant, seed=demo.seed,
               method=method, type_true=truth.type, type_est=est.type,
               tangent_error_deg=math.degrees(metrics.tangent_error(truth, est, positions)),
               axis_angle_deg=axis, line_distance_m=line, converge_s=converge_s,
               runtime_s=runtime)


def _ours(demo: Demonstration, method: str, tracker: TrackerConfig,
          kinematics: KinematicsConfig) -> Row:
    t0 = time.perf_counter()
    result = run_pipeline(demo, tracker, kinematics)
    runtime = time.perf_counter() - t0
    truth = JointEstimate.from_joint(demo.truth.joint)
    estimates = _distinct_estimates(result.history)
    errors = metrics.tangent_errors_over_time(truth, estimates, demo.truth.grasp_points)
    converge = metrics.time_to_converge(result.stamps_ns, errors, CONVERGED_DEG)
    return _row(demo, method, joint_estimate(result.final), runtime,
                math.nan if converge is None else converge)


def _distinct_estimates(history: Sequence[KinematicModel | None]) -> list[JointEstimate | None]:
    """Joint estimates per frame, converting each distinct model once."""
    out: list[JointEstimate | None] = []
    last: tuple[KinematicModel | None, JointEstimate | None] = (None, None)
    for model in history:
        if model is not last[0]:
            last = (model, None if model is None else joint_estimate(model))
        out.append(last[1])
    return out


def _timed(demo: Demonstration, method: str, fn: Callable[[], JointEstimate]) -> Row:
    t0 = time.perf_counter()
    est = fn()
    return _row(demo, method, est, time.perf_counter() - t0)


def _stream(demo: Demonstration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The landmark stream every method sees: stamps, points (NaN = missing), visibility."""
    return demo.stamps_ns, demo.points, demo.visibility


def evaluate_demo(object_name: str, participant: int, seed: int, settings: Settings,
                  methods: Iterable[str] = METHODS) -> list[Row]:
    """All ``methods`` on one generated demonstration."""
    demo = generate(object_name, participant, seed)
    rows = []
    for method in methods:
        if method == "ours":
            rows.append(_ours(demo, method, settings.tracker, settings.kinematics))
        elif method == "ours_no_unc":
            rows.append(_ours(demo, method, ablation_config(settings.tracker),
                              settings.kinematics))
        elif method == "regal":
            rows.append(_timed(demo, method, lambda: baselines.regal_style(*_stream(demo))))
        elif method == "screwmimic_faithful":
            rows.append(_timed(demo, method,
                               lambda: baselines.screwmimic_style(*_stream(demo),
                                                                  variant="faithful")))
        elif method == "screwmimic_fair":
            rows.append(_timed(demo, method,
                               lambda: baselines.screwmimic_style(*_stream(demo),
                                                                  variant="fair")))
        else:
            raise ValueError(f"unknown method {method!r}; known: {list(METHODS)}")
    return rows


def evaluate(split: str = "evaluation", seeds: int = 1, settings: Settings | None = None,
             methods: Iterable[str] = METHODS, jobs: int = 1,
             progress: Callable[[str], None] = print) -> list[Row]:
    """Every method on every (object, participant, seed) of ``split``."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose from {list(SPLITS)}")
    settings = settings or Settings(TrackerConfig(), KinematicsConfig())
    methods = tuple(methods)
    tasks = [(o, p, s) for o, p in SPLITS[split] for s in range(seeds)]
    rows: list[Row] = []
    t0 = time.monotonic()

    def report(i: int, task: tuple[str, int, int], got: list[Row]) -> None:
        errs = "  ".join(f"{r.method} {r.tangent_error_deg:5.1f}" for r in got)
        progress(f"[{i + 1:3d}/{len(tasks)} {time.monotonic() - t0:6.1f} s] "
                 f"{task[0]:<13} p{task[1]} s{task[2]}  {errs}")

    if jobs <= 1:
        for i, task in enumerate(tasks):
            got = evaluate_demo(*task, settings, methods)
            rows.extend(got)
            report(i, task, got)
    else:
        with ProcessPoolExecutor(jobs) as pool:
            futures = [pool.submit(evaluate_demo, *task, settings, methods) for task in tasks]
            for i, (task, future) in enumerate(zip(tasks, futures, strict=True)):
                got = future.result()
                rows.extend(got)
                report(i, task, got)
    return rows
