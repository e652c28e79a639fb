"""Our method in-process: tracker -> kinematics on one demonstration, no bus needed.

The wiring is the services' (the tracker predicts with the latest model, the kinematics
estimator absorbs every initialised hand-body pose), minus the transport, so the evaluation runs
the same estimation code as the deployed services.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from services.common.protocol import KinematicModel
from services.evaluation.metrics import JointEstimate, tangent_error
from services.kinematics.config import KinematicsConfig
from services.kinematics.estimator import KinematicEstimator
from services.kinematics.prediction import predict_hand_pose
from services.synthetic.generator import Demonstration
from services.tracker.config import TrackerConfig
from services.tracker.tracker import HandObservation, HandTracker


@dataclass(frozen=True)
class PipelineResult:
    """Final model, the model after each frame (None before the first), and step timings."""

    final: KinematicModel
    history: Sequence[KinematicModel | None]
    stamps_ns: np.ndarray
    step_seconds: np.ndarray


def joint_estimate(model: KinematicModel) -> JointEstimate:
    """The most probable joint of a model.

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
    """Feed every frame of ``demo`` through the tracker and the kinematics estimator.

    The tracker gets every hand the detector delivers in a frame (``demo.detections``, an idle
    second hand included) and picks the manipulating one itself; bodies it produces late
    (``StepResult.replayed``) are absorbed in order before the frame's own. A hand body of a new body epoch
    (``HandBodyEstimate.body_epoch``: the tracker defined a new body frame) starts a new
    estimate: poses of two body frames are never mixed.
    """
    tracker = HandTracker(tracker_config or TrackerConfig())
    estimator = KinematicEstimator(kinematics_config or KinematicsConfig())
    model: KinematicModel | None = None
    epoch: int | None = None
    history: list[KinematicModel | None] = []
    seconds = np.zeros(len(demo.stamps_ns))

    def prior(stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        return None if model is None else predict_hand_pose(model, stamp_ns)

    for i, stamp in enumerate(demo.stamps_ns):
        t0 = time.perf_counter()
        hands = [HandObservation(handedness=d.handedness, score=d.score,
                                 points=np.asarray(d.points, float),
                                 visibility=np.asarray(d.visibility, float))
                 for d in demo.detections(i)]
        step = tracker.step(int(stamp), hands, kinematic_prior=prior)
        for body in (*step.replayed, step.estimate):
            if body is None or not body.initialized:
                continue
            if epoch is not None and body.body_epoch != epoch:
                estimator.reset()
                model = None
            epoch = body.body_epoch
            result = estimator.update(int(body.stamp_ns), body.pose, body.covariance[:6, :6])
            if result.model is not None:
                model = result.model
        seconds[i] = time.perf_counter() - t0
        history.append(model)
    return PipelineResult(final=estimator.model, history=history,
                          stamps_ns=np.asarray(demo.stamps_ns), step_seconds=seconds)


def ablation_config(config: TrackerConfig | None = None) -> TrackerConfig:
    """The "without uncertainty models" variant of a tracker config."""
    return replace(config or TrackerConfig(), use_uncertainty_models=False)


def no_kinematic_prior_config(config: TrackerConfig | None = None) -> TrackerConfig:
    """The "without the kinematic motion model" variant of a tracker config."""
    return replace(config or TrackerConfig(), use_kinematic_prior=False)


def demo_tangent_error_deg(model: KinematicModel, demo: Demonstration) -> float:
    """Tangent error (deg) of ``model``'s most probable joint (:func:`joint_estimate`) against
    ``demo``'s true joint, sampled along the true grasp path (camera frame)."""
    truth = JointEstimate.from_joint(demo.truth.joint)
    return float(np.degrees(tangent_error(truth, joint_estimate(model), demo.truth.grasp_points)))
