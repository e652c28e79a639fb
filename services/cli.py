"""``handkse`` command line: one subcommand per process or operator action.

One module although it is long: the parser is one table of commands; each command's work lives
in its own package (``add_arguments``/``main`` of the service modules), only the glue is here.

Every subcommand takes the Zenoh options spelled as in Zenoh's examples (``-m -e -l
--no-multicast-scouting -c``) plus ``--rig``, ``--config FILE`` and ``--set section.key=value``.
Heavy modules are imported inside each command, so ``handkse --help`` is fast and optional
extras are needed only by the commands that use them.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import logging
import sys
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from services.common.arguments import (
    non_negative_float,
    non_negative_int,
    object_name,
    participant_id,
    positive_float,
    positive_int,
    rig_name,
    service_name,
    topic_list,
)
from services.common.bus import (
    Bus,
    BusError,
    ZenohOptions,
    add_zenoh_arguments,
    options_from_args,
    wait_for_services,
)
from services.common.config import SECTIONS, ConfigError, section_from_args, to_toml
from services.common.errors import UserError
from services.common.keys import Keys
from services.common.protocol import Ack, KinematicModel, ServiceStats
from services.common.provenance import ask_service
from services.common.recording import McapRecorder, read_recording, write_recording
from services.common.service import stop_on_signals
from services.common.state_file import StateFileError

log = logging.getLogger("handkse")

Command = Callable[[argparse.Namespace], int]


def _common(parser: argparse.ArgumentParser) -> None:
    add_zenoh_arguments(parser)
    parser.add_argument("--rig", default="default", type=rig_name,
                        help="rig name: keys live under handkse/{rig}/ (default: default)")
    parser.add_argument("--config", metavar="FILE", help="handkse TOML config file")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        dest="overrides", help="override one config value (repeatable)")
    parser.add_argument("--log-level", default="INFO",
                        choices=("DEBUG", "INFO", "WARNING", "ERROR"))


def zenoh_options(args: argparse.Namespace) -> ZenohOptions:
    """Zenoh options: command line > environment > ``[zenoh]`` of the config file."""
    base = section_from_args(args, "zenoh")
    assert isinstance(base, ZenohOptions)
    return options_from_args(args, base)


def open_bus(args: argparse.Namespace) -> Bus:
    return Bus(zenoh_options(args))


# --- commands ---


def cmd_router(args: argparse.Namespace) -> int:
    options = zenoh_options(args)
    stop = threading.Event()
    stop_on_signals(stop)
    with Bus(ZenohOptions(**{**options.__dict__, "mode": "router"})) as bus:
        bus.declare_token(Keys(args.rig).alive("router"))  # what `handkse health router` sees
        log.info("router %s listening on %s", bus.zid, list(options.listen) or "defaults")
        print("router ready", flush=True)
        # wait with a timeout: a SIGTERM delivered to one of zenoh's threads sets ``stop`` but
        # does not wake a main thread blocked without one
        while not stop.wait(0.2):
            pass
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    keys = Keys(args.rig)
    stop = threading.Event()
    stop_on_signals(stop)
    key_exprs = args.key or [keys.all]
    with McapRecorder(args.file) as rec, open_bus(args) as bus:
        write = rec.write
        if args.foxglove:
            from services.view.export import foxglove_writer

            write = foxglove_writer(rec)
        for k in key_exprs:
            bus.subscribe(k, write)
        bus.declare_token(keys.alive("recorder"))
        print(f"recording {key_exprs} to {args.file}", flush=True)
        deadline = time.monotonic() + args.duration if args.duration else None
        while not stop.is_set():
            if deadline is not None and time.monotonic() > deadline:
                break
            if args.count and rec.count >= args.count:
                break
            stop.wait(0.02)
    print(f"recorded {rec.count} messages", flush=True)
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from services.common.playback import (
        PlaybackOptions,
        play,
        restamped,
        select_topics,
        target_rig,
        wall_clock_offset,
    )

    if args.remap_rig:
        log.warning("--remap-rig is not needed any more: a recording is published under --rig "
                    "whenever one is given")
    if args.synthetic and args.file:
        raise UserError(f"give a FILE ({args.file}) or --synthetic {args.synthetic}, not both")
    if args.synthetic:
        from services.synthetic.replay import synthetic_recording

        rig, remap = args.rig or "default", None
        source = f"the synthetic {args.synthetic} demonstration"
        try:
            messages = synthetic_recording(args.synthetic, args.participant, args.seed, rig,
                                           variant=args.variant, idle_hand=args.idle_hand,
                                           gap=args.gap, hand=args.hand)
        except ValueError as exc:  # an unsupported combination; the message names it
            raise UserError(f"--synthetic {args.synthetic}: {exc}") from None
    elif args.file:
        if args.save:
            raise UserError("--save works with --synthetic only (FILE is a recording already)")
        source = str(args.file)
        messages = list(read_recording(args.file))
        rig, remap = target_rig(messages, args.rig, source)
    else:
        raise UserError("replay needs a recording FILE or --synthetic OBJECT "
                        "(see handkse replay --help)")
    if not args.all_topics:
        messages = select_topics(messages, args.topics, source)
    if args.save:
        if not args.keep_stamps:
            messages = list(restamped(messages, wall_clock_offset(messages, 1.0, time.time_ns())))
        n = write_recording(args.save, ((m.key, m.payload, m.log_time_ns) for m in messages))
        print(f"saved {n} messages to {args.save}", flush=True)
        return 0
    keys = Keys(rig)
    options = PlaybackOptions(rate=args.rate, loop=args.loop, loop_pause_s=args.loop_pause,
                              keep_stamps=args.keep_stamps, remap_rig=remap,
                              reset=tuple(args.reset or ()),
                              standby_while=tuple(args.standby_while or ()))
    stop = threading.Event()
    stop_on_signals(stop)
    with open_bus(args) as bus:
        bus.declare_token(keys.alive("replay"))
        if args.wait_for:
            wait_for_services(bus, keys, args.wait_for, args.wait_timeout)
        total = play(bus, keys, messages, options, stop)
        time.sleep(0.2)  # let the last BLOCK-mode samples leave before the session closes
    print(f"replayed {total} messages", flush=True)
    return 0


def cmd_health(args: argparse.Namespace) -> int:
    """Exit 0 when every named service's liveliness token is on the bus, 1 when one is not
    within ``--timeout`` (a container health check), 2 when the bus cannot be reached."""
    keys = Keys(args.rig)
    timeout_ms = max(1, int(args.timeout * 1000))
    options = dataclasses.replace(zenoh_options(args), connect_timeout_ms=timeout_ms)
    deadline = time.monotonic() + args.timeout
    with Bus(options) as bus:
        while True:
            alive = set(bus.alive(keys.alive_all, timeout=min(0.5, args.timeout)))
            missing = [s for s in args.service if keys.alive(s) not in alive]
            if not missing or time.monotonic() >= deadline:
                break
            time.sleep(0.1)
    if missing:
        print(f"handkse health: {', '.join(missing)} not alive on rig {keys.rig} after "
              f"{args.timeout:g} s (is it running and connected to the same router?)",
              file=sys.stderr)
        return 1
    print(f"alive: {', '.join(args.service)}", flush=True)
    return 0


def cmd_get(args: argparse.Namespace) -> int:
    """The model as the kinematics service's own session answers it (others are set aside)."""
    keys = Keys(args.rig)
    selector = keys.kinematics_model + ("?format=json" if args.json else "")
    with open_bus(args) as bus:
        answer = ask_service(bus, keys, "kinematics", selector, timeout=args.timeout)
    for reply in answer.untrusted:
        print(f"handkse get: ignored a reply from session {reply.replier}, which does not run "
              "the kinematics service", file=sys.stderr)
    payload = answer.reply.payload
    if args.json:
        print(payload.decode())
    else:
        print(format_model(KinematicModel.from_msgpack(payload)))
    return 0


