"""Run every method on every demonstration of a split and collect one row per (demo, method).

Methods, all fed the same synthetic landmark stream:
``regal`` (Regal-style single-landmark screw fit), ``screwmimic_faithful`` and
``screwmimic_fair`` (ScrewMimic-style fits to per-frame Kabsch hand poses), ``ours_no_unc``
(our pipeline with the tracker's uncertainty models and outlier rejection off) and ``ours``;
on request also ``ours_no_kinematic_prior`` (ours without the tracker's kinematic motion model,
``TrackerConfig.use_kinematic_prior``).
Our two methods also give a per-frame :class:`History` (tangent error and the true type's
probability over time) for the convergence plot.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass

import numpy as np

from services.common.progress import Progress
from services.common.protocol import KinematicModel
from services.evaluation import baselines, metrics
from services.evaluation.metrics import JointEstimate
from services.evaluation.pipeline import (
    ablation_config,
    joint_estimate,
    no_kinematic_prior_config,
    run_pipeline,
)
from services.kinematics.config import KinematicsConfig
from services.synthetic.generator import (
    EVALUATION_SPLIT,
    TUNING_SPLIT,
    Demonstration,
    generate,
)
from services.tracker.config import TrackerConfig

METHODS = ("regal", "screwmimic_faithful", "screwmimic_fair", "ours_no_unc", "ours")
OPTIONAL_METHODS = ("ours_no_kinematic_prior",)  # run only when asked for (--methods)
LABELS = {
    "regal": "Regal et al. (style)",
    "screwmimic_faithful": "ScrewMimic (faithful)",
    "screwmimic_fair": "ScrewMimic (fair)",
    "ours_no_unc": "Ours w/o unc. models",
    "ours_no_kinematic_prior": "Ours w/o kin. prior",
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


@dataclass(frozen=True, eq=False)
class History:
    """One of our methods on one demonstration, frame by frame (M frames).

    ``t_s`` (M,) seconds since the demonstration's first frame; ``tangent_error_deg`` (M,) of the
    model held after each frame; ``p_true`` (M,) that model's probability of the true joint type.
    Both NaN before the first model.
    """

    object: str
    participant: int
    seed: int
    method: str
    type_true: str
    t_s: np.ndarray
    tangent_error_deg: np.ndarray
    p_true: np.ndarray


@dataclass(frozen=True)
class Evaluation:
    """What :func:`run_evaluation` returns: one row per (demo, method), in task order, and the
    per-frame histories of our methods."""

    rows: list[Row]
    histories: list[History]


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
          kinematics: KinematicsConfig) -> tuple[Row, History]:
    t0 = time.perf_counter()
    result = run_pipeline(demo, tracker, kinematics)
    runtime = time.perf_counter() - t0
    truth = JointEstimate.from_joint(demo.truth.joint)
    estimates = _distinct_estimates(result.history)
    errors = metrics.tangent_errors_over_time(truth, estimates, demo.truth.grasp_points)
    converge = metrics.time_to_converge(result.stamps_ns, errors, CONVERGED_DEG)
    row = _row(demo, method, joint_estimate(result.final), runtime,
               math.nan if converge is None else converge)
    no_model = np.array([m is None for m in result.history], dtype=bool)
    p_true = np.array([math.nan if m is None else float(m.probabilities.get(truth.type, 0.0))
                       for m in result.history])
    history = History(object=demo.object_name, participant=demo.participant, seed=demo.seed,
                      method=method, type_true=truth.type,
                      t_s=(result.stamps_ns - result.stamps_ns[0]) * 1e-9,
                      tangent_error_deg=np.where(no_model, math.nan, np.degrees(errors)),
                      p_true=p_true)
    return row, history


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


def run_demo(object_name: str, participant: int, seed: int, settings: Settings,
             methods: Iterable[str] = METHODS) -> tuple[list[Row], list[History]]:
    """All ``methods`` on one generated demonstration: their rows, and the per-frame histories
    of our methods (the baselines fit once, at the end, and have none)."""
    demo = generate(object_name, participant, seed)
    rows: list[Row] = []
    histories: list[History] = []
    for method in methods:
        if method in ("ours", "ours_no_unc", "ours_no_kinematic_prior"):
            tracker = {"ours": settings.tracker,
                       "ours_no_unc": ablation_config(settings.tracker),
                       "ours_no_kinematic_prior": no_kinematic_prior_config(settings.tracker)
                       }[method]
            row, history = _ours(demo, method, tracker, settings.kinematics)
            rows.append(row)
            histories.append(history)
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
            raise ValueError(f"unknown method {method!r}; known: "
                             f"{list(METHODS + OPTIONAL_METHODS)}")
    return rows, histories


def evaluate_demo(object_name: str, participant: int, seed: int, settings: Settings,
                  methods: Iterable[str] = METHODS) -> list[Row]:
    """All ``methods`` on one generated demonstration (the rows of :func:`run_demo`)."""
    return run_demo(object_name, participant, seed, settings, methods)[0]


def run_evaluation(split: str = "evaluation", seeds: int = 1, settings: Settings | None = None,
                   methods: Iterable[str] = METHODS, jobs: int = 1,
                   progress: Progress | None = None) -> Evaluation:
    """Every method on every (object, participant, seed) of ``split``, in that order.

    ``progress`` (optional) counts the demonstrations as they finish, with their errors.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose from {list(SPLITS)}")
    settings = settings or Settings(TrackerConfig(), KinematicsConfig())
    methods = tuple(methods)
    tasks = [(o, p, s) for o, p in SPLITS[split] for s in range(seeds)]
    if progress is not None:
        progress.total = len(tasks)
    results: list[tuple[list[Row], list[History]] | None] = [None] * len(tasks)

    def finished(i: int, result: tuple[list[Row], list[History]]) -> None:
        results[i] = result
        if progress is not None:
            o, p, s = tasks[i]
            errors = ", ".join(f"{r.method} {r.tangent_error_deg:.1f}" for r in result[0])
            progress.advance(f"{o} p{p} s{s}: {errors} deg")

    if jobs <= 1:
        for i, task in enumerate(tasks):
            finished(i, run_demo(*task, settings, methods))
    else:
        with ProcessPoolExecutor(jobs) as pool:
            futures = {pool.submit(run_demo, *task, settings, methods): i
                       for i, task in enumerate(tasks)}
            for future in as_completed(futures):
                finished(futures[future], future.result())
    done = [r for r in results if r is not None]
    return Evaluation(rows=[row for rows, _ in done for row in rows],
                      histories=[h for _, hs in done for h in hs])


def evaluate(split: str = "evaluation", seeds: int = 1, settings: Settings | None = None,
             methods: Iterable[str] = METHODS, jobs: int = 1,
             progress: Progress | None = None) -> list[Row]:
    """The rows of :func:`run_evaluation`."""
    return run_evaluation(split, seeds, settings, methods, jobs, progress).rows
