"""``handkse articulate``: ask the robot bridge to articulate, as an operator does.

Sends one ``ArticulateRequest`` to ``handkse/{rig}/robot/articulate`` and prints the
``ArticulateResult`` as one block of text (``--json``: one JSON document). ``--dry-run`` asks
for the plan only: joint type, axis and point (robot base frame), amount, duration, peak speeds
and the limits it would run under, or the refusal that would stop it. Exit status: 0 for a
successful articulation or an accepted dry run, 1 for a refusal or a failed articulation (the
reason and its explanation printed), 2 for a usage or bus error (one line, from the ``handkse``
command).

Defaults, when not given: the amount is 180 deg (the paper's task) in the direction of the
model's joint value ``q`` for a revolute joint, and ``q`` itself (the demonstrated stroke) for a
prismatic one; the duration is the paper's pace (6 s per 180 deg, 2 cm/s); for either, the model
is read as ``handkse get model`` reads it (or from ``--model-file``). ``handkse demo`` sends its
request through :func:`articulate` too.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from services.common.arguments import positive_float
from services.common.bus import Bus, BusError, NoResponder, QueryTimeout, options_from_args
from services.common.config import section_from_args
from services.common.errors import UserError
from services.common.keys import Keys
from services.common.protocol import (
    ArticulateRequest,
    ArticulateResult,
    KinematicModel,
    ProtocolError,
)
from services.common.provenance import ask_service
from services.robot_bridge.trajectory import amount_text, default_duration

# Below these the model's joint value says nothing about a direction or a stroke.
MIN_DEFAULT_TURN_RAD = math.radians(5.0)
MIN_DEFAULT_STROKE_M = 0.005
DEFAULT_FORCE_LIMIT_N = 70.0
# The caller's default wait: the motion at a third of real time (a loaded simulation), then
# the hold, settling and reply.
TIMEOUT_SLOWNESS = 3.0
TIMEOUT_MARGIN_S = 10.0


@dataclass(frozen=True)
class ArticulateOptions:
    """What to ask for; None: the default (module docstring).

    ``amount`` rad or m, signed about / along the model's axis; ``duration_s`` of the motion;
    ``force_limit_n`` (the bridge caps it at its own limit); ``timeout_s`` how long to wait for
    the result (default ``3 duration + 10 s``); ``model`` sent in the request (None: the bridge
    asks the kinematics service).
    """

    amount: float | None = None
    duration_s: float | None = None
    force_limit_n: float = DEFAULT_FORCE_LIMIT_N
    dry_run: bool = False
    timeout_s: float | None = None
    model: KinematicModel | None = None


def default_amount(model: KinematicModel) -> float:
    """180 deg in the direction of a revolute model's ``q``, or a prismatic model's ``q``.

    Raises :class:`UserError` when the model has no joint or too small a ``q`` to tell.
    """
    if model.type == "revolute" and model.revolute is not None:
        q = float(model.revolute.q)
        if abs(q) < MIN_DEFAULT_TURN_RAD:
            raise UserError(f"the model's joint value is {math.degrees(q):.1f} deg, too small to "
                            "tell which way the demonstration turned: give --amount (rad)")
        return math.copysign(math.pi, q)
    if model.type == "prismatic" and model.prismatic is not None:
        q = float(model.prismatic.q)
        if abs(q) < MIN_DEFAULT_STROKE_M:
            raise UserError(f"the model's joint value is {q * 1e3:.1f} mm, too small for a "
                            "stroke: give --amount (m)")
        return q
    raise UserError(f"the model is {model.type}, not a joint to articulate; demonstrate again, "
                    "or give --amount and --duration to see what the bridge says")


def request_for(options: ArticulateOptions, model: Callable[[], KinematicModel]
                ) -> ArticulateRequest:
    """The request, stamped now; ``model()`` is called only for a default amount or
    duration."""
    amount, duration = options.amount, options.duration_s
    if amount is None or duration is None:
        current = model()
        amount = default_amount(current) if amount is None else amount
        if duration is None:
            duration = default_duration(amount, current.type)
    timeout = options.timeout_s
    if timeout is None:
        timeout = TIMEOUT_SLOWNESS * duration + TIMEOUT_MARGIN_S
    return ArticulateRequest(stamp_ns=time.time_ns(), amount=float(amount),
                             duration_s=float(duration), force_limit_n=options.force_limit_n,
                             model=options.model, dry_run=options.dry_run, timeout_s=timeout)


def send(bus: Bus, keys: Keys, request: ArticulateRequest) -> ArticulateResult:
    """Send ``request`` and wait up to its ``timeout_s`` (plus a second) for the result.

    Raises :class:`UserError` when no robot bridge answers, :class:`BusError` for an error
    reply, :class:`ProtocolError` for a reply that is not a result.
    """
    wait = (request.timeout_s or 10.0) + 1.0
    try:
        replies = bus.get(keys.robot_articulate, payload=request.to_msgpack(), timeout=wait)
    except NoResponder:
        raise UserError(f"no robot bridge answers on {keys.robot_articulate}: is handkse "
                        f"robot-bridge running on rig {keys.rig} and connected to the same "
                        "router?") from None
    except QueryTimeout:
        raise UserError(f"the robot bridge on rig {keys.rig} did not answer within {wait:.0f} s "
                        "(see its log; a longer --timeout waits longer)") from None
    return ArticulateResult.from_msgpack(replies[0][1])


def service_model(bus: Bus, keys: Keys, timeout_s: float = 2.0) -> KinematicModel:
    """The kinematics service's model, as ``handkse get model`` reads it."""
    try:
        answer = ask_service(bus, keys, "kinematics", keys.kinematics_model, timeout=timeout_s)
    except BusError as exc:
        raise UserError(f"cannot read the model for the default amount or duration ({exc}); "
                        "give --amount and --duration") from None
    return KinematicModel.from_msgpack(answer.reply.payload)


