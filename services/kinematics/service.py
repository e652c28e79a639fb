"""Kinematics service: HandBody in, KinematicModel out; the current model answers ``get``.

Subscribes ``handkse/{rig}/hand/body``, publishes ``handkse/{rig}/kinematics/model`` after every
accepted update (with its own ``seq``; the estimator's models carry 0), answers ``get`` on the
same key (msgpack, or JSON with ``?format=json``) and on ``handkse/{rig}/kinematics/models``
(``KinematicModelList``: every contact phase's model), and restarts the demonstration on
``reset``. The estimate is segmented into contact phases (:mod:`services.kinematics.segments`,
docs/estimation.md#contact-phases): the published model is the open phase's while the hand is in
contact, else the latest phase with a verdict, which is also what ``get`` answers. A body of a new
``body_epoch`` (a new body frame of the tracker) restarts the open phase's estimate.
A reset publishes nothing: the next model is the one of the first hand body of the new
demonstration; until then ``get`` answers the empty model (``updates`` 0, ``stamp_ns`` 0, type
unknown), as at a first start (docs/protocol.md). A rejected hand body is counted under the
reason for that body: ``frame_changed`` (its ``frame_id`` is not the demonstration's; a new
demonstration, after a reset, adopts the frame of its first body), ``far_future`` (its stamp runs
far ahead of the stream or of the receive clock, :mod:`services.common.stamps`), or the
estimator's reason (:data:`~services.kinematics.estimator.RejectReason`, ``outlier`` among them).
After every update the estimator's state is written atomically (temporary file + rename, by a
writer thread off the update path) to the state file and restored at start, so a killed and
restarted service continues the demonstration where it was, every closed contact phase
included. A state file that does not hold a valid estimate (any field of the wrong type, shape
or range, NaN, an unknown frame, a stamp far ahead of the clock) is ignored with a warning naming
the problem: the service starts fresh.

With ``robot_fusion`` (opt-in, ``--fuse-robot-body``) it also subscribes
``handkse/{rig}/robot/body``: the robot bridge's grasp poses while it articulates continue the
latest articulated phase's estimate in a separate estimator (:mod:`services.kinematics.
robot_fusion`); each accepted one publishes the refined model as usual (``get`` answers it until
the next camera update). Refused robot bodies are counted as ``robot_`` plus the reason (e.g.
``robot_hand_in_contact``, ``robot_no_articulated_model``, ``robot_frame_changed``). The robot
session is not written to the state file.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from services.common.bus import JSON, Bus, QueryAnswer, QueryRequest, options_from_args
from services.common.config import section_from_args
from services.common.keys import Keys
from services.common.protocol import HandBody, KinematicModel, KinematicModelList
from services.common.service import BusLike, Service, ServiceLimits, stop_on_signals
from services.common.stamps import StampLimits, StampWindow
from services.common.state_file import StateFile
from services.kinematics.config import KinematicsConfig
from services.kinematics.contact import SegmentationConfig
from services.kinematics.robot_fusion import RobotFusion, RobotFusionConfig
from services.kinematics.segments import SegmentedEstimator, verdict_of

log = logging.getLogger(__name__)

SNAPSHOT_VERSION = 3


class KinematicsNode:
    """Binds a :class:`SegmentedEstimator` to the bus through a :class:`Service`.

    ``clock``: the receive clock (wall clock, ns) that stamps are compared with.
    """

    def __init__(self, service: Service, config: KinematicsConfig,
                 state_file: Path | None = None, stamp_limits: StampLimits | None = None,
                 clock: Callable[[], int] = time.time_ns,
                 segmentation: SegmentationConfig | None = None,
                 robot_fusion: RobotFusionConfig | None = None) -> None:
        self.service = service
        self.config = config
        self.segmentation = SegmentationConfig() if segmentation is None else segmentation
        self.stamp_limits = StampLimits() if stamp_limits is None else stamp_limits
        self.clock = clock
        self.state_file = StateFile(state_file, SNAPSHOT_VERSION)
        self.estimator, self.stamps = self._restore() or (
            SegmentedEstimator(config, self.segmentation), StampWindow(self.stamp_limits))
        self._latest = self.estimator.model
        self._closed = self.estimator.closed
        self._lock = threading.Lock()
        keys = service.keys
        service.subscribe(keys.hand_body, HandBody, self.on_body)
        self.robot = None if robot_fusion is None else RobotFusion(config, robot_fusion)
        self.robot_stamps = StampWindow(self.stamp_limits)
        if self.robot is not None:
            service.subscribe(keys.robot_body, HandBody, self.on_robot_body)
        service.bus.declare_queryable(keys.kinematics_model, self.answer_model)
        service.bus.declare_queryable(keys.kinematics_models, self.answer_models)
        service.on_reset(self.reset)

    def _restore(self) -> tuple[SegmentedEstimator, StampWindow] | None:
        """The estimator and stamp window of the state file, or None (absent, or not valid)."""
        try:
            doc = self.state_file.load()
            if doc is None:
                return None
            if not isinstance(doc, dict) or set(doc) != {"estimator", "stamps"}:
                raise ValueError(f"expected the keys estimator and stamps, got {sorted(doc)}")
            now = self.clock()
            estimator = SegmentedEstimator.from_snapshot(doc["estimator"], self.config,
                                                         self.segmentation)
            stamps = StampWindow.from_state(doc["stamps"], self.stamp_limits, now)
            last = estimator.last_stamp_ns
            problem = None if last is None else stamps.lead_problem(last, now)
            if problem is not None:
                raise ValueError(f"estimator.last_stamp_ns: {problem}")
        except Exception as exc:  # whatever a corrupt file makes the restore raise: start fresh
            log.warning("ignoring the state file %s, it does not hold a valid estimate (%s: %s); "
                        "starting a new demonstration", self.state_file.path,
                        type(exc).__name__, exc)
            return None
        log.info("restored kinematics state from %s (%d closed contact phases, %d updates)",
                 self.state_file.path, len(estimator.closed), estimator.model.updates)
        return estimator, stamps

    def _save(self) -> None:
        self.state_file.save_later({"estimator": self.estimator.to_snapshot(),
                                    "stamps": self.stamps.to_state()})

    def on_body(self, body: HandBody) -> None:
        if not body.initialized:
            return  # the tracker has no hand pose yet; nothing to learn from
        if body.frame_id != self.estimator.frame_id:
            if self.estimator.last_stamp_ns is not None:
                # a demonstration is estimated in one frame; a body in another cannot continue
                # it (and must not end it): refused until a reset starts a new one
                self.service.reject("frame_changed", f"hand body at {body.stamp_ns} ns in "
                                    f"{body.frame_id!r}, the demonstration is in "
                                    f"{self.estimator.frame_id!r} (reset to start a new one)")
                return
            self.estimator = SegmentedEstimator(self.config, self.segmentation,
                                                frame_id=body.frame_id)
        received = self.clock()
        far = self.stamps.check(body.stamp_ns, received)
        if far is not None:
            self.service.reject("far_future", f"hand body: {far}")
            return
        with self.service.latency.measure("update"):
            result = self.estimator.update(body.stamp_ns, body.pose, body.covariance[:6, :6],
                                           body.landmarks.points, body.body_epoch)
        if result.reason is not None:
            detail = f": {result.note}" if result.note else ""
            self.service.reject(result.reason, f"hand body at {body.stamp_ns} ns{detail}")
            return
        if result.note:
            log.warning("kinematics: %s", result.note)
        assert result.model is not None
        self.stamps.accept(body.stamp_ns, received)
        self._publish(result.model)
        self._save()

    def on_robot_body(self, body: HandBody) -> None:
        """A robot grasp pose (module docstring): refine and publish, or count why not."""
        assert self.robot is not None
        if not body.initialized:
            return
        if body.frame_id != self.estimator.frame_id:
            self.service.reject("robot_frame_changed", f"robot body at {body.stamp_ns} ns in "
                                f"{body.frame_id!r}, the demonstration is in "
                                f"{self.estimator.frame_id!r}")
            return
        received = self.clock()
        far = self.robot_stamps.check(body.stamp_ns, received)
        if far is not None:
            self.service.reject("robot_far_future", f"robot body: {far}")
            return
        with self.service.latency.measure("robot_update"):
            result = self.robot.update(self.estimator, body.stamp_ns, body.pose,
                                       body.covariance[:6, :6])
        if result.reason is not None or result.model is None:
            detail = f": {result.note}" if result.note else ""
            self.service.reject(f"robot_{result.reason}", f"robot body at {body.stamp_ns} ns"
                                f"{detail}")
            return
        self.robot_stamps.accept(body.stamp_ns, received)
        self._publish(result.model)

    def _publish(self, model: KinematicModel) -> None:
        keys = self.service.keys
        message = replace(model, seq=self.service.next_seq(keys.kinematics_model))
        closed = self.estimator.closed
        with self._lock:
            self._latest = message
            self._closed = closed
        self.service.publish(keys.kinematics_model, message)

    def reset(self) -> None:
        """Forget the demonstration (and the stream's stamps: a new one may bring another clock);
        publish nothing until its first hand body (module docstring)."""
        self.estimator.reset()
        self.stamps.forget()
        self.robot_stamps.forget()
        if self.robot is not None:
            self.robot.reset()
        with self._lock:
            self._latest = self.estimator.model
            self._closed = ()
        self._save()

    def answer_model(self, request: QueryRequest) -> QueryAnswer:
        """The model of the latest contact phase with a verdict (:func:`verdict_of`), with the
        latest message's envelope. Runs on a bus thread: reads only immutable messages."""
        with self._lock:
            message, closed = self._latest, self._closed
        return _answer(verdict_of(closed, message), request)

    def answer_models(self, request: QueryRequest) -> QueryAnswer:
        """``KinematicModelList``: every contact phase's model, oldest first, each with the
        latest message's stamp and phase (the open phase's is the latest message). Runs on a bus
        thread: reads only immutable messages."""
        with self._lock:
            latest, closed = self._latest, self._closed
        models = [replace(m, stamp_ns=latest.stamp_ns, phase=latest.phase) for m in closed]
        if latest.phase == "contact" and latest.segment == len(closed):
            models.append(latest)
        return _answer(KinematicModelList(seq=latest.seq, stamp_ns=latest.stamp_ns,
                                          frame_id=latest.frame_id, models=tuple(models)),
                       request)


def _answer(message: KinematicModel | KinematicModelList, request: QueryRequest) -> QueryAnswer:
    """msgpack, or UTF-8 JSON with the selector parameter ``format=json``."""
    if request.parameters.get("format") == "json":
        return QueryAnswer(json.dumps(message.to_json_obj()).encode(), JSON)
    return QueryAnswer(message.to_msgpack())


def run(bus: BusLike, keys: Keys, config: KinematicsConfig, stop: threading.Event,
        state_file: Path | None = None, stamp_limits: StampLimits | None = None,
        limits: ServiceLimits | None = None,
        segmentation: SegmentationConfig | None = None,
        robot_fusion: RobotFusionConfig | None = None) -> None:
    service = Service("kinematics", bus, keys, limits)
    node = KinematicsNode(service, config, state_file, stamp_limits, segmentation=segmentation,
                          robot_fusion=robot_fusion)
    service.run(stop)
    node.state_file.flush()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--state-file", type=Path,
                        help="write the estimator state here after every update and restore it "
                             "at start (survives kill and restart)")
    parser.add_argument("--fuse-robot-body", action="store_true",
                        help="also refine the latest articulated phase's estimate from the robot "
                             "bridge's grasp poses (robot/body) while it articulates")


def main(args: argparse.Namespace) -> int:
    config = section_from_args(args, "kinematics")
    stamp_limits = section_from_args(args, "stamps")
    stop = threading.Event()
    stop_on_signals(stop)
    base = section_from_args(args, "zenoh")
    with Bus(options_from_args(args, base)) as bus:
        print("kinematics ready", flush=True)
        run(bus, Keys(args.rig), config, stop, args.state_file, stamp_limits,
            section_from_args(args, "limits"), section_from_args(args, "segmentation"),
            RobotFusionConfig() if getattr(args, "fuse_robot_body", False) else None)
    return 0
