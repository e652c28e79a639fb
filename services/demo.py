"""``handkse demo``: every service as its own process on loopback, one demonstration through them.

Starts a Zenoh router, the tracker and the kinematics service as separate processes on a TCP
loopback endpoint, replays a synthetic demonstration (default: the whole demonstration of the
key by participant 3: reach, grasp, turn, release, withdraw) in real time from this process,
stamped with the wall clock as ``handkse replay`` does, prints live progress (type,
probabilities, tangent error against the ground truth) and each contact phase as the kinematics
service detects it (:class:`PhasePrinter`), then queries the final model with ``get`` and prints
it beside the truth, and the detected phases beside the true contact intervals.

With the robot (the default), ``handkse robot-bridge --sim-object synthetic:OBJECT:P:SEED:VARIANT`` runs
as one more process: its simulated Panda holds the demonstration's true object, placed through
the bridge's camera calibration. The demo then asks it to articulate exactly as ``handkse
articulate`` does (:func:`services.robot_bridge.client.articulate`, the demonstrated task: 180 deg
for the key and the window lock, else the demonstrated stroke, the way the human moved) and
prints the bridge's answer. With ``view``, ``handkse view`` runs beside them as one more client
(Rerun's web viewer on 127.0.0.1; the URL is printed) and stays up, on a terminal, until Enter is
pressed.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from services.common.bus import Bus, BusError, ZenohOptions, wait_for_services
from services.common.errors import UserError
from services.common.keys import Keys
from services.common.playback import PlaybackOptions, play
from services.common.processes import ProcessGroup, client_args, free_tcp_endpoint
from services.common.protocol import HandLandmarks, KinematicModel, KinematicModelList
from services.evaluation.metrics import JointEstimate, axis_angle_error
from services.evaluation.pipeline import demo_tangent_error_deg, joint_estimate
from services.synthetic.generator import Demonstration, generate
from services.synthetic.replay import demonstration_recording

SERVICES = ("tracker", "kinematics")


def _progress_line(model: KinematicModel, demo: Demonstration, t: float) -> str:
    probs = " ".join(f"{k[:3]} {v:.2f}" for k, v in model.probabilities.items())
    err = demo_tangent_error_deg(model, demo) if model.type in ("prismatic", "revolute") else None
    err_text = f"{err:5.1f} deg" if err is not None else "  -  "
    return (f"  t={t:5.1f} s  updates {model.updates:4d}  {model.type:<12} [{probs}]  "
            f"tangent error {err_text}")


def print_comparison(model: KinematicModel, demo: Demonstration) -> float:
    """Print the final model beside the ground truth; returns the tangent error in degrees."""
    truth = JointEstimate.from_joint(demo.truth.joint)
    est = joint_estimate(model)
    err = demo_tangent_error_deg(model, demo)
    fmt = lambda v: "[" + ", ".join(f"{x:+.3f}" for x in v) + "]"  # noqa: E731
    print()
    print(f"{'':14}{'estimate':<34}{'ground truth':<34}")
    print(f"{'type':14}{est.type:<34}{truth.type:<34}")
    print(f"{'P(type)':14}{model.probabilities.get(est.type, 0.0):<34.3f}{'':34}")
    print(f"{'axis':14}{fmt(est.axis):<34}{fmt(truth.axis):<34}")
    if truth.type == "revolute" or est.type == "revolute":
        print(f"{'point (m)':14}{fmt(est.point):<34}{fmt(truth.point):<34}")
    print(f"{'updates':14}{model.updates:<34d}")
    print(f"\ntangent error {err:.1f} deg (frame: {model.frame_id})")
    if est.type in ("prismatic", "revolute") and truth.type in ("prismatic", "revolute"):
        # the tangent error mixes direction and position; a robot engineer wants both
        detail = f"axis direction {math.degrees(axis_angle_error(truth, est)):.1f} deg off"
        if est.type == truth.type == "revolute":
            grasp = np.asarray(demo.truth.grasp_points[0], float)  # where the hand grasps
            offset = _foot(est, grasp) - _foot(truth, grasp)
            detail += (f"; at the grasp the axis is {np.linalg.norm(offset) * 1e3:.0f} mm off, "
                       f"{np.linalg.norm(grasp - _foot(truth, grasp)) * 1e3:.0f} mm from the "
                       "grasp (a small radius turns millimetres into degrees of tangent)")
        print(detail)
    return err


def _foot(joint: JointEstimate, x: np.ndarray) -> np.ndarray:
    """The point of ``joint``'s axis line nearest ``x`` (camera frame, m)."""
    a, p = np.asarray(joint.axis, float), np.asarray(joint.point, float)
    return p + float((x - p) @ a) * a