def format_model(model: object) -> str:
    """Human-readable one-model summary (also used by the demo)."""
    assert isinstance(model, KinematicModel)
    probs = ", ".join(f"{k} {v:.2f}" for k, v in model.probabilities.items())
    lines = [f"type {model.type}  ({probs})  after {model.updates} updates, frame {model.frame_id}"]
    if model.revolute is not None and model.type in ("revolute", "unknown"):
        r = model.revolute
        lines.append(f"  revolute axis {_vec(r.axis)} point {_vec(r.point)} m  q {r.q:.3f} rad")
    if model.prismatic is not None and model.type in ("prismatic", "unknown"):
        p = model.prismatic
        lines.append(f"  prismatic axis {_vec(p.axis)}  q {p.q:.4f} m")
    return "\n".join(lines)


def _vec(v: object) -> str:
    return "[" + ", ".join(f"{x:+.4f}" for x in v) + "]"  # type: ignore[attr-defined]


def cmd_stats(args: argparse.Namespace) -> int:
    keys = Keys(args.rig)
    selector = keys.stats(args.service or "*")
    with open_bus(args) as bus:
        replies = bus.get(selector, timeout=args.timeout)
    for _key, payload in replies:
        print(json.dumps(ServiceStats.from_msgpack(payload).to_json_obj(), indent=2))
    return 0


