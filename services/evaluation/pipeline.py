"""Our method in-process: tracker -> kinematics on one demonstration, no bus needed.

The wiring is the services' (the tracker predicts with the latest model while the hand is in
contact, the kinematics estimator absorbs every initialised hand-body pose), minus the
transport, so the evaluation runs the same estimation code as the deployed services.

``segmented=False`` feeds every pose to one :class:`KinematicEstimator` (the stream is one
contact phase: the ``cut`` variant's setting); ``segmented=True`` runs the deployed service's
:class:`SegmentedEstimator` (contact phases found online; docs/estimation.md#contact-phases)
and also returns the phase decided at every frame and every phase's model. By default a
demonstration of the ``cut`` variant is not segmented, every other (whole, sequence, regrasp,
the free stream) is.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from services.common.protocol import KinematicModel
from services.evaluation.metrics import JointEstimate, tangent_error
from services.kinematics.config import KinematicsConfig
from services.kinematics.contact import SegmentationConfig
from services.kinematics.estimator import KinematicEstimator
from services.kinematics.phase_watch import ContactPhaseWatch, predicts_hand
from services.kinematics.prediction import predict_hand_pose
from services.kinematics.segments import SegmentedEstimator
from services.synthetic.generator import Demonstration
from services.tracker.config import TrackerConfig
from services.tracker.tracker import HandObservation, HandTracker


@dataclass(frozen=True)
class PipelineResult:
    """Final model, the model after each frame (None before the first), and step timings.

    ``final`` is what a ``get`` on the kinematics service answers after the last frame (for a
    segmented run: the model of the latest contact phase with a verdict). Segmented runs also
    give ``phases``, the phase decided online at each frame ("contact"/"free"; "free" while the
    tracker has no hand body yet), and ``segment_models``, every contact phase's model, oldest
    first (``segment_start_ns``/``segment_end_ns`` are the dated onset and release; the last
    phase's end is None if it was still open); both None for an unsegmented run.
    """

    final: KinematicModel
    history: Sequence[KinematicModel | None]
    stamps_ns: np.ndarray
    step_seconds: np.ndarray
    phases: Sequence[str] | None = None
    segment_models: tuple[KinematicModel, ...] | None = None


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
                 kinematics_config: KinematicsConfig | None = None, *,
                 segmented: bool | None = None,
                 segmentation_config: SegmentationConfig | None = None) -> PipelineResult:
    """Feed every frame of ``demo`` through the tracker and the kinematics estimator (module
    docstring for ``segmented``).

    The tracker gets every hand the detector delivers in a frame (``demo.detections``, an idle
    second hand included) and picks the manipulating one itself; bodies it produces late
    (``StepResult.replayed``) are absorbed in order before the frame's own. A hand body of a new
    body epoch (``HandBodyEstimate.body_epoch``: the tracker defined a new body frame) starts a
    new estimate (segmented: the open contact phase's): poses of two body frames are never mixed.
    Segmented, the wiring is the services' (:mod:`services.kinematics.phase_watch`): the tracker
    predicts with the model only while in contact and starts a new hand body when a contact phase
    begins.
    """
    tracker = HandTracker(tracker_config or TrackerConfig())
    config = kinematics_config or KinematicsConfig()
    estimator = KinematicEstimator(config)
    if segmented is None:
        segmented = demo.variant != "cut"
    sequence = SegmentedEstimator(config, segmentation_config) if segmented else None
    watch = ContactPhaseWatch()
    model: KinematicModel | None = None
    epoch: int | None = None
    history: list[KinematicModel | None] = []
    phases: list[str] = []
    seconds = np.zeros(len(demo.stamps_ns))

    def prior(stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        return predict_hand_pose(model, stamp_ns) if predicts_hand(model) else None  # type: ignore[arg-type]

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
            if sequence is not None:
                update = sequence.update(int(body.stamp_ns), body.pose, body.covariance[:6, :6],
                                         body.landmark_points, body.body_epoch)
                if update.model is not None:
                    model = update.model
                    if watch.new_contact(model):
                        tracker.reset()  # its later bodies of this step are of the old body
                        break
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
        phases.append("contact" if model is not None and model.phase == "contact" else "free")
    if sequence is None:
        return PipelineResult(final=estimator.model, history=history,
                              stamps_ns=np.asarray(demo.stamps_ns), step_seconds=seconds)
    return PipelineResult(final=sequence.verdict_model, history=history,
                          stamps_ns=np.asarray(demo.stamps_ns), step_seconds=seconds,
                          phases=phases, segment_models=sequence.models)


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