class PhasePrinter:
    """Prints each contact phase as the published models reveal it: an onset when the models'
    ``phase`` turns to "contact", the phase's verdict when it turns back to "free".

    Times are seconds since the demonstration's first frame: ``offset_ns`` (set from the first
    landmark message heard) is what playback added to the recorded stamps.
    """

    def __init__(self, demo: Demonstration) -> None:
        self.start_ns = int(demo.stamps_ns[0])
        self.offset_ns: int | None = None
        self._phase: str | None = None

    def seconds(self, stamp_ns: int | None) -> float:
        """A published stamp as seconds since the demonstration's first frame."""
        if stamp_ns is None or self.offset_ns is None:
            return math.nan
        return (stamp_ns - self.offset_ns - self.start_ns) * 1e-9

    def on_landmarks(self, message: HandLandmarks) -> None:
        if self.offset_ns is None:
            self.offset_ns = message.stamp_ns - self.start_ns

    def on_model(self, model: KinematicModel) -> None:
        if model.phase is None or model.phase == self._phase:
            return
        if model.phase == "contact":
            print(f"  phase: contact from t={self.seconds(model.segment_start_ns):.2f} s "
                  f"(segment {model.segment})", flush=True)
        elif self._phase == "contact":
            print(f"  phase: free at t={self.seconds(model.stamp_ns):.2f} s; latest verdict: "
                  f"segment {model.segment}, {model.type}", flush=True)
        self._phase = model.phase

    def print_segments(self, models: KinematicModelList, demo: Demonstration) -> None:
        """Every detected phase beside the true contact intervals (seconds since the start)."""
        print("\ncontact phases (s since the first frame):")
        for m in models.models:
            end = self.seconds(m.segment_end_ns)
            print(f"  detected segment {m.segment}: {self.seconds(m.segment_start_ns):5.2f} - "
                  f"{'open' if math.isnan(end) else f'{end:5.2f}'}  {m.type}")
        for seg in demo.truth.segments:
            print(f"  true     contact {seg.index}: {(seg.onset_ns - self.start_ns) * 1e-9:5.2f} - "
                  f"{(seg.release_ns - self.start_ns) * 1e-9:5.2f}")