def load_model(path: Path) -> KinematicModel:
    """A ``KinematicModel`` from a JSON file (``handkse get model --json``) or a msgpack one."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise UserError(f"--model-file {path} does not exist") from None
    except OSError as exc:
        raise UserError(f"--model-file {path} cannot be read: {exc.strerror}") from None
    try:
        if data.lstrip()[:1] == b"{":
            return KinematicModel.from_json_obj(json.loads(data))
        return KinematicModel.from_msgpack(data)
    except (ValueError, ProtocolError) as exc:  # json.JSONDecodeError is a ValueError
        raise UserError(f"--model-file {path} is not a KinematicModel (JSON from handkse get "
                        f"model --json, or msgpack): {' '.join(str(exc).split())}") from None


def outcome(result: ArticulateResult, dry_run: bool) -> str:
    """``OK`` / ``SUCCESS``, ``REFUSED`` (nothing moved) or ``FAILED`` (stopped on the way)."""
    if result.success:
        return "OK" if dry_run else "SUCCESS"
    moved = result.duration_s > 0.0 or result.articulated != 0.0
    return "FAILED" if moved else "REFUSED"


def format_result(result: ArticulateResult, request: ArticulateRequest | None = None) -> str:
    """The result as one block of text for an operator."""
    dry = request.dry_run if request is not None else result.reason == "dry_run"
    head = "articulate (dry run)" if dry else "articulate"
    lines = [f"{head}: {outcome(result, dry)} ({result.reason})"]

    def row(name: str, text: str) -> None:
        lines.append(f"  {name:<10} {text}")

    if result.detail:
        row("detail", result.detail)
    plan = result.plan
    if not dry and plan is not None and outcome(result, dry) != "REFUSED":
        kind = plan.joint_type
        row("reached", f"{amount_text(result.articulated, kind)} of "
                       f"{amount_text(plan.amount, kind)}")
        row("force", f"peak {result.peak_force_n:.1f} N, mean {result.mean_force_n:.1f} N")
        row("duration", f"{result.duration_s:.1f} s")
    if result.stamp_ns > 0:
        age = (time.time_ns() - result.stamp_ns) * 1e-9
        row("model", f"stamped {age:.1f} s ago, frame {result.frame_id}")
    if plan is not None:
        where = "through" if plan.joint_type == "revolute" else "from"
        row("joint", f"{plan.joint_type}, axis {_vec(plan.axis)} {where} {_vec(plan.point)} m "
                     "(robot base frame)")
        row("motion", f"{amount_text(plan.amount, plan.joint_type)} in {plan.duration_s:.1f} s, "
                      f"then {plan.hold_s:.1f} s hold; peak speed "
                      f"{plan.peak_linear_speed_m_per_s:.3f} m/s, "
                      f"{plan.peak_angular_speed_rad_per_s:.2f} rad/s")
        row("limits", f"force {plan.force_limit_n:.1f} N, wrist torque "
                      f"{plan.wrist_torque_limit_nm:.1f} N m, speed "
                      f"{plan.max_linear_speed_m_per_s:.2f} m/s and "
                      f"{plan.max_angular_speed_rad_per_s:.2f} rad/s")
    elif request is not None:
        row("asked", f"{request.amount:+.4f} (rad or m) in {request.duration_s:.1f} s, force "
                     f"limit {request.force_limit_n:.1f} N")
    return "\n".join(lines)


def _vec(v: object) -> str:
    return "[" + ", ".join(f"{x:+.3f}" for x in v) + "]"  # type: ignore[attr-defined]


def articulate(bus: Bus, keys: Keys, options: ArticulateOptions, *, as_json: bool = False,
               out: Callable[[str], None] = print) -> int:
    """Ask, print the answer (text or JSON), return the exit status (0 success / dry run
    accepted, 1 refused or failed). Usage and bus errors raise :class:`UserError` /
    :class:`BusError`."""
    request = request_for(options, lambda: options.model or service_model(bus, keys))
    result = send(bus, keys, request)
    if as_json:
        out(json.dumps({"request": request.to_json_obj(), "result": result.to_json_obj()},
                       indent=2))
    else:
        out(format_result(result, request))
    return 0 if result.success else 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``handkse articulate`` (the CLI adds --rig/--config/--set/zenoh)."""
    p.add_argument("--amount", type=_nonzero_float, metavar="X",
                   help="rad (revolute) or m (prismatic), signed about / along the model's "
                        "axis (default: 180 deg the way the model's q points; prismatic: q)")
    p.add_argument("--duration", type=positive_float, metavar="S",
                   help="seconds for the motion (default: 6 s per 180 deg, 2 cm/s)")
    p.add_argument("--force-limit", type=positive_float, default=DEFAULT_FORCE_LIMIT_N,
                   metavar="N", help="abort above this wrist force; the bridge caps it at "
                                     "robot_bridge.force_limit_n (default 70)")
    p.add_argument("--dry-run", action="store_true",
                   help="plan and check only: print the plan, or what would refuse it")
    p.add_argument("--timeout", type=positive_float, metavar="S",
                   help="seconds to wait for the result (default: 3 x duration + 10)")
    p.add_argument("--model-file", type=Path, metavar="FILE",
                   help="send this KinematicModel (JSON from handkse get model --json, or "
                        "msgpack) instead of the kinematics service's")
    p.add_argument("--json", action="store_true", help="print request and result as JSON")


def _nonzero_float(text: str) -> float:
    """An argparse type: a finite, non-zero number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value == 0.0:
        raise argparse.ArgumentTypeError(f"must be a finite, non-zero number, got {text}")
    return value


def main(args: argparse.Namespace) -> int:
    """``handkse articulate``: options from the command line, one request, the answer printed."""
    options = ArticulateOptions(
        amount=args.amount, duration_s=args.duration, force_limit_n=args.force_limit,
        dry_run=args.dry_run, timeout_s=args.timeout,
        model=None if args.model_file is None else load_model(args.model_file))
    with Bus(options_from_args(args, section_from_args(args, "zenoh"))) as bus:
        return articulate(bus, Keys(args.rig), options, as_json=args.json)
