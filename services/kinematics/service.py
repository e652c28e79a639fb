"""Kinematics service: HandBody in, KinematicModel out; the current model answers ``get``.

Subscribes ``handkse/{rig}/hand/body``, publishes ``handkse/{rig}/kinematics/model`` after every
update, answers ``get`` on the same key (msgpack, or JSON with ``?format=json``), and restarts
the demonstration on ``reset``. After every update the estimator's state is written atomically
(temporary file + rename, by a writer thread off the update path) to the state file and restored
at start, so a killed and restarted service continues the demonstration where it was.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
from pathlib import Path

import numpy as np

from services.common.bus import JSON, Bus, QueryAnswer, QueryRequest, options_from_args
from services.common.config import section_from_args
from services.common.keys import Keys
from services.common.protocol import (
    HandBody,
    KinematicModel,
    PrismaticParams,
    RevoluteParams,
)
from services.common.service import BusLike, Service, stop_on_signals
from services.common.state_file import StateFile
from services.kinematics.config import KinematicsConfig
from services.kinematics.estimator import KinematicBelief, KinematicEstimator

log = logging.getLogger(__name__)

SNAPSHOT_VERSION = 1


def model_message(belief: KinematicBelief, seq: int) -> KinematicModel:
    """The wire form of an estimator belief."""
    p, r = belief.prismatic, belief.revolute
    return KinematicModel(
        seq=seq, stamp_ns=int(belief.stamp_ns), frame_id=belief.frame_id, type=belief.type,
        probabilities={k: float(v) for k, v in belief.probabilities.items()},
        prismatic=None if p is None else PrismaticParams(
            axis=np.asarray(p.axis, "<f8"), q=float(p.q), dq=float(p.dq),
            covariance=np.asarray(p.covariance, "<f8")),
        revolute=None if r is None else RevoluteParams(
            axis=np.asarray(r.axis, "<f8"), point=np.asarray(r.point, "<f8"), q=float(r.q),
            dq=float(r.dq), covariance=np.asarray(r.covariance, "<f8")),
        reference_pose=np.asarray(belief.reference_pose, "<f8"), updates=int(belief.updates))


class KinematicsNode:
    """Binds a :class:`KinematicEstimator` to the bus through a :class:`Service`."""

    def __init__(self, service: Service, config: KinematicsConfig,
                 state_file: Path | None = None) -> None:
        self.service = service
        self.config = config
        self.state_file = StateFile(state_file, SNAPSHOT_VERSION)
        self.estimator = self._restore() or KinematicEstimator(config)
        self._latest = model_message(self.estimator.belief, 0)
        self._lock = threading.Lock()
        keys = service.keys
        service.subscribe(keys.hand_body, HandBody, self.on_body)
        service.bus.declare_queryable(keys.kinematics_model, self.answer_model)
        service.on_reset(self.reset)

    def _restore(self) -> KinematicEstimator | None:
        doc = self.state_file.load()
        if doc is None:
            return None
        try:
            estimator = KinematicEstimator.from_snapshot(doc["estimator"], self.config)
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("ignoring unusable state file %s: %s", self.state_file.path, exc)
            return None
        log.info("restored kinematics state from %s (%d updates)", self.state_file.path,
                 estimator.belief.updates)
        return estimator

    def _save(self) -> None:
        self.state_file.save_later({"estimator": self.estimator.to_snapshot()})

    def on_body(self, body: HandBody) -> None:
        if not body.initialized:
            return  # the tracker has no hand pose yet; nothing to learn from
        if body.frame_id != self.estimator.frame_id:
            # A fresh estimator adopts the frame of its first body; a camera<->world switch in
            # the middle of a demonstration cannot continue it, so it starts a new one.
            if self.estimator.belief.updates > 0:
                self.service.reject("frame_changed",
                                    f"{self.estimator.frame_id} -> {body.frame_id}")
            self.estimator = KinematicEstimator(self.config, frame_id=body.frame_id)
        before = sum(self.estimator.rejected.values())
        with self.service.latency.measure("update"):
            belief = self.estimator.update(body.stamp_ns, np.array(body.pose),
                                           np.array(body.covariance[:6, :6]))
        if sum(self.estimator.rejected.values()) > before:
            reason = max(self.estimator.rejected, key=lambda r: self.estimator.rejected[r])
            self.service.reject(reason, f"hand body at {body.stamp_ns} ns")
            return
        self._publish(belief)
        self._save()

    def _publish(self, belief: KinematicBelief) -> None:
        keys = self.service.keys
        message = model_message(belief, self.service.next_seq(keys.kinematics_model))
        with self._lock:
            self._latest = message
        self.service.publish(keys.kinematics_model, message)

    def reset(self) -> None:
        self.estimator.reset()
        self._publish(self.estimator.belief)
        self._save()

    def answer_model(self, request: QueryRequest) -> QueryAnswer:
        """Runs on a bus thread: reads only the latest immutable message."""
        with self._lock:
            message = self._latest
        if request.parameters.get("format") == "json":
            return QueryAnswer(json.dumps(message.to_json_obj()).encode(), JSON)
        return QueryAnswer(message.to_msgpack())


def run(bus: BusLike, keys: Keys, config: KinematicsConfig, stop: threading.Event,
        state_file: Path | None = None) -> None:
    service = Service("kinematics", bus, keys)
    node = KinematicsNode(service, config, state_file)
    service.run(stop)
    node.state_file.flush()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--state-file", type=Path,
                        help="write the estimator state here after every update and restore it "
                             "at start (survives kill and restart)")


def main(args: argparse.Namespace) -> int:
    config = section_from_args(args, "kinematics")
    stop = threading.Event()
    stop_on_signals(stop)
    base = section_from_args(args, "zenoh")
    with Bus(options_from_args(args, base)) as bus:
        print("kinematics ready", flush=True)
        run(bus, Keys(args.rig), config, stop, args.state_file)
    return 0
