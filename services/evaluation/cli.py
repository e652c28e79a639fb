"""``handkse eval``: every method on every demonstration; Table II, a CSV and the figures."""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

from services.common.config import section_from_args

LATEST = Path(__file__).resolve().parents[2] / "bench" / "results" / "eval"


def main(args: argparse.Namespace) -> int:
    from services.common.progress import Progress
    from services.evaluation.figures import describe_data
    from services.evaluation.report import write_report
    from services.evaluation.runner import METHODS, Settings, run_evaluation

    settings = Settings(tracker=section_from_args(args, "tracker"),
                        kinematics=section_from_args(args, "kinematics"))
    methods = tuple(args.methods.split(",")) if args.methods else METHODS
    jobs = args.jobs or max(1, (os.cpu_count() or 1))
    with Progress(1) as progress:  # the total is set by the evaluation
        result = run_evaluation(args.split, args.seeds, settings, methods, jobs, progress)
    out = Path(args.out or Path("eval") / time.strftime("%Y-%m-%d"))
    title = (f"handkse evaluation: {args.split} split, {args.seeds} seed(s) per demonstration, "
             "synthetic demonstrations")
    written = write_report(result.rows, methods, out, title, result.histories,
                           describe_data(result.rows, args.split))
    print((out / "table.md").read_text())
    print(f"written {out}/" + ", ".join(p.name for p in written))
    if args.publish:
        LATEST.mkdir(parents=True, exist_ok=True)
        for path in written:
            shutil.copy(path, LATEST / path.name)
        print(f"copied to {LATEST}")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--split", default="evaluation", choices=("evaluation", "tuning", "all"))
    p.add_argument("--seeds", type=int, default=1, help="demonstrations per (object, participant)")
    p.add_argument("--methods", help="comma-separated subset of regal, screwmimic_faithful, "
                   "screwmimic_fair, ours_no_unc, ours (default: all), and "
                   "ours_no_kinematic_prior (only when named)")
    p.add_argument("--jobs", type=int, help="worker processes (default: all cores)")
    p.add_argument("--out", help="output folder (default eval/<date>)")
    p.add_argument("--publish", action="store_true", help="also copy to bench/results/eval/")