def cmd_reset(args: argparse.Namespace) -> int:
    keys = Keys(args.rig)
    with open_bus(args) as bus:
        replies = bus.get(keys.reset(args.service), timeout=args.timeout)
    ack = Ack.from_msgpack(replies[0][1])
    print(ack.message)
    return 0 if ack.ok else 1


def cmd_config(args: argparse.Namespace) -> int:
    sections = {name: section_from_args(args, name) for name in SECTIONS}
    print(to_toml(sections))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from services.demo import main as demo_main

    return demo_main(args)


def cmd_eval(args: argparse.Namespace) -> int:
    from services.evaluation.cli import main as eval_main

    return eval_main(args)


def cmd_tune(args: argparse.Namespace) -> int:
    from services.evaluation.tune import main as tune_main

    return tune_main(args)


def cmd_bench(args: argparse.Namespace) -> int:
    from bench.run import run

    run(args.name)
    return 0


def cmd_module(module_name: str) -> Command:
    """A command that runs ``main(args)`` of ``module_name``."""

    def run(args: argparse.Namespace) -> int:
        return int(importlib.import_module(module_name).main(args) or 0)

    return run


# --- parser ---


class HandkseParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line: the option, the rule, where to read more
    (``handkse replay: --participant: must be 1..3, got 99 (see handkse replay --help)``).
    Subcommand parsers are of this class too."""

    def error(self, message: str) -> NoReturn:
        text = " ".join(message.split()).removeprefix("argument ")
        self.exit(2, f"{self.prog}: {text} (see {self.prog} --help)\n")


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; a module command's own arguments are added only when it is the one run
    (``argv``), so listing the commands imports no optional extra."""
    parser = HandkseParser(prog="handkse", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name: str, fn: Command, help_text: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text)
        _common(p)
        p.set_defaults(func=fn)
        return p

    add("router", cmd_router, "run a Zenoh router in this process (tests, small setups)")

    p = add("record", cmd_record, "record bus traffic to an MCAP file")
    p.add_argument("file", type=Path)
    p.add_argument("--key", action="append", metavar="KEYEXPR",
                   help="key expression to record (repeatable; default handkse/{rig}/**)")
    p.add_argument("--duration", type=positive_float, help="stop after this many seconds")
    p.add_argument("--count", type=positive_int, help="stop after this many messages")
    p.add_argument("--foxglove", action="store_true",
                   help="also write channels in Foxglove's schemas (extra 'view'; see export)")

    p = add("replay", cmd_replay, "replay an MCAP recording or a synthetic demonstration "
            "(source topics only, re-stamped to the wall clock)")
    p.set_defaults(rig=None)  # None: a recording keeps the rig it was recorded on
    next(a for a in p._actions if a.dest == "rig").help = (
        "publish under handkse/{rig}/ (default: the recorded rig; 'default' for --synthetic)")
    p.add_argument("file", nargs="?", type=Path, help="an MCAP recording (handkse record)")
    p.add_argument("--rate", type=non_negative_float, default=1.0,
                   help="speed factor; 0 = as fast as possible (default 1)")
    p.add_argument("--loop", action="store_true", help="replay again and again")
    p.add_argument("--loop-pause", type=non_negative_float, default=0.0, metavar="SECONDS",
                   help="with --loop: wait this long between passes (default 0)")
    p.add_argument("--keep-stamps", action="store_true",
                   help="publish the recorded stamp_ns (default: moved onto the wall clock)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--topics", type=topic_list, metavar="TOPIC,...",
                       help="replay these topics (keys below the rig, e.g. hand/landmarks); "
                            "default: the sources camera/rgbd and hand/landmarks")
    which.add_argument("--all-topics", action="store_true",
                       help="replay every recorded topic, results (hand/body, "
                            "kinematics/model) included")
    p.add_argument("--remap-rig", action="store_true", help=argparse.SUPPRESS)  # old; no-op
    p.add_argument("--synthetic", metavar="OBJECT", type=object_name,
                   help="generate a synthetic demonstration of this object (e.g. key)")
    p.add_argument("--participant", type=participant_id, default=3,
                   help="with --synthetic: participant 1..7 (1-3 paper, 4-7 household; default 3)")
    p.add_argument("--seed", type=non_negative_int, default=0)
    from services.synthetic.splits import GAPS, IDLE_HAND_LABELS, VARIANTS

    p.add_argument("--variant", choices=VARIANTS, default="cut",
                   help="with --synthetic: cut (manipulation only, default), whole (reach, grasp, "
                        "manipulate, release, withdraw), sequence (two joints), regrasp (two "
                        "strokes)")
    p.add_argument("--idle-hand", choices=IDLE_HAND_LABELS,
                   help="with --synthetic: an idle second hand in view, labelled like this")
    p.add_argument("--gap", choices=GAPS, help="with --synthetic: a tracking gap of 0.3-1.5 s")
    p.add_argument("--hand", choices=("left", "right"),
                   help="with --synthetic: the manipulating hand (default: the participant's)")
    p.add_argument("--save", type=Path, help="with --synthetic: write the MCAP file and exit")
    p.add_argument("--wait-for", action="append", metavar="SERVICE", type=service_name,
                   help="wait for this service's liveliness token before publishing")
    p.add_argument("--wait-timeout", type=positive_float, default=30.0)
    p.add_argument("--reset", action="append", metavar="SERVICE", type=service_name,
                   help="reset this service before every pass (repeatable)")
    p.add_argument("--standby-while", action="append", metavar="SERVICE", type=service_name,
                   help="publish nothing while this service is alive, e.g. a live camera "
                        "(repeatable)")

    p = add("health", cmd_health, "exit 0 if the services' liveliness tokens are on the bus "
            "(container health checks)")
    p.add_argument("service", nargs="+", type=service_name)
    p.add_argument("--timeout", type=positive_float, default=5.0,
                   help="seconds to reach the router and find the tokens (default 5)")

    p = add("get", cmd_get, "query the current kinematic model")
    p.add_argument("what", choices=("model",))
    p.add_argument("--json", action="store_true", help="print the JSON form")
    p.add_argument("--timeout", type=positive_float, default=2.0)

    p = add("stats", cmd_stats, "print service statistics")
    p.add_argument("service", nargs="?", type=service_name)
    p.add_argument("--timeout", type=positive_float, default=2.0)

    p = add("reset", cmd_reset, "reset a service (start a new demonstration)")
    p.add_argument("service", type=service_name)
    p.add_argument("--timeout", type=positive_float, default=5.0)

    add("config", cmd_config, "print the effective configuration as TOML")

    p = add("demo", cmd_demo, "run every service on loopback on one synthetic demonstration")
    p.add_argument("--object", default="key", type=object_name, help="object preset (default key)")
    p.add_argument("--participant", type=participant_id, default=3)
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--rate", type=non_negative_float, default=1.0,
                   help="replay speed factor (default 1)")
    p.add_argument("--variant", choices=VARIANTS, default="whole",
                   help="the demonstration: whole (reach, grasp, manipulate, release, withdraw; "
                        "default), cut (the manipulation only), sequence (two joints), regrasp "
                        "(two strokes)")
    p.add_argument("--no-robot", action="store_true",
                   help="stop after the estimate (no robot bridge, no articulation)")
    p.add_argument("--view", action="store_true",
                   help="show the run in Rerun's web viewer (handkse view; extra 'view')")
    p.add_argument("--web-port", type=int, default=9090, help="with --view: web viewer port")
    p.add_argument("--grpc-port", type=int, default=9876,
                   help="with --view: port of the viewer's data server")

    p = add("eval", cmd_eval, "evaluate every method on the synthetic demonstrations (Table II)")
    from services.evaluation.cli import add_arguments as add_eval_arguments

    add_eval_arguments(p)

    p = add("tune", cmd_tune, "Bayesian optimisation of the Table I dagger parameters (optuna)")
    from services.evaluation.tune import add_arguments as add_tune_arguments

    add_tune_arguments(p)

    p = add("bench", cmd_bench, "run a benchmark and record it in bench/results/")
    p.add_argument("name", help="protocol, tracker, kinematics or all")

    chosen = _command_in(argv)
    for name, module_name, help_text in MODULE_COMMANDS:
        p = add(name, cmd_module(module_name), help_text)
        if name == chosen:
            module = importlib.import_module(module_name)
            if hasattr(module, "add_arguments"):
                module.add_arguments(p)
    return parser