def run_demo(object_name: str = "key", participant: int = 3, seed: int = 0, rate: float = 1.0,
             rig: str = "demo", workdir: Path | None = None, robot: bool = True,
             view: bool = False, view_ports: tuple[int, int] = (9090, 9876),
             variant: str = "whole") -> float:
    """Run the whole pipeline on one synthetic demonstration; returns the tangent error (deg).

    ``variant`` as :func:`services.synthetic.generator.generate` ("whole" by default: the stream
    a camera sees, reach and withdrawal included); the contact phases are printed as detected.

    With ``robot``, a robot bridge process on the simulated Panda, holding the true object, is
    asked to articulate it along the estimated model (over the bus, as ``handkse articulate``
    asks), and its result with peak and mean force is printed. With ``view``,
    ``handkse view`` shows the run in Rerun's web viewer (its URL is printed); ``view_ports``
    are the viewer's web and data ports on 127.0.0.1.
    """
    demo = generate(object_name, participant, seed, variant=variant)
    messages = demonstration_recording(demo, rig)
    duration = (demo.stamps_ns[-1] - demo.stamps_ns[0]) * 1e-9
    workdir = workdir or Path(tempfile.mkdtemp(prefix="handkse-demo-"))
    endpoint = free_tcp_endpoint()
    keys = Keys(rig)
    print(f"handkse demo: {object_name} ({variant}), participant {participant}, "
          f"{len(messages)} frames "
          f"({duration:.1f} s at rate {rate:g}); services on {endpoint}; logs in {workdir}")
    options = ZenohOptions(mode="client", connect=(endpoint,), multicast_scouting=False)
    with ProcessGroup(workdir) as group:
        group.start_pipeline(endpoint, rig, SERVICES)
        if robot:  # starts while the demonstration plays; asked once it is estimated
            group.start("robot_bridge", "robot-bridge", *client_args(endpoint, rig),
                        "--sim-object",
                        f"synthetic:{object_name}:{participant}:{seed}:{variant}")
        if view:
            group.start("view", "view", *client_args(endpoint, rig), "--web-port",
                        str(view_ports[0]), "--grpc-port", str(view_ports[1]))
            group.wait_log("view", "web viewer at", 60.0)
            print(next(line for line in group.log("view").splitlines()
                       if line.startswith("web viewer at")), flush=True)
        with Bus(options) as bus:
            wait_for_services(bus, keys, (*SERVICES, "view") if view else SERVICES, 60.0)
            bus.get(keys.reset("kinematics"))  # a fresh demonstration even with an old state file
            bus.get(keys.reset("tracker"))
            latest: list[KinematicModel] = []
            phases = PhasePrinter(demo)

            def on_model(_key: str, payload: bytes) -> None:
                latest.append(KinematicModel.from_msgpack(payload))
                phases.on_model(latest[-1])

            bus.subscribe(keys.hand_landmarks,
                          lambda _k, p: phases.on_landmarks(HandLandmarks.from_msgpack(p)))
            bus.subscribe(keys.kinematics_model, on_model)
            stop = threading.Event()
            player = threading.Thread(target=play, args=(bus, keys, messages,
                                                         PlaybackOptions(rate=rate), stop),
                                      daemon=True)
            t0 = time.monotonic()
            player.start()
            while player.is_alive():
                player.join(0.5)
                if latest:
                    print(_progress_line(latest[-1], demo, time.monotonic() - t0), flush=True)
            _wait_settled(latest)
            final = KinematicModel.from_msgpack(bus.get(keys.kinematics_model)[0][1])
            phases.print_segments(KinematicModelList.from_msgpack(
                bus.get(keys.kinematics_models)[0][1]), demo)
            error = print_comparison(final, demo)
            if robot:
                articulate_on_bridge(group, bus, keys, final, demo)
        if view and sys.stdin.isatty():
            input("\nthe viewer stays open; press Enter to stop it ")
    return error


def articulate_on_bridge(group: ProcessGroup, bus: Bus, keys: Keys, model: KinematicModel,
                         demo: Demonstration) -> int | None:
    """Ask the demo's robot bridge to articulate the demonstrated task along ``model``, as
    ``handkse articulate`` would; print its answer. Returns the command's exit status (None: the
    bridge did not come up; its log is printed)."""
    from services.robot_bridge.client import ArticulateOptions, articulate
    from services.robot_bridge.simulation import object_in_camera, task_amount
    from services.robot_bridge.trajectory import default_duration

    try:
        group.wait_log("robot_bridge", "robot_bridge ready", 120.0)
        wait_for_services(bus, keys, ("robot_bridge",), 30.0)
    except (RuntimeError, TimeoutError, BusError) as exc:
        print(f"\nthe robot bridge did not come up: {' '.join(str(exc).split())[:2000]}")
        return None
    ready = next(line for line in group.log("robot_bridge").splitlines()
                 if line.startswith("robot_bridge ready"))
    # The task comes from the demonstration; the model only supplies the joint. A model that is
    # not a joint gets half a turn, which the bridge refuses with its reason.
    amount = task_amount(model, object_in_camera(demo)) or math.pi
    duration = default_duration(amount, model.type)
    print(f"\n{ready}\n$ handkse articulate --rig {keys.rig} --amount {amount:.4f} "
          f"--duration {duration:.1f}", flush=True)
    try:
        return articulate(bus, keys, ArticulateOptions(amount=amount, duration_s=duration))
    except (UserError, BusError) as exc:
        print(f"handkse articulate: {exc}")
        return 2


def _wait_settled(latest: list[KinematicModel], quiet_s: float = 1.0, timeout: float = 20.0
                  ) -> None:
    """Wait until no new model arrived for ``quiet_s`` (the pipeline drained)."""
    deadline = time.monotonic() + timeout
    count = len(latest)
    quiet_since = time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.1)
        if len(latest) != count:
            count, quiet_since = len(latest), time.monotonic()
        elif time.monotonic() - quiet_since >= quiet_s:
            return


def main(args: argparse.Namespace) -> int:
    run_demo(args.object, args.participant, args.seed, args.rate, args.rig,
             robot=not args.no_robot, view=args.view,
             view_ports=(args.web_port, args.grpc_port), variant=args.variant)
    return 0
