"""The robot's grasp poses as a second source of the joint estimate (docs/estimation.md is the
camera's; this module: docs/robot_bridge.md#kinematics-fusion).

While the robot bridge articulates, it publishes its grasp pose on ``handkse/{rig}/robot/body``
(a ``HandBody`` of the gripper, in the demonstration's frame, with the robot's own covariance).
:class:`RobotFusion` continues the estimate of the latest contact phase with a verdict (the
model the robot executes, :meth:`SegmentedEstimator.continuation`) in a separate
:class:`KinematicEstimator` restored from that phase's state, fed the robot's poses carried onto
the phase's last hand pose like a re-grasp: ``T' = T T_1^-1 T_end`` (``T_1`` the session's first
robot pose, ``T_end`` the phase's hand pose at its end), which leaves every displacement, and
so the joint, unchanged. The gripper is another body than the hand: its poses never enter the
camera's estimators, and the camera's estimate is never changed by them.

A session is one articulation: robot bodies less than ``session_gap_s`` apart. Each session
starts again from the camera's estimate (a refinement is not carried into the next one), and
``q`` continues from the phase's last value (its offset from the object's joint is whatever the
object was turned by between the demonstration and the grasp). Robot bodies are refused while the
hand is in contact (a phase is open: two bodies would move one joint) and when there is no
articulated phase to continue. No I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from services.common.protocol import KinematicModel
from services.kinematics.config import KinematicsConfig
from services.kinematics.estimator import KinematicEstimator, RejectReason
from services.kinematics.filters.geometry import se3_inverse_fast
from services.kinematics.segments import SegmentedEstimator

Array = NDArray[np.float64]

FusionRefusal = Literal["hand_in_contact", "no_articulated_model"]


@dataclass(frozen=True)
class RobotFusionConfig:
    """Fusion of ``robot/body`` (opt-in: ``handkse kinematics --fuse-robot-body``).

    ``session_gap_s``: a robot body this long after the previous one starts a new session (s).
    """

    session_gap_s: float = 0.5

    def __post_init__(self) -> None:
        if not self.session_gap_s > 0.0:
            raise ValueError(f"robot fusion session_gap_s must be > 0, got {self.session_gap_s!r}")


@dataclass(frozen=True)
class FusionUpdate:
    """One robot body's outcome: the refined model to publish, or why not (``reason``)."""

    model: KinematicModel | None
    reason: RejectReason | FusionRefusal | None = None
    note: str = ""


class _Session:
    def __init__(self, base: KinematicModel, estimator: KinematicEstimator,
                 pose_map: Array) -> None:
        self.base = base                 # the continued phase's model (its segment fields)
        self.estimator = estimator
        self.pose_map = pose_map         # estimator pose = robot pose @ pose_map
        self.last_ns: int | None = None


class RobotFusion:
    """Sessions of robot grasp poses continuing the latest verdict phase (module docstring)."""

    def __init__(self, config: KinematicsConfig, fusion: RobotFusionConfig | None = None) -> None:
        self.config = config
        self.fusion = RobotFusionConfig() if fusion is None else fusion
        self._session: _Session | None = None
        self.sessions = 0

    def reset(self) -> None:
        """Forget the session (a new demonstration)."""
        self._session = None

    @property
    def active(self) -> bool:
        return self._session is not None

    def update(self, segmented: SegmentedEstimator, stamp_ns: int, T_frame_tcp: Array,
               pose_covariance: Array) -> FusionUpdate:
        """Absorb one robot grasp pose (``T_frame_tcp`` 4x4 in the demonstration's frame, its
        6x6 left-perturbation covariance, linear first, [m^2, rad^2]); never raises."""
        if segmented.phase == "contact":
            self._session = None
            return FusionUpdate(None, "hand_in_contact",
                                "the hand is in contact: its body and the gripper's would "
                                "move one joint")
        s = self._session
        gap_ns = self.fusion.session_gap_s * 1e9
        if s is None or (s.last_ns is not None and isinstance(stamp_ns, (int, np.integer))
                         and int(stamp_ns) - s.last_ns > gap_ns):
            s = self._start(segmented, T_frame_tcp)
            if isinstance(s, FusionUpdate):
                return s
        try:
            T = np.asarray(T_frame_tcp, dtype=float) @ s.pose_map
        except (TypeError, ValueError):
            return FusionUpdate(None, "invalid_value")
        if T.shape != (4, 4):
            return FusionUpdate(None, "bad_shape")
        result = s.estimator.update(stamp_ns, T, pose_covariance)
        if result.reason is not None or result.model is None:
            if s.last_ns is None:
                self._session = None  # its first pose was refused: the next one starts again
            return FusionUpdate(None, result.reason, result.note)
        s.last_ns = int(stamp_ns)
        self._session = s
        m = result.model
        reference = np.asarray(m.reference_pose, dtype=float) @ se3_inverse_fast(s.pose_map)
        reference.flags.writeable = False
        b = s.base
        return FusionUpdate(replace(m, reference_pose=reference, segment=b.segment,
                                    segment_start_ns=b.segment_start_ns,
                                    segment_end_ns=b.segment_end_ns,
                                    first_segment=b.first_segment, phase="free"),
                            note=result.note)

    def _start(self, segmented: SegmentedEstimator, T_frame_tcp: Array) -> _Session | FusionUpdate:
        cont = segmented.continuation()
        if cont is None or cont[0].type not in ("prismatic", "revolute"):
            self._session = None
            return FusionUpdate(None, "no_articulated_model",
                                "no articulated contact phase to refine from the robot's motion")
        base, snapshot, T_end = cont
        try:
            T1 = np.asarray(T_frame_tcp, dtype=float)
            if T1.shape != (4, 4) or not np.isfinite(T1).all():
                return FusionUpdate(None, "non_finite" if T1.shape == (4, 4) else "bad_shape")
        except (TypeError, ValueError):
            return FusionUpdate(None, "invalid_value")
        estimator = KinematicEstimator.from_snapshot(snapshot, self.config)
        self.sessions += 1
        return _Session(base, estimator, se3_inverse_fast(T1) @ np.asarray(T_end, float))
