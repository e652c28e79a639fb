"""``handkse robot-trials``: the paper's Table III (robot success rates) in simulation.

For the key and the window lock, five synthetic demonstrations each (participant 3, seeds
0-4, the evaluation split's participant) are estimated by our pipeline, the Regal-style and the
ScrewMimic-style baselines; each estimate drives one simulated trial
(:func:`services.robot_bridge.simulation.articulate_in_simulation`): the simulated Panda grasps
the true object and turns it 180 deg along the estimated axis under the 70 N force limit. A trial
succeeds if it reaches 180 deg (within the success tolerance) without an abort, as in the paper
(sec. IV.C). Writes ``table.md`` (success rates, forces), ``results.csv`` (one row per trial),
``traces.json`` (the force traces) and the figures of :mod:`services.evaluation.robot_plots`:
``force_trials.png`` (every trial) and ``force_key.png`` (one key demonstration, like the
paper's Fig. 6).

Every method gets the same task: turn 180 deg in the direction the human turned (from the
demonstration's ground truth, expressed about each estimated axis); baseline estimates, which
carry no joint value, get the observed opening stroke as ``q`` (:func:`demonstrated_extent`).
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from services.common.progress import Progress
from services.common.protocol import KinematicModel, PrismaticParams, RevoluteParams
from services.evaluation.publish import RESULTS, publish
from services.evaluation.robot_trial_rows import LABELS, METHODS, OBJECTS, PARTICIPANT, TrialRow
from services.robot_bridge.config import RobotBridgeConfig, config_from_args

Array = NDArray[np.float64]

LATEST = RESULTS / "robot_trials"
# robot_perturbations.CASES spelled out, so that building the parser imports no simulation code
# (tests/evaluation/test_robot_perturbations.py checks they agree).
DEFAULT_CASES_TEXT = "5:0,10:0,20:0,0:5,0:10,0:20,10:10"
REPORT_FILES = ("table.md", "results.csv", "traces.json", "force_trials.png", "force_key.png")


def demonstrated_extent(joint_type: str, axis: Array, point: Array, points: Array) -> float:
    """Signed extreme of the observed motion along a joint (rad or m), e.g. the opening stroke.

    Per frame, the median increment of the landmarks seen in both frames (robust to depth
    outliers): the angle about the axis through ``point`` (revolute) or the displacement along
    ``axis`` (prismatic); summed over frames, the value farthest from 0 is returned (a return
    stroke does not cancel it). ``points`` (N, 21, 3), NaN where not seen. Noisy (tens of
    percent); used for the sign and as a rough range.
    """
    x0, x1 = points[:-1], points[1:]
    ok = np.isfinite(x0).all(axis=2) & np.isfinite(x1).all(axis=2)
    steps = np.zeros(len(x0))
    for k in range(len(x0)):
        a0, a1 = x0[k][ok[k]], x1[k][ok[k]]
        if len(a0) == 0:
            continue
        if joint_type == "revolute":
            r0 = a0 - point - np.outer((a0 - point) @ axis, axis)
            r1 = a1 - point - np.outer((a1 - point) @ axis, axis)
            steps[k] = float(np.median(np.arctan2(np.cross(r0, r1) @ axis,
                                                  np.einsum("ij,ij->i", r0, r1))))
        else:
            steps[k] = float(np.median((a1 - a0) @ axis))
    path = np.cumsum(steps)
    return float(path[int(np.argmax(np.abs(path)))]) if len(path) else 0.0


def model_from_estimate(joint_type: str, axis: Array, point: Array, demo: object) -> KinematicModel:
    """A wire ``KinematicModel`` (camera frame, P = 1) for a baseline's joint estimate.

    ``q`` is the observed opening stroke along the estimated joint (:func:`demonstrated_extent`).
    """
    probs = {k: 0.0 for k in ("rigid", "prismatic", "revolute", "disconnected")}
    if joint_type not in ("revolute", "prismatic"):
        probs["rigid"] = 1.0
        return KinematicModel(type="rigid", probabilities=probs)
    points = np.asarray(demo.points, float)  # type: ignore[attr-defined]
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    p = np.asarray(point, float)
    probs[joint_type] = 1.0
    q = demonstrated_extent(joint_type, a, p, points)
    if joint_type == "revolute":
        return KinematicModel(type="revolute", probabilities=probs, revolute=RevoluteParams(
            axis=a, point=p - (p @ a) * a, q=q, dq=0.0, covariance=np.zeros((7, 7))))
    ref = np.eye(4)
    ref[:3, 3] = p
    return KinematicModel(type="prismatic", probabilities=probs, reference_pose=ref,
                          prismatic=PrismaticParams(axis=a, q=q, dq=0.0,
                                                    covariance=np.zeros((4, 4))))


def estimate(method: str, demo: object) -> KinematicModel:
    """The model of ``method`` ("ours", "regal", "screwmimic") on a demonstration."""
    d = demo
    if method == "ours":
        from services.evaluation.pipeline import run_pipeline

        return run_pipeline(d).final  # type: ignore[arg-type]
    from services.evaluation import baselines

    stream = (d.stamps_ns, d.points, d.visibility)  # type: ignore[attr-defined]
    if method == "regal":
        est = baselines.regal_style(*stream)
    elif method == "screwmimic":
        est = baselines.screwmimic_style(*stream, variant="faithful")
    else:
        raise ValueError(f"unknown method {method!r}; known: {list(METHODS)}")
    return model_from_estimate(est.type, est.axis, est.point, d)


def _axis_errors(model: KinematicModel, obj: object) -> tuple[float, float]:
    """(axis angle deg, axis distance at the human grasp cm) of a revolute model vs the truth."""
    if model.type != "revolute" or model.revolute is None:
        return math.nan, math.nan
    a = np.asarray(model.revolute.axis)
    t = np.asarray(obj.axis)  # type: ignore[attr-defined]
    angle = math.degrees(math.acos(min(1.0, abs(float(a @ t)))))
    g = np.asarray(obj.grasp)  # type: ignore[attr-defined]

    def foot(axis: Array, point: Array) -> Array:
        return point + ((g - point) @ axis) * axis

    off = float(np.linalg.norm(foot(a, np.asarray(model.revolute.point))
                               - foot(t, np.asarray(obj.point))))  # type: ignore[attr-defined]
    return angle, off * 100.0


def run_trial(object_name: str, seed: int, method: str, config: RobotBridgeConfig,
              closed_loop: bool = False) -> tuple[TrialRow, dict[str, list[float]]]:
    """Estimate on one demonstration and run one simulated trial (``closed_loop``: refined from
    the robot's own motion, docs/robot_bridge.md#closed-loop); the row and the force trace."""
    from services.robot_bridge.simulation import articulate_in_simulation, object_in_camera
    from services.synthetic.generator import generate

    demo = generate(object_name, PARTICIPANT, seed)
    obj = object_in_camera(demo)
    model = estimate(method, demo)
    angle, offset = _axis_errors(model, obj)
    refinement = None
    if closed_loop:
        from services.robot_bridge.refinement import RefinementConfig

        refinement = RefinementConfig()
    sim = articulate_in_simulation(model, obj, config=config, refinement=refinement)
    r = sim.result
    ex = sim.execution
    reached = math.degrees(r.articulated) if model.type == "revolute" else r.articulated * 1e3
    row = TrialRow(object=object_name, seed=seed, method=method, type_est=model.type,
                   axis_angle_deg=angle, axis_offset_cm=offset, success=r.success,
                   reason=r.reason, articulated_deg=reached, peak_force_n=r.peak_force_n,
                   mean_force_n=r.mean_force_n,
                   peak_torque_nm=ex.peak_torque_nm if ex is not None else 0.0,
                   duration_s=r.duration_s)
    trace: dict[str, list[float]] = {"t_s": [], "force_n": [], "stop_s": []}
    if ex is not None:
        stride = 10  # 100 Hz is plenty for the plot
        trace = {"t_s": ex.trace.t_s[::stride], "force_n": ex.trace.force_n[::stride],
                 "stop_s": [] if ex.trace.stopped_at_s is None else [ex.trace.stopped_at_s]}
    return row, trace


def table_markdown(rows: Sequence[TrialRow], methods: Sequence[str], title: str) -> str:
    """Success rates per method and object (Table III) with force statistics."""
    lines = [f"# {title}", "",
             "| method | " + " | ".join(o.replace("_", " ") for o in OBJECTS)
             + " | mean force, successes (N) | peak force, all trials (N) |",
             "|---|" + "---|" * (len(OBJECTS) + 2)]
    for m in methods:
        cells = []
        for o in OBJECTS:
            rs = [r for r in rows if r.method == m and r.object == o]
            cells.append(f"{sum(r.success for r in rs)}/{len(rs)}")
        ok = [r.mean_force_n for r in rows if r.method == m and r.success]
        peaks = [r.peak_force_n for r in rows if r.method == m]
        mean = f"{np.mean(ok):.1f}" if ok else "-"
        peak = f"{np.max(peaks):.1f}" if peaks else "-"
        lines.append(f"| {LABELS.get(m, m)} | " + " | ".join(cells) + f" | {mean} | {peak} |")
    lines += ["", "Failures: " + (", ".join(
        f"{r.method}/{r.object}/s{r.seed}: {r.reason}" for r in rows if not r.success) or "none"),
        "", "| object | seed | method | type | axis error (deg) | axis offset (cm) | result | "
        "reached (deg) | peak F (N) | mean F (N) | peak T (N m) |",
        "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r.object} | {r.seed} | {r.method} | {r.type_est} | "
                     f"{r.axis_angle_deg:.1f} | {r.axis_offset_cm:.2f} | "
                     f"{'ok' if r.success else r.reason} | {r.articulated_deg:.1f} | "
                     f"{r.peak_force_n:.1f} | {r.mean_force_n:.1f} | {r.peak_torque_nm:.2f} |")
    return "\n".join(lines) + "\n"


def run_trials(seeds: int = 5, methods: Sequence[str] = METHODS,
               config: RobotBridgeConfig | None = None, jobs: int = 1,
               objects: Sequence[str] = OBJECTS, closed_loop: bool = False
               ) -> tuple[list[TrialRow], dict[tuple[str, int, str], dict[str, list[float]]]]:
    """Every (object, seed, method) trial; rows in task order and their force traces. Shows
    the trials as they finish and how many are left."""
    t0 = time.monotonic()
    cfg = config or RobotBridgeConfig()
    tasks = [(o, s, m) for o in objects for s in range(seeds) for m in methods]
    results: list[tuple[TrialRow, dict[str, list[float]]] | None] = [None] * len(tasks)
    with Progress(len(tasks)) as progress:
        def finished(i: int, result: tuple[TrialRow, dict[str, list[float]]]) -> None:
            results[i] = result
            r = result[0]
            progress.advance(f"{r.object} s{r.seed} {r.method}: {r.type_est}, axis "
                             f"{r.axis_angle_deg:.1f} deg {r.axis_offset_cm:.2f} cm -> "
                             f"{'ok' if r.success else r.reason} at {r.articulated_deg:.1f}, "
                             f"peak {r.peak_force_n:.1f} N, mean {r.mean_force_n:.1f} N")

        if jobs <= 1:
            for i, t in enumerate(tasks):
                finished(i, run_trial(*t, cfg, closed_loop))
        else:
            with ProcessPoolExecutor(jobs) as pool:
                futures = {pool.submit(run_trial, *t, cfg, closed_loop): i
                           for i, t in enumerate(tasks)}
                for future in as_completed(futures):
                    finished(futures[future], future.result())
        progress.done(f"{len(tasks)} trials in {time.monotonic() - t0:.1f} s")
    done = [r for r in results if r is not None]
    rows = [r for r, _ in done]
    traces = {t: tr for t, (_, tr) in zip(tasks, done, strict=True)}
    return rows, traces


def write_report(rows: Sequence[TrialRow], traces: dict[tuple[str, int, str],
                 dict[str, list[float]]], methods: Sequence[str], out: Path, plot_seed: int,
                 force_limit_n: float, title: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.md").write_text(table_markdown(rows, methods, title))
    with open(out / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(rows[0]).keys()))
        w.writeheader()
        for r in rows:
            w.writerow(asdict(r))
    from services.evaluation import robot_plots

    robot_plots.write_traces(traces, out / "traces.json")
    robot_plots.write_figures(rows, traces, out, force_limit_n, title, plot_seed)


def main(args: argparse.Namespace) -> int:
    """Run the trials, print Table III, write the report folder (``--perturbed``: the
    perturbed starting models instead, :func:`perturbed_main`)."""
    config = config_from_args(args)
    if getattr(args, "perturbed", False):
        return perturbed_main(args, config)
    methods = tuple(args.methods.split(",")) if args.methods else METHODS
    for m in methods:
        if m not in METHODS:
            raise SystemExit(f"unknown method {m!r}; choose from {list(METHODS)}")
    jobs = args.jobs or max(1, os.cpu_count() or 1)
    closed = bool(getattr(args, "closed_loop", False))
    rows, traces = run_trials(args.seeds, methods, config, jobs, closed_loop=closed)
    loop = "closed_loop" if closed else ""
    out = Path(args.out or Path("robot_trials") / time.strftime("%Y-%m-%d") / loop)
    title = (f"handkse robot trials in simulation: {len(OBJECTS)} objects x {args.seeds} "
             f"demonstrations (participant {PARTICIPANT}), force limit "
             f"{config.force_limit_n:.0f} N, 180 deg in 6 s"
             + (", closed loop (refined from the robot's own motion)" if closed else ""))
    write_report(rows, traces, methods, out, args.plot_seed, config.force_limit_n, title)
    print((out / "table.md").read_text().split("\n\nFailures")[0])
    print(f"written {out}/" + ", ".join(REPORT_FILES))
    if args.publish:
        publish([out / name for name in REPORT_FILES], LATEST / loop if loop else LATEST)
    return 0


def perturbed_main(args: argparse.Namespace, config: RobotBridgeConfig) -> int:
    """Perturbed starting models (:mod:`services.evaluation.robot_perturbations`), open and
    closed loop: print and write ``perturbed.md`` and ``perturbed.csv`` (``--publish``: also to
    bench/results/robot_trials/, with the machine that ran them)."""
    from services.common.errors import UserError
    from services.evaluation import robot_perturbations as rp

    try:
        cases = rp.parse_cases(args.cases) if args.cases else rp.CASES
        objects = tuple(x.strip() for x in args.objects.split(",") if x.strip()) \
            if args.objects else rp.OBJECTS
        unknown = [o for o in objects if o not in rp.OBJECTS]
        if unknown or not objects:
            raise ValueError(f"unknown object(s) {unknown}; choose from {list(rp.OBJECTS)}")
        if args.directions < 1:
            raise ValueError(f"--directions must be >= 1, got {args.directions}")
    except ValueError as exc:
        raise UserError(str(exc)) from None
    jobs = args.jobs or max(1, os.cpu_count() or 1)
    rows = rp.run_perturbed(objects, cases, args.directions, config, jobs)
    out = Path(args.out or Path("robot_trials") / time.strftime("%Y-%m-%d"))
    title = (f"handkse robot trials in simulation, perturbed starting models: "
             f"{', '.join(objects)} (participant {PARTICIPANT}, seed 0), {args.directions} "
             f"direction(s) per case, open and closed loop, force limit "
             f"{config.force_limit_n:.0f} N, 180 deg in 6 s")
    written = rp.write_report(rows, out, title, rp.describe_machine())
    print(written[0].read_text())
    print(f"written {out}/" + ", ".join(p.name for p in written))
    if args.publish:
        publish(written, LATEST)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``handkse robot-trials`` (the CLI adds --rig/--config/--set/zenoh)."""
    p.add_argument("--seeds", type=int, default=5, help="demonstrations per object (default 5)")
    p.add_argument("--methods", help="comma-separated subset of ours, regal, screwmimic")
    p.add_argument("--jobs", type=int, help="worker processes (default: all cores)")
    p.add_argument("--out", help="output folder (default robot_trials/<date>)")
    p.add_argument("--plot-seed", type=int, default=0, help="key demonstration for force_key.png")
    p.add_argument("--publish", action="store_true",
                   help="also copy to bench/results/robot_trials/")
    p.add_argument("--closed-loop", action="store_true",
                   help="refine each model from the robot's own motion while articulating "
                   "(reports under closed_loop/, published to bench/results/robot_trials/"
                   "closed_loop/)")
    p.add_argument("--perturbed", action="store_true",
                   help="instead of Table III: the true key and window-lock joints perturbed "
                   "(tilt, offset), each run open and closed loop (perturbed.md, perturbed.csv)")
    p.add_argument("--cases", help="with --perturbed: comma-separated TILT_DEG:OFFSET_MM cases "
                   f"(default: {DEFAULT_CASES_TEXT})")
    p.add_argument("--directions", type=int, default=10,
                   help="with --perturbed: perturbation directions per case (default 10)")
    p.add_argument("--objects", help="with --perturbed: comma-separated subset of key, "
                   "window_lock")


if __name__ == "__main__":
    import logging

    parser = argparse.ArgumentParser(prog="python -m services.evaluation.robot_trials",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--config", metavar="FILE")
    parser.add_argument("--set", action="append", default=[], dest="overrides",
                        metavar="SECTION.KEY=VALUE")
    add_arguments(parser)
    logging.basicConfig(level="WARNING")
    raise SystemExit(main(parser.parse_args()))
