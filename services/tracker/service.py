"""Tracker service: HandLandmarks in, HandBody out.

Subscribes ``handkse/{rig}/hand/landmarks`` (FIFO: every frame matters to the filters) and
``handkse/{rig}/kinematics/model`` (the latest model drives the third motion model, through the
same prediction function the kinematics library uses), publishes ``handkse/{rig}/hand/body``.

With ``--state-file`` the hand body model (body-frame landmark coordinates) is written atomically
when a body is initialised and then about once a second, and restored at start: a tracker that is
killed and restarted re-acquires the hand in the same body frame, so the kinematics service's
displacements stay valid (``TrackerConfig.reacquire_body_frame``). ``reset`` forgets it. A state
file that does not hold a valid body model (unreadable, another version, any field of the wrong
type, shape or range, an unknown frame: :mod:`services.tracker.state`) is ignored with a warning
naming the fault, and the tracker starts without one; it never stops the start.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from services.common.bus import Bus, options_from_args
from services.common.config import section_from_args
from services.common.keys import Keys
from services.common.protocol import HandBody, HandLandmarks, KinematicModel, LandmarkStates
from services.common.service import BusLike, Service, ServiceLimits, stop_on_signals
from services.common.snapshot import SnapshotError
from services.common.stamps import StampLimits, StampWindow
from services.common.state_file import StateFile
from services.kinematics.phase_watch import ContactPhaseWatch, predicts_hand
from services.kinematics.prediction import predict_hand_pose
from services.tracker.config import TrackerConfig
from services.tracker.state import body_document, body_from_document, epoch_from_document
from services.tracker.tracker import FRAME_REJECTIONS, HandBodyEstimate, HandObservation, HandTracker

log = logging.getLogger(__name__)

SNAPSHOT_VERSION = 1
SAVE_PERIOD_NS = 1_000_000_000  # body model snapshots while tracking, in stamp time


def body_message(estimate: HandBodyEstimate, seq: int, frame_id: str | None = None) -> HandBody:
    """The wire form of a tracker estimate; ``frame_id`` overrides the tracker's own label
    (landmarks that already arrive in the world frame are tracked, and published, there)."""
    return HandBody(
        seq=seq, stamp_ns=int(estimate.stamp_ns), frame_id=frame_id or estimate.frame_id,
        initialized=bool(estimate.initialized), pose=np.asarray(estimate.pose, "<f8"),
        twist=np.asarray(estimate.twist, "<f8"),
        covariance=np.asarray(0.5 * (estimate.covariance + estimate.covariance.T), "<f8"),
        motion_model=estimate.motion_model,
        landmarks=LandmarkStates(points=np.asarray(estimate.landmark_points, "<f4"),
                                 variance=np.asarray(estimate.landmark_variance, "<f4"),
                                 status=np.asarray(estimate.landmark_status, "|u1")),
        body_epoch=int(estimate.body_epoch))


def observations(message: HandLandmarks) -> list[HandObservation]:
    """The tracker's input: camera-frame points (world points are taken back through
    ``T_world_camera``, which the tracker then applies itself)."""
    T = message.T_world_camera
    T_cw = None if T is None or message.frame_id != "world" else np.linalg.inv(T)
    return [HandObservation(handedness=h.handedness, score=float(h.score),
                            points=(np.asarray(h.points, float) if T_cw is None else
                                    np.asarray(h.points, float) @ T_cw[:3, :3].T + T_cw[:3, 3]),
                            visibility=np.asarray(h.visibility, float))
            for h in message.hands]


class TrackerNode:
    """Binds a :class:`HandTracker` to the bus through a :class:`Service`."""

    def __init__(self, service: Service, config: TrackerConfig,
                 state_file: Path | None = None, stamp_limits: StampLimits | None = None,
                 clock: Callable[[], int] = time.time_ns) -> None:
        self.service = service
        self.tracker = HandTracker(config)
        # A stamp far ahead must not become the latest (every real frame would then be out of
        # order), and a demonstration keeps the frame_id of its first landmarks.
        self.clock = clock
        self.stamps = StampWindow(stamp_limits)
        self._label: str | None = None
        self.model: KinematicModel | None = None
        self.phases = ContactPhaseWatch()
        self.state_file = StateFile(state_file, SNAPSHOT_VERSION)
        self._saved_stamp_ns: int | None = None
        self._restore()
        keys = service.keys
        service.subscribe(keys.hand_landmarks, HandLandmarks, self.on_landmarks)
        service.subscribe(keys.kinematics_model, KinematicModel, self.on_model, latest=True)
        service.on_reset(self.reset)

    def on_model(self, model: KinematicModel) -> None:
        if self.phases.new_contact(model):
            self.tracker.reset()  # a new hand body for the grasp (docs/estimation.md#contact-phases)
        self.model = model

    def _prior(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
        return predict_hand_pose(self.model, stamp_ns) if predicts_hand(self.model) else None  # type: ignore[arg-type]

    def on_landmarks(self, message: HandLandmarks) -> None:
        received = self.clock()
        far = self.stamps.check(message.stamp_ns, received)
        if far is not None:
            self.service.reject("far_future", f"landmarks: {far}")
            return
        if self._label is not None and message.frame_id != self._label:
            self.service.reject("frame_mismatch", f"landmarks in {message.frame_id!r}, this "
                                f"demonstration's are in {self._label!r} (reset to start anew)")
            return
        with self.service.latency.measure("step"):
            result = self.tracker.step(message.stamp_ns, observations(message),
                                       T_world_camera=message.T_world_camera,
                                       kinematic_prior=self._prior)
        for reason in result.rejected:
            self.service.reject(reason, f"landmarks at {message.stamp_ns} ns")
        if result.reason not in FRAME_REJECTIONS:
            self.stamps.accept(message.stamp_ns, received)
            self._label = message.frame_id
        skipped = self.service.skipped
        if result.reason is not None and result.skipped:
            skipped[result.reason] = skipped.get(result.reason, 0) + 1
        for note in result.notes:  # handled, but worth counting (StepResult.notes)
            skipped[note] = skipped.get(note, 0) + 1
        keys = self.service.keys
        for estimate in (*result.replayed, result.estimate):  # held-back frames first
            if estimate is None:
                continue
            self._maybe_save(estimate)
            frame = "world" if message.frame_id == "world" else estimate.frame_id
            self.service.publish(keys.hand_body, body_message(
                estimate, self.service.next_seq(keys.hand_body), frame))

    def reset(self) -> None:
        self.tracker.reset()
        self.stamps.forget()
        self._label = None
        self.model = None
        self.phases.reset()
        self._saved_stamp_ns = None
        self.state_file.save(body_document(None, self.tracker.body_epoch))

    def _restore(self) -> None:
        """Adopt the body model of the state file; on any fault in it (unreadable, of another
        version, a field of the wrong type, shape or range: :mod:`services.tracker.state`) warn,
        naming the fault, and start fresh. Never raises: a bad file must not stop a start."""
        try:
            doc = self.state_file.load()
            remembered = None if doc is None else body_from_document(doc)
            if remembered is None:
                epoch = None if doc is None else epoch_from_document(doc)
                if epoch is not None:  # after a reset: the next body frame is a new epoch
                    self.tracker.continue_epochs(epoch)
                return
            if not self.tracker.remember_body(remembered.frame_id, remembered.points,
                                              remembered.body_epoch):
                raise SnapshotError(
                    f"tracker.body.points: fewer than min_inliers = {self.tracker.config.min_inliers} "
                    "landmarks in the model")
        except Exception as exc:  # whatever a corrupt file makes the restore raise: start fresh
            log.warning("ignoring the state file %s, it does not hold a valid hand body model "
                        "(%s: %s); starting without one", self.state_file.path,
                        type(exc).__name__, exc)
            return
        log.info("restored the hand body model from %s", self.state_file.path)

    def _maybe_save(self, estimate: HandBodyEstimate) -> None:
        """Snapshot the body model at a (re)initialisation and then every ``SAVE_PERIOD_NS``."""
        if self.state_file.path is None:
            return
        if not estimate.initialized:
            self._saved_stamp_ns = None
            return
        last = self._saved_stamp_ns
        if last is not None and 0 <= estimate.stamp_ns - last < SAVE_PERIOD_NS:
            return
        remembered = self.tracker.remembered_body()
        if remembered is not None:
            self.state_file.save_later(body_document(remembered, self.tracker.body_epoch))
            self._saved_stamp_ns = estimate.stamp_ns


def run(bus: BusLike, keys: Keys, config: TrackerConfig, stop: threading.Event,
        state_file: Path | None = None, limits: ServiceLimits | None = None,
        stamp_limits: StampLimits | None = None) -> None:
    service = Service("tracker", bus, keys, limits)
    node = TrackerNode(service, config, state_file, stamp_limits)
    service.run(stop)
    node.state_file.flush()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--state-file", type=Path,
                        help="keep the hand body model here and restore it at start (a restarted "
                             "tracker continues the same body frame)")


def main(args: argparse.Namespace) -> int:
    config = section_from_args(args, "tracker")
    stop = threading.Event()
    stop_on_signals(stop)
    with Bus(options_from_args(args, section_from_args(args, "zenoh"))) as bus:
        print("tracker ready", flush=True)
        run(bus, Keys(args.rig), config, stop, args.state_file, section_from_args(args, "limits"),
            section_from_args(args, "stamps"))
    return 0
