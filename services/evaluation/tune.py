"""``handkse tune``: Bayesian optimisation of the Table I parameters marked with a dagger.

As in the paper, only the tuning split is used (valve, tension belt, window lock and flap latch
by participants 1 and 2): the objective is our method's mean tangent error there. The sampler
is optuna's TPE (a sequential model-based, i.e. Bayesian, optimiser), seeded. The result is a
TOML config with the tuned ``[tracker]`` values, and a side-by-side report of the default and
the tuned parameters on both splits (the evaluation split is only read after tuning).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from services.common.config import section_from_args, to_toml
from services.common.progress import Progress
from services.tracker.config import TrackerConfig

# Table I dagger parameters: field -> (low, high, log scale). Ranges span about a decade around
# the paper's values (the paper's units, see TrackerConfig).
SEARCH_SPACE: dict[str, tuple[float, float, bool]] = {
    "q_lm_position_m2": (0.01, 1.0, True),
    "q_lm_velocity_m2ps2": (0.005, 0.5, True),
    "r_lm_m2": (0.005, 0.5, True),
    "lm_loss_trace_m2": (0.05, 3.0, True),
    "visibility_threshold": (0.0005, 0.5, True),
    "mahalanobis_lm": (0.05, 1.0, True),
    "mahalanobis_rb": (0.05, 1.0, True),
}


def tune(base: TrackerConfig, kinematics: object, trials: int, seeds: int, jobs: int,
         seed: int = 0) -> tuple[TrackerConfig, float, list[tuple[int, float]]]:
    """Best tracker config, its tuning-split mean tangent error, and (trial, value) history."""
    try:
        import optuna
    except ImportError as exc:
        raise SystemExit("handkse tune needs optuna: pip install 'handkse[tune]'") from exc
    from services.evaluation.report import method_means
    from services.evaluation.runner import Settings, evaluate

    def objective(trial: optuna.Trial) -> float:
        values = {k: trial.suggest_float(k, lo, hi, log=log)
                  for k, (lo, hi, log) in SEARCH_SPACE.items()}
        cfg = dataclasses.replace(base, **values)
        rows = evaluate("tuning", seeds, Settings(cfg, kinematics), ("ours",), jobs)  # type: ignore[arg-type]
        return method_means(rows, ("ours",))["ours"]

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="minimize",
                                sampler=optuna.samplers.TPESampler(seed=seed))
    study.enqueue_trial({k: getattr(base, k) for k in SEARCH_SPACE})  # the paper's values first

    with Progress(trials) as progress:
        def log_trial(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
            progress.advance(f"trial {trial.number}: {trial.value:.2f} deg, "
                             f"best {study.best_value:.2f} deg")

        study.optimize(objective, n_trials=trials, callbacks=[log_trial])
    best = dataclasses.replace(base, **study.best_params)
    history = [(t.number, float(t.value)) for t in study.trials if t.value is not None]
    return best, float(study.best_value), history


def main(args: argparse.Namespace) -> int:
    from services.evaluation.report import method_means
    from services.evaluation.runner import Settings, evaluate

    base = section_from_args(args, "tracker")
    kinematics = section_from_args(args, "kinematics")
    best, value, _ = tune(base, kinematics, args.trials, args.seeds, args.jobs)
    out = Path(args.out)
    out.write_text("# handkse tracker parameters tuned by `handkse tune` on the tuning split\n"
                   + to_toml({"tracker": best}))
    print(f"tuned config written to {out} (tuning-split mean {value:.2f} deg)")
    lines = ["| split | default | tuned |", "| --- | ---: | ---: |"]
    with Progress(4) as progress:
        for split in ("tuning", "evaluation"):
            means = []
            for name, cfg in (("default", base), ("tuned", best)):
                progress.step(f"{split} split with the {name} parameters")
                rows = evaluate(split, args.seeds, Settings(cfg, kinematics), ("ours",), args.jobs)
                means.append(method_means(rows, ("ours",))["ours"])
            lines.append(f"| {split} | {means[0]:.2f} | {means[1]:.2f} |")
        progress.done("\n".join(lines))
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trials", type=int, default=40)
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", default="tuned.toml")