def _command_in(argv: list[str] | None) -> str | None:
    """The subcommand named in ``argv`` (the first argument that is not an option)."""
    args = sys.argv[1:] if argv is None else argv
    return next((a for a in args if not a.startswith("-")), None)


# Commands whose module has ``main(args)`` and optionally ``add_arguments(parser)``.
MODULE_COMMANDS: list[tuple[str, str, str]] = [
    ("tracker", "services.tracker.service", "run the tracker service (landmarks -> hand body)"),
    ("kinematics", "services.kinematics.service",
     "run the kinematics service (hand body -> kinematic model)"),
    ("camera", "services.detector.camera",
     "publish RGB-D frames (RealSense, Kinect, a recording or a folder)"),
    ("detector", "services.detector.service", "run the detector (RGB-D -> 3-D hand landmarks)"),
    ("models", "services.detector.models", "prepare or show the ONNX hand models"),
    ("robot-bridge", "services.robot_bridge.service",
     "run the robot bridge (MuJoCo simulation or a real Panda)"),
    ("articulate", "services.robot_bridge.client",
     "ask the robot bridge to articulate along the current model (--dry-run: the plan only)"),
    ("robot-trials", "services.evaluation.robot_trials",
     "Table III in simulation: articulate key and window lock along each method's estimates"),
    ("view", "services.view.service",
     "live 3-D view of the bus or of a recording in Rerun (web, native or .rrd; extra 'view')"),
    ("export", "services.view.export",
     "copy an MCAP recording adding channels in Foxglove's schemas (extra 'view')"),
]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        return int(args.func(args))
    except (BusError, ConfigError, StateFileError, UserError) as exc:
        if args.log_level == "DEBUG":
            traceback.print_exc()
        print(f"handkse {args.command}: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
