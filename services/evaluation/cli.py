"""``handkse eval``: every method on every demonstration of a split; the report (Table II per
split, variant and condition, calibration, times, segments, conditions, free stream), CSVs and
the figures (docs/evaluation.md#running-it)."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from services.common.config import section_from_args

# The choices of the command line, spelled out so that building the parser imports no
# estimation code (tests/evaluation/test_eval.py checks them against the runner and splits).
SPLIT_CHOICES = ("paper", "household", "all", "evaluation", "tuning")
PARTITION_CHOICES = ("evaluation", "tuning", "all")
VARIANT_CHOICES = ("cut", "whole", "sequence", "regrasp")
CONDITION_CHOICES = ("plain", "idle_opposite", "idle_same", "idle_flipping", "dropout",
                     "regrasp_gap")
METHOD_CHOICES = ("regal", "screwmimic_faithful", "screwmimic_fair", "screwmimic_robust",
                  "ours_no_unc", "ours_no_unc_gates", "ours", "ours_no_kinematic_prior")


def _names(text: str | None, default: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(x.strip() for x in text.split(",") if x.strip()) if text else default


def main(args: argparse.Namespace) -> int:
    from services.common.errors import UserError
    from services.common.progress import Progress
    from services.evaluation.figures import describe_data
    from services.evaluation.publish import RESULTS, publish
    from services.evaluation.report import write_report
    from services.evaluation.runner import (
        METHODS,
        OPTIONAL_METHODS,
        Settings,
        resolve_split,
        run_tasks,
        tasks,
    )

    settings = Settings(tracker=section_from_args(args, "tracker"),
                        kinematics=section_from_args(args, "kinematics"))
    methods = _names(args.methods, METHODS)
    variants = _names(args.variant, ("cut",))
    conditions = _names(args.condition, ("plain",))
    free = True if args.free else (False if args.no_free else None)
    try:
        task_list = tasks(args.split, args.partition, args.seeds, variants, conditions, free)
        for m in methods:
            if m not in (*METHODS, *OPTIONAL_METHODS):
                raise ValueError(f"unknown method {m!r}; choose from "
                                 f"{', '.join((*METHODS, *OPTIONAL_METHODS))}")
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if not [t for t in task_list if t.split != "free"]:
        raise UserError("no demonstrations to run: a gap condition (dropout, regrasp_gap) "
                        "applies to the cut and whole variants only")
    names, partition = resolve_split(args.split, args.partition)
    jobs = args.jobs or max(1, (os.cpu_count() or 1))
    with Progress(1) as progress:  # the total is set by the evaluation
        result = run_tasks(task_list, settings, methods, jobs, progress)
    out = Path(args.out or Path("eval") / time.strftime("%Y-%m-%d"))
    split_text = "+".join(names)
    title = (f"handkse evaluation: {split_text} split, {partition} partition, "
             f"{'/'.join(variants)} variant, {'/'.join(conditions)} condition, {args.seeds} "
             "seed(s) per demonstration, synthetic demonstrations")
    data = describe_data(result.rows, f"{split_text} {partition}")
    written = write_report(result, methods, out, title, data=data)
    print(written[0].read_text())
    print(f"written {out}/" + ", ".join(p.name for p in written))
    if args.publish:
        publish(written, RESULTS / "eval")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--split", default="paper", choices=SPLIT_CHOICES,
                   help="paper (the ICRA-25 objects), household, or all; the old names "
                   "evaluation and tuning mean the paper split's partition of that name "
                   "(default paper)")
    p.add_argument("--partition", default="evaluation", choices=PARTITION_CHOICES,
                   help="participants to evaluate (default evaluation; tune only on tuning)")
    p.add_argument("--variant", help="comma-separated: " + ", ".join(VARIANT_CHOICES)
                   + " (default cut)")
    p.add_argument("--condition", help="comma-separated: " + ", ".join(CONDITION_CHOICES)
                   + " (default plain; with plain listed too, the report compares each "
                   "condition with it on the same demonstrations)")
    p.add_argument("--seeds", type=int, default=1, help="demonstrations per (object, participant)")
    free = p.add_mutually_exclusive_group()
    free.add_argument("--free", action="store_true",
                      help="also run the free hand streams (default: with a variant other "
                      "than cut)")
    free.add_argument("--no-free", action="store_true", help="never run the free hand streams")
    p.add_argument("--methods", help="comma-separated subset of " + ", ".join(METHOD_CHOICES)
                   + " (default: all)")
    p.add_argument("--jobs", type=int, help="worker processes (default: all cores)")
    p.add_argument("--out", help="output folder (default eval/<date>)")
    p.add_argument("--publish", action="store_true", help="also copy to bench/results/eval/")
