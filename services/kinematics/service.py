"""Kinematics service: HandBody in, KinematicModel out; the current model answers ``get``.

Subscribes ``handkse/{rig}/hand/body``, publishes ``handkse/{rig}/kinematics/model`` after every
accepted update (with its own ``seq``; the estimator's models carry 0), answers ``get`` on the
same key (msgpack, or JSON with ``?format=json``), and restarts the demonstration on ``reset``.
A reset publishes nothing: the next model is the one of the first hand body of the new
demonstration; until then ``get`` answers the empty model (``updates`` 0, ``stamp_ns`` 0, type
unknown), as at a first start (docs/protocol.md). A rejected hand body is counted under the
estimator's reason for that body. After every update the estimator's state is written atomically
(temporary file + rename, by a writer thread off the update path) to the state file and restored
at start, so a killed and restarted service continues the demonstration where it was.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
from dataclasses import replace
from pathlib import Path

from services.common.bus import JSON, Bus, QueryAnswer, QueryRequest, options_from_args
from services.common.config import section_from_args
from services.common.keys import Keys
from services.common.protocol import HandBody, KinematicModel
from services.common.service import BusLike, Service, stop_on_signals
from services.common.state_file import StateFile
from services.kinematics.config import KinematicsConfig
from services.kinematics.estimator import KinematicEstimator

log = logging.getLogger(__name__)

SNAPSHOT_VERSION = 1


class KinematicsNode:
    """Binds a :class:`KinematicEstimator` to the bus through a :class:`Service`."""

    def __init__(self, service: Service, config: KinematicsConfig,
                 state_file: Path | None = None) -> None:
        self.service = service
        self.config = config
        self.state_file = StateFile(state_file, SNAPSHOT_VERSION)
        self.estimator = self._restore() or KinematicEstimator(config)
        self._latest = self.estimator.model
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
                 estimator.model.updates)
        return estimator

    def _save(self) -> None:
        self.state_file.save_later({"estimator": self.estimator.to_snapshot()})

    def on_body(self, body: HandBody) -> None:
        if not body.initialized:
            return  # the tracker has no hand pose yet; nothing to learn from
        if body.frame_id != self.estimator.frame_id:
            # A fresh estimator adopts the frame of its first body; a camera<->world switch in
            # the middle of a demonstration cannot continue it, so it starts a new one.
            if self.estimator.model.updates > 0:
                self.service.reject("frame_changed",
                                    f"{self.estimator.frame_id} -> {body.frame_id}")
            self.estimator = KinematicEstimator(self.config, frame_id=body.frame_id)
        with self.service.latency.measure("update"):
            result = self.estimator.update(body.stamp_ns, body.pose, body.covariance[:6, :6])
        if result.reason is not None:
            self.service.reject(result.reason, f"hand body at {body.stamp_ns} ns")
            return
        assert result.model is not None
        self._publish(result.model)
        self._save()

    def _publish(self, model: KinematicModel) -> None:
        keys = self.service.keys
        message = replace(model, seq=self.service.next_seq(keys.kinematics_model))
        with self._lock:
            self._latest = message
        self.service.publish(keys.kinematics_model, message)

    def reset(self) -> None:
        """Forget the demonstration; publish nothing until its first hand body (module docstring)."""
        self.estimator.reset()
        with self._lock:
            self._latest = self.estimator.model
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
