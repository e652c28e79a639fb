"""Our method in-process: tracker -> kinematics on one demonstration, no bus needed.

The wiring is the services' (the tracker predicts with the latest model, the kinematics
estimator absorbs every initialised hand-body pose), minus the transport, so the evaluation runs
the same estimation code as the deployed services.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from services.kinematics.config import KinematicsConfig
from services.kinematics.estimator import KinematicBelief, KinematicEstimator
from services.kinematics.metrics import JointEstimate
from services.kinematics.prediction import predict_hand_pose
from services.synthetic.generator import Demonstration
from services.tracker.config import TrackerConfig
from services.tracker.tracker import HandObservation, HandTracker


@dataclass(frozen=True)
class PipelineResult:
    """Final belief, the belief after each frame (None before the first), and step timings."""

    final: KinematicBelief
    history: Sequence[KinematicBelief | None]
    stamps_ns: np.ndarray
    step_seconds: np.ndarray


def joint_estimate(model: Any) -> JointEstimate:
    """The most probable joint of a ``KinematicBelief`` or wire ``KinematicModel`` (same fields).

    Rigid, disconnected and unknown carry no axis; the prismatic line passes through the hand
    at q = 0 (``reference_pose``).
    """
    if model.type == "revolute" and model.revolute is not None:
        return JointEstimate(type="revolute", axis=np.asarray(model.revolute.axis, float),
                             point=np.asarray(model.revolute.point, float))
    if model.type == "prismatic" and model.prismatic is not None:
        return JointEstimate(type="prismatic", axis=np.asarray(model.prismatic.axis, float),
                             point=np.asarray(model.reference_pose, float)[:3, 3])
    return JointEstimate(type="rigid", axis=np.zeros(3), point=np.zeros(3))


def run_pipeline(demo: Demonstration, tracker_config: TrackerConfig | None = None,
                 kinematics_config: KinematicsConfig | None = None) -> PipelineResult:
    """Feed every frame of ``demo`` through the tracker and the kinematics estimator."""
    tracker = HandTracker(tracker_config or TrackerConfig())
    estimator = KinematicEstimator(kinematics_config or KinematicsConfig())
    belief: KinematicBelief | None = None
    history: list[KinematicBelief | None] = []
    seconds = np.zeros(len(demo.stamps_ns))

    def prior(stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        return None if belief is None else predict_hand_pose(belief, stamp_ns)

    for i, stamp in enumerate(demo.stamps_ns):
        t0 = time.perf_counter()
        hand = HandObservation(handedness=demo.handedness, score=float(demo.score[i]),
                               points=np.asarray(demo.points[i], float),
                               visibility=np.asarray(demo.visibility[i], float))
        body = tracker.step(int(stamp), [hand], kinematic_prior=prior).estimate
        if body is not None and body.initialized:
            updated = estimator.update(int(stamp), body.pose, body.covariance[:6, :6])
            belief = updated if updated is not None else belief
        seconds[i] = time.perf_counter() - t0
        history.append(belief)
    final = belief if belief is not None else estimator.belief
    return PipelineResult(final=final, history=history, stamps_ns=np.asarray(demo.stamps_ns),
                          step_seconds=seconds)


def ablation_config(config: TrackerConfig | None = None) -> TrackerConfig:
    """The "without uncertainty models" variant of a tracker config."""
    return replace(config or TrackerConfig(), use_uncertainty_models=False)
