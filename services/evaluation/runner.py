"""Run every method on every demonstration of a split and collect what the report needs.

Methods, all fed the same landmark stream of the manipulating hand:

- ``regal``: Regal-style single-landmark screw fit;
- ``screwmimic_faithful``, ``screwmimic_fair``: ScrewMimic-style fits to per-frame Kabsch hand
  poses; ``screwmimic_robust``: the ``fair`` fit on per-frame RANSAC-Kabsch poses (outliers
  rejected, still no temporal filter), so the comparison is not won against a straw man;
- ``ours_no_unc``: our pipeline without the tracker's uncertainty models (and so without its
  outlier gates, the paper's ablation); ``ours_no_unc_gates``: the same with the gates on;
- ``ours``.

Tasks come from :func:`services.synthetic.splits.demo_specs`: a split (``paper``,
``household``), a partition, a variant and a condition, seeds ``0 .. seeds-1``
(docs/evaluation.md#splits-and-tuning). Results per demonstration and method
(:class:`Row`): the final model's tangent error and types, time to the right type and to
within 10 deg, and the calibration statistics of its covariance; per frame (:class:`History`)
for our methods; per contact phase (:class:`SegmentRow`) for sequences and re-grasps; the
segmentation quality (:class:`PhaseRow`) where the pipeline decides contact phases; and the
free hand stream (:class:`FreeRow`) next to whole demonstrations.

Where the pipeline segments (``PipelineResult.phases``: per frame "contact"/"free" or bool;
``PipelineResult.segment_models``: one ``KinematicModel`` per contact phase with
``segment_start_ns``/``segment_end_ns``), those are scored; without them a segment is scored
by the model held at its last frame, and segmentation quality is not available.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from services.common.progress import Progress
from services.common.protocol import KinematicModel
from services.evaluation import baselines, metrics, phase_metrics
from services.evaluation.metrics import JointEstimate
from services.evaluation.phase_metrics import PhaseScore
from services.evaluation.pipeline import (
    ablation_config,
    joint_estimate,
    no_kinematic_prior_config,
    run_pipeline,
)
from services.kinematics.config import KinematicsConfig
from services.synthetic import splits
from services.synthetic.demonstration import Demonstration, cut_to_segment
from services.synthetic.generator import generate
from services.synthetic.splits import DemoSpec
from services.tracker.config import TrackerConfig

ARTICULATED = ("prismatic", "revolute")


def gated_ablation_config(config: TrackerConfig | None = None) -> TrackerConfig:
    """The ablation with the outlier gates on: no uncertainty models, gates as in ``ours``."""
    return replace(ablation_config(config), ablation_gates=True)


# Our methods: the tracker config each runs with, from the evaluated one.
OURS: dict[str, Callable[[TrackerConfig], TrackerConfig]] = {
    "ours_no_unc": ablation_config,
    "ours_no_unc_gates": gated_ablation_config,
    "ours": lambda config: config,
    "ours_no_kinematic_prior": no_kinematic_prior_config,
}
OPTIONAL_METHODS = ("ours_no_kinematic_prior",)  # run only when named in --methods
BASELINES: dict[str, Callable[[Demonstration], JointEstimate]] = {
    "regal": lambda d: baselines.regal_style(d.stamps_ns, d.points, d.visibility),
    "screwmimic_faithful": lambda d: baselines.screwmimic_style(
        d.stamps_ns, d.points, d.visibility, variant="faithful"),
    "screwmimic_fair": lambda d: baselines.screwmimic_style(
        d.stamps_ns, d.points, d.visibility, variant="fair"),
    "screwmimic_robust": lambda d: baselines.screwmimic_style(
        d.stamps_ns, d.points, d.visibility, variant="fair", front_end="ransac"),
}
METHODS = ("regal", "screwmimic_faithful", "screwmimic_fair", "screwmimic_robust",
           "ours_no_unc", "ours_no_unc_gates", "ours")
LABELS = {
    "regal": "Regal et al. (style)",
    "screwmimic_faithful": "ScrewMimic (faithful)",
    "screwmimic_fair": "ScrewMimic (fair)",
    "screwmimic_robust": "ScrewMimic (fair, RANSAC poses)",
    "ours_no_unc": "Ours w/o unc. models",
    "ours_no_unc_gates": "Ours w/o unc. models, gates on",
    "ours_no_kinematic_prior": "Ours w/o kin. prior",
    "ours": "Ours",
}
CONVERGED_DEG = 10.0
# The split names of the old command line: the paper split's partitions.
LEGACY_SPLITS = ("evaluation", "tuning")
PARTITIONS = ("evaluation", "tuning", "all")
# Rows of a whole demonstration's final contact phase cut at grasp and release carry this
# variant (the comparison of issue 15's goal: whole vs. cut on the same demonstrations).
WHOLE_CUT = "whole_cut"


@dataclass(frozen=True)
class Row:
    """One method on one demonstration. Angles in degrees, distances in metres, times in s.

    ``type_est``: the final verdict (ours: the model's type, "unknown"/"disconnected"
    included). ``tangent_error_deg`` is NaN for a rigid truth (no motion to compare).
    ``converge_s`` / ``type_s``: time from the grasp of the final joint until the tangent error
    is below 10 deg / the type is right, for good (NaN: never, or a baseline, which has no
    estimate over time). ``axis_d2`` / ``point_d2``: squared Mahalanobis distances of the true
    axis direction / revolute axis position under the published covariance
    (docs/evaluation.md#calibration), NaN unless the final type is the true articulated type.
    ``p_true``: the final model's probability of the true type (NaN for the baselines).
    """

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
    split: str = "paper"
    variant: str = "cut"
    condition: str = "plain"
    type_s: float = math.nan
    axis_d2: float = math.nan
    point_d2: float = math.nan
    p_true: float = math.nan


@dataclass(frozen=True, eq=False)
class History:
    """One of our methods on one demonstration, frame by frame (M frames).

    ``t_s`` (M,) seconds since the demonstration's first frame; ``tangent_error_deg`` (M,) of the
    model held after each frame (NaN before the first model, and for a rigid truth);
    ``p_true`` (M,) that model's probability of the true joint type (NaN before the first).
    """

    object: str
    participant: int
    seed: int
    method: str
    type_true: str
    t_s: np.ndarray
    tangent_error_deg: np.ndarray
    p_true: np.ndarray
    split: str = "paper"
    variant: str = "cut"
    condition: str = "plain"


@dataclass(frozen=True)
class DemoIds:
    """Which demonstration and method a per-phase row is about (:meth:`_Label.ids` plus the
    method)."""

    object: str
    participant: int
    seed: int
    split: str
    variant: str
    condition: str
    method: str


@dataclass(frozen=True)
class SegmentRow(DemoIds):
    """One contact phase of a demonstration with several (sequence, re-grasp), one method.

    ``source``: "segment" (the pipeline's model of that phase) or "at_release" (the model held
    at the phase's last frame, without segmentation). ``tangent_error_deg`` against the phase's
    own joint over its own rows.
    """

    segment: int
    joint: str
    type_true: str
    type_est: str
    tangent_error_deg: float
    source: str


@dataclass(frozen=True)
class PhaseRow(DemoIds):
    """The pipeline's contact phases on one demonstration against the true ones: ``score`` the
    phase decided online at each frame's own time (tentative phases that were later dropped
    included), ``dated`` the phases as finally kept, dated back by at most the segmentation's
    ``max_lag_s`` (``PipelineResult.segment_models``; None without them)."""

    score: PhaseScore
    dated: PhaseScore | None = None


@dataclass(frozen=True)
class FreeRow:
    """One of our methods on a free hand stream (no contact at all).

    ``articulated_frames``: frames after which the published model is prismatic or revolute
    with probability > 0.5; ``phases``: the pipeline's contact phases, decided online at each
    frame, scored against none (None without segmentation); ``dated``: the phases it kept;
    ``articulated_phases``: kept phases whose verdict is prismatic or revolute with probability
    > 0.5 (what ``get`` could answer a robot).
    """

    participant: int
    seed: int
    method: str
    frames: int
    articulated_frames: int
    final_type: str
    duration_s: float
    phases: PhaseScore | None
    dated: PhaseScore | None = None
    articulated_phases: int = 0


@dataclass
class DemoResult:
    """Everything one task produced."""

    rows: list[Row] = field(default_factory=list)
    histories: list[History] = field(default_factory=list)
    segments: list[SegmentRow] = field(default_factory=list)
    phases: list[PhaseRow] = field(default_factory=list)
    free: list[FreeRow] = field(default_factory=list)

    def extend(self, other: DemoResult) -> None:
        self.rows += other.rows
        self.histories += other.histories
        self.segments += other.segments
        self.phases += other.phases
        self.free += other.free


@dataclass
class Evaluation(DemoResult):
    """What :func:`run_evaluation` returns: every task's results, in task order."""


@dataclass(frozen=True)
class Settings:
    tracker: TrackerConfig
    kinematics: KinematicsConfig


@dataclass(frozen=True)
class Task:
    """One demonstration to evaluate: its split and condition names, and what to generate
    (``split == "free"``: a free hand stream)."""

    split: str
    condition: str
    spec: DemoSpec

    def describe(self) -> str:
        s = self.spec
        extra = "".join(f" {x}" for x in (s.variant, self.condition)
                        if x not in ("cut", "plain"))
        return f"{s.object_name} p{s.participant} s{s.seed}{extra}"


@dataclass(frozen=True)
class _Label:
    """The identity fields every row of one demonstration shares."""

    object: str
    participant: int
    seed: int
    split: str
    variant: str
    condition: str

    def ids(self) -> dict[str, Any]:
        return {"object": self.object, "participant": self.participant, "seed": self.seed,
                "split": self.split, "variant": self.variant, "condition": self.condition}


def _final_joint_start_ns(demo: Demonstration) -> int:
    """When the final joint is first grasped: the onset of the first contact phase on it (the
    first stamp for a demonstration cut at grasp and release, or without phases)."""
    tr = demo.truth
    final = tr.segments[-1].joint if tr.segments else None
    for seg in tr.segments:
        if seg.joint == final:
            return max(int(seg.onset_ns), int(demo.stamps_ns[0]))
    return int(demo.stamps_ns[0])


def _scores(truth: JointEstimate, est: JointEstimate, positions: np.ndarray
            ) -> tuple[float, float, float]:
    """(tangent error deg, axis angle deg, line distance m) of ``est``; NaN where undefined."""
    if truth.type == "rigid":
        return math.nan, math.nan, math.nan
    line = (metrics.axis_line_distance(truth, est)
            if truth.type == "revolute" and est.type == "revolute" else math.nan)
    axis = (math.degrees(metrics.axis_angle_error(truth, est))
            if est.type in ARTICULATED else math.nan)
    return math.degrees(metrics.tangent_error(truth, est, positions)), axis, line


def _calibration(truth: JointEstimate, model: KinematicModel) -> tuple[float, float]:
    """(axis_d2, point_d2) of the final model, NaN unless its type is the true articulated
    type (docs/evaluation.md#calibration)."""
    if truth.type not in ARTICULATED or model.type != truth.type:
        return math.nan, math.nan
    if truth.type == "prismatic" and model.prismatic is not None:
        p = model.prismatic
        return metrics.axis_direction_d2(truth.axis, p.axis, p.covariance[:2, :2]), math.nan
    r = model.revolute
    if r is None:
        return math.nan, math.nan
    return (metrics.axis_direction_d2(truth.axis, r.axis, r.covariance[:2, :2]),
            metrics.axis_position_d2(truth.axis, truth.point, r.axis, r.point,
                                     r.covariance[2:5, 2:5]))


def _distinct_estimates(history: Sequence[KinematicModel | None]) -> list[JointEstimate | None]:
    """Joint estimates per frame, converting each distinct model once."""
    out: list[JointEstimate | None] = []
    last: tuple[KinematicModel | None, JointEstimate | None] = (None, None)
    for model in history:
        if model is not last[0]:
            last = (model, None if model is None else joint_estimate(model))
        out.append(last[1])
    return out


def _ours(demo: Demonstration, label: _Label, method: str, settings: Settings) -> DemoResult:
    """One of our methods on one demonstration: its row, history, segments and phases."""
    tracker = OURS[method](settings.tracker)
    t0 = time.perf_counter()
    result = run_pipeline(demo, tracker, settings.kinematics)
    runtime = time.perf_counter() - t0
    truth = JointEstimate.from_joint(demo.truth.joint)
    stamps = np.asarray(result.stamps_ns)
    start_ns = _final_joint_start_ns(demo)
    model = result.final
    no_model = np.array([m is None for m in result.history], dtype=bool)
    if truth.type == "rigid":
        errors_deg = np.full(len(stamps), math.nan)
        converge: float | None = None
    else:
        errors = metrics.tangent_errors_over_time(truth, _distinct_estimates(result.history),
                                                  demo.truth.grasp_points)
        converge = metrics.time_to_converge(stamps, errors, CONVERGED_DEG, start_ns)
        errors_deg = np.where(no_model, math.nan, np.degrees(errors))
    types = np.array(["" if m is None else m.type for m in result.history])
    type_s = metrics.time_held_from(stamps, types == truth.type, start_ns)
    tangent, axis, line = _scores(truth, joint_estimate(model), demo.truth.grasp_points)
    axis_d2, point_d2 = _calibration(truth, model)
    row = Row(method=method, type_true=truth.type, type_est=model.type,
              tangent_error_deg=tangent, axis_angle_deg=axis, line_distance_m=line,
              converge_s=math.nan if converge is None else converge, runtime_s=runtime,
              type_s=math.nan if type_s is None else type_s, axis_d2=axis_d2,
              point_d2=point_d2, p_true=float(model.probabilities.get(truth.type, 0.0)),
              **label.ids())
    p_true = np.array([math.nan if m is None else float(m.probabilities.get(truth.type, 0.0))
                       for m in result.history])
    history = History(method=method, type_true=truth.type, t_s=(stamps - stamps[0]) * 1e-9,
                      tangent_error_deg=errors_deg, p_true=p_true,
                      **{k: v for k, v in label.ids().items()})
    out = DemoResult(rows=[row], histories=[history])
    if len(demo.truth.segments) > 1:
        out.segments = _segment_rows(demo, label, method, result)
    phases = getattr(result, "phases", None)
    if phases is not None:
        out.phases = [PhaseRow(method=method, score=score_demo_phases(demo, phases),
                               dated=score_kept_phases(demo, result), **label.ids())]
    return out


def score_demo_phases(demo: Demonstration, phases: Any) -> PhaseScore:
    """A per-frame phase decision on ``demo``'s frames ((N,) "contact"/"free" or bool) against
    its true contact phases (:func:`~services.evaluation.phase_metrics.score_phases`)."""
    truth = [(s.onset_ns, s.release_ns) for s in demo.truth.segments]
    return phase_metrics.score_phases(demo.stamps_ns, phase_metrics.as_contact(phases), truth)


def score_kept_phases(demo: Demonstration, result: Any) -> PhaseScore | None:
    """The contact phases the pipeline kept (``segment_models``: from ``segment_start_ns`` to
    ``segment_end_ns``, an open one to the last frame) against ``demo``'s true ones; None for a
    pipeline without them."""
    models: Sequence[KinematicModel] | None = getattr(result, "segment_models", None)
    if models is None:
        return None
    stamps = np.asarray(demo.stamps_ns, dtype=np.int64)
    contact = np.zeros(len(stamps), dtype=bool)
    for m in models:
        start = int(m.segment_start_ns)  # type: ignore[arg-type]
        end = int(m.segment_end_ns) if m.segment_end_ns is not None else int(stamps[-1])
        contact |= (stamps >= start) & (stamps <= end)
    truth = [(s.onset_ns, s.release_ns) for s in demo.truth.segments]
    return phase_metrics.score_phases(stamps, contact, truth)


def _segment_rows(demo: Demonstration, label: _Label, method: str, result: Any
                  ) -> list[SegmentRow]:
    """Each true contact phase scored by the pipeline's model of it (matched by overlap), or,
    without segmentation, by the model held at its last frame."""
    tr = demo.truth
    models: Sequence[KinematicModel] | None = getattr(result, "segment_models", None)
    chosen: list[KinematicModel | None]
    if models is not None:
        spans = [(int(m.segment_start_ns),  # type: ignore[attr-defined]
                  int(getattr(m, "segment_end_ns", None) or demo.stamps_ns[-1]))
                 for m in models]
        matched = phase_metrics.match_intervals(
            [(s.onset_ns, s.release_ns) for s in tr.segments], spans)
        chosen = [None if j is None else models[j] for j in matched]
        source = "segment"
    else:
        chosen = [result.history[s.end] for s in tr.segments]
        source = "at_release"
    out = []
    for i, model in enumerate(chosen):
        joint = tr.segment_joint(i)
        truth = JointEstimate.from_joint(joint)
        if model is None:
            type_est, error = "none", (math.nan if truth.type == "rigid" else 90.0)
        else:
            type_est = model.type
            error = _scores(truth, joint_estimate(model), tr.segment_grasp_points(i))[0]
        out.append(SegmentRow(method=method, segment=i, joint=joint.name, type_true=truth.type,
                              type_est=type_est, tangent_error_deg=error, source=source,
                              **label.ids()))
    return out


def _baseline(demo: Demonstration, label: _Label, method: str) -> Row:
    t0 = time.perf_counter()
    est = BASELINES[method](demo)
    runtime = time.perf_counter() - t0
    truth = JointEstimate.from_joint(demo.truth.joint)
    tangent, axis, line = _scores(truth, est, demo.truth.grasp_points)
    return Row(method=method, type_true=truth.type, type_est=est.type,
               tangent_error_deg=tangent, axis_angle_deg=axis, line_distance_m=line,
               converge_s=math.nan, runtime_s=runtime, **label.ids())


def _methods_on(demo: Demonstration, label: _Label, settings: Settings,
                methods: Sequence[str]) -> DemoResult:
    out = DemoResult()
    for method in methods:
        if method in OURS:
            out.extend(_ours(demo, label, method, settings))
        elif method in BASELINES:
            out.rows.append(_baseline(demo, label, method))
        else:
            raise ValueError(f"unknown method {method!r}; known: {list(METHODS)}")
    return out


def _free(task: Task, settings: Settings, methods: Sequence[str]) -> DemoResult:
    """Our methods on a free hand stream (the baselines always answer a joint: not run)."""
    demo = generate(**task.spec.kwargs())  # type: ignore[arg-type]
    out = DemoResult()
    for method in (m for m in methods if m in OURS):
        result = run_pipeline(demo, OURS[method](settings.tracker), settings.kinematics)
        articulated = sum(m is not None and m.type in ARTICULATED
                          and m.probabilities.get(m.type, 0.0) > 0.5 for m in result.history)
        phases = getattr(result, "phases", None)
        stamps = np.asarray(result.stamps_ns)
        score = None if phases is None else score_demo_phases(demo, phases)
        kept = getattr(result, "segment_models", None) or ()
        out.free.append(FreeRow(participant=demo.participant, seed=demo.seed, method=method,
                                frames=len(stamps), articulated_frames=int(articulated),
                                final_type=result.final.type,
                                duration_s=float(stamps[-1] - stamps[0]) * 1e-9,
                                phases=score, dated=score_kept_phases(demo, result),
                                articulated_phases=sum(
                                    m.type in ARTICULATED
                                    and m.probabilities.get(m.type, 0.0) > 0.5 for m in kept)))
    return out


def run_task(task: Task, settings: Settings, methods: Iterable[str] = METHODS) -> DemoResult:
    """All ``methods`` on one task; a whole demonstration also on its final contact phase cut
    at grasp and release (variant :data:`WHOLE_CUT`)."""
    methods = tuple(methods)
    if task.split == "free":
        return _free(task, settings, methods)
    spec = task.spec
    demo = generate(**spec.kwargs())  # type: ignore[arg-type]
    label = _Label(spec.object_name, spec.participant, spec.seed, task.split, spec.variant,
                   task.condition)
    out = _methods_on(demo, label, settings, methods)
    if spec.variant == "whole" and demo.truth.segments:
        cut = cut_to_segment(demo, len(demo.truth.segments) - 1)
        out.extend(_methods_on(cut, replace(label, variant=WHOLE_CUT), settings, methods))
    return out


def run_demo(object_name: str, participant: int, seed: int, settings: Settings,
             methods: Iterable[str] = METHODS, *, variant: str = "cut",
             condition: str = "plain") -> DemoResult:
    """All ``methods`` on one generated demonstration (:func:`run_task`)."""
    cond = splits.CONDITIONS[condition]
    spec = DemoSpec(object_name, participant, seed, variant, cond.get("idle_hand"),
                    cond.get("gap"))
    split = splits.split_of(object_name)
    return run_task(Task(split, condition, spec), settings, methods)


def resolve_split(split: str, partition: str = "evaluation") -> tuple[tuple[str, ...], str]:
    """(splits, partition) of a command line: ``paper``, ``household`` or ``all`` (both), with
    ``partition`` "evaluation", "tuning" or "all"; the old names ``evaluation``/``tuning`` are
    the paper split's partitions (their ``partition`` is ignored)."""
    if split in LEGACY_SPLITS:
        return ("paper",), split
    if partition not in PARTITIONS:
        raise ValueError(f"unknown partition {partition!r}; choose from {list(PARTITIONS)}")
    if split == "all":
        return splits.SPLITS, partition
    if split not in splits.SPLITS:
        raise ValueError(f"unknown split {split!r}; choose from "
                         f"{[*splits.SPLITS, 'all', *LEGACY_SPLITS]}")
    return (split,), partition


def tasks(split: str = "paper", partition: str = "evaluation", seeds: int = 1,
          variants: Sequence[str] = ("cut",), conditions: Sequence[str] = ("plain",),
          free: bool | None = None) -> list[Task]:
    """The demonstrations of a run, in report order: per split, variant and condition, the
    :func:`~services.synthetic.splits.demo_specs` of the partition (``all``: both, ordered by
    object, participant and seed). ``free`` (default: when a variant other than ``cut`` is
    asked for) adds the free hand streams of the partition."""
    names, part = resolve_split(split, partition)
    for v in variants:
        if v not in splits.VARIANTS:
            raise ValueError(f"unknown variant {v!r}; choose from {list(splits.VARIANTS)}")
    for c in conditions:
        if c not in splits.CONDITIONS:
            raise ValueError(f"unknown condition {c!r}; choose from {list(splits.CONDITIONS)}")
    parts = ("tuning", "evaluation") if part == "all" else (part,)

    def specs(name: str, variant: str, condition: str) -> list[DemoSpec]:
        found = [s for p in parts for s in splits.demo_specs(name, p, seeds, variant, condition)]
        if part == "all":
            found = sorted(set(found), key=lambda s: (s.object_name, s.participant, s.seed))
        return found

    out = [Task(name, c, s) for name in names for v in variants for c in conditions
           for s in specs(name, v, c)]
    if free if free is not None else any(v != "cut" for v in variants):
        out += [Task("free", "plain", s) for p in parts
                for s in splits.demo_specs("free", p, seeds)]
    return out


def run_tasks(task_list: Sequence[Task], settings: Settings | None = None,
              methods: Iterable[str] = METHODS, jobs: int = 1,
              progress: Progress | None = None) -> Evaluation:
    """Every method on every task, in task order; ``progress`` (optional) counts the tasks as
    they finish, with their errors."""
    settings = settings or Settings(TrackerConfig(), KinematicsConfig())
    methods = tuple(methods)
    for m in methods:
        if m not in (*METHODS, *OPTIONAL_METHODS):
            raise ValueError(f"unknown method {m!r}; known: {[*METHODS, *OPTIONAL_METHODS]}")
    if progress is not None:
        progress.total = len(task_list)
    results: list[DemoResult | None] = [None] * len(task_list)

    def finished(i: int, result: DemoResult) -> None:
        results[i] = result
        if progress is not None:
            progress.advance(f"{task_list[i].describe()}: {_summary(result)}")

    if jobs <= 1:
        for i, task in enumerate(task_list):
            finished(i, run_task(task, settings, methods))
    else:
        with ProcessPoolExecutor(jobs) as pool:
            futures = {pool.submit(run_task, task, settings, methods): i
                       for i, task in enumerate(task_list)}
            for future in as_completed(futures):
                finished(futures[future], future.result())
    out = Evaluation()
    for r in results:
        if r is not None:
            out.extend(r)
    return out


def _summary(result: DemoResult) -> str:
    """One progress line's worth: each method's error (or type) on the task itself."""
    if result.free:
        return ", ".join(f"{f.method} articulated {f.articulated_frames}/{f.frames} frames"
                         for f in result.free)
    rows = [r for r in result.rows if r.variant != WHOLE_CUT]
    if all(r.type_true == "rigid" for r in rows):  # a still hold: no error, only a verdict
        return ", ".join(f"{r.method} {r.type_est}" for r in rows)
    return ", ".join(f"{r.method} {r.tangent_error_deg:.1f}" for r in rows) + " deg"


def run_evaluation(split: str = "paper", seeds: int = 1, settings: Settings | None = None,
                   methods: Iterable[str] = METHODS, jobs: int = 1,
                   progress: Progress | None = None, *, partition: str = "evaluation",
                   variants: Sequence[str] = ("cut",), conditions: Sequence[str] = ("plain",),
                   free: bool | None = None) -> Evaluation:
    """Every method on every demonstration of :func:`tasks` (:func:`run_tasks`)."""
    return run_tasks(tasks(split, partition, seeds, variants, conditions, free), settings,
                     methods, jobs, progress)


def evaluate(split: str = "paper", seeds: int = 1, settings: Settings | None = None,
             methods: Iterable[str] = METHODS, jobs: int = 1,
             progress: Progress | None = None) -> list[Row]:
    """The rows of :func:`run_evaluation` (cut variant, plain condition)."""
    return run_evaluation(split, seeds, settings, methods, jobs, progress).rows
