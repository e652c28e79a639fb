"""``handkse`` command line: one subcommand per process or operator action.

Every subcommand takes the Zenoh options spelled as in Zenoh's examples (``-m -e -l
--no-multicast-scouting -c``) plus ``--rig``, ``--config FILE`` and ``--set section.key=value``.
Heavy modules are imported inside each command, so ``handkse --help`` is fast and optional
extras are needed only by the commands that use them.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from services.common.bus import (
    Bus,
    BusError,
    ZenohOptions,
    add_zenoh_arguments,
    options_from_args,
)
from services.common.config import SECTIONS, ConfigError, section_from_args, to_toml
from services.common.keys import Keys, check_rig
from services.common.protocol import Ack, KinematicModel, ServiceStats
from services.common.recording import McapRecorder, read_recording, replay, write_recording
from services.common.service import stop_on_signals

log = logging.getLogger("handkse")

Command = Callable[[argparse.Namespace], int]


def _common(parser: argparse.ArgumentParser) -> None:
    add_zenoh_arguments(parser)
    parser.add_argument("--rig", default="default", type=check_rig,
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


def wait_for_services(bus: Bus, keys: Keys, services: list[str], timeout: float) -> None:
    """Block until every named service's liveliness token is visible."""
    deadline = time.monotonic() + timeout
    wanted = {keys.alive(s) for s in services}
    while True:
        missing = wanted - set(bus.alive(keys.alive_all, timeout=0.5))
        if not missing:
            return
        if time.monotonic() > deadline:
            raise BusError(f"services not alive after {timeout:.0f} s: {sorted(missing)}")
        time.sleep(0.05)


# --- commands ---


def cmd_router(args: argparse.Namespace) -> int:
    options = zenoh_options(args)
    stop = threading.Event()
    stop_on_signals(stop)
    with Bus(ZenohOptions(**{**options.__dict__, "mode": "router"})) as bus:
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
        for k in key_exprs:
            bus.subscribe(k, rec.write)
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
    stop = threading.Event()
    stop_on_signals(stop)
    if args.synthetic:
        from services.synthetic.replay import synthetic_recording

        messages = synthetic_recording(args.synthetic, args.participant, args.seed, args.rig)
        if args.save:
            n = write_recording(args.save, ((m.key, m.payload, m.log_time_ns) for m in messages))
            print(f"saved {n} messages to {args.save}", flush=True)
            return 0
    elif args.file:
        messages = list(read_recording(args.file))
    else:
        raise SystemExit("replay needs FILE or --synthetic OBJECT")
    keys = Keys(args.rig)
    with open_bus(args) as bus:
        if args.wait_for:
            wait_for_services(bus, keys, args.wait_for, args.wait_timeout)
        total = 0
        while True:
            total += replay(messages, lambda k, p: bus.put(k, p, frame=k.endswith("/camera/rgbd")),
                            rate=args.rate, rig=args.rig if args.remap_rig else None, stop=stop)
            if not args.loop or stop.is_set():
                break
        time.sleep(0.2)  # let the last BLOCK-mode samples leave before the session closes
    print(f"replayed {total} messages", flush=True)
    return 0


def cmd_get(args: argparse.Namespace) -> int:
    keys = Keys(args.rig)
    selector = keys.kinematics_model + ("?format=json" if args.json else "")
    with open_bus(args) as bus:
        replies = bus.get(selector, timeout=args.timeout)
    payload = replies[0][1]
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


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; a module command's own arguments are added only when it is the one run
    (``argv``), so listing the commands imports no optional extra."""
    parser = argparse.ArgumentParser(prog="handkse", description=__doc__.splitlines()[0])
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
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--count", type=int, help="stop after this many messages")

    p = add("replay", cmd_replay, "replay an MCAP recording or a synthetic demonstration")
    p.add_argument("file", nargs="?", type=Path)
    p.add_argument("--rate", type=float, default=1.0,
                   help="speed factor; 0 = as fast as possible (default 1)")
    p.add_argument("--loop", action="store_true", help="replay again and again")
    p.add_argument("--remap-rig", action="store_true",
                   help="publish under --rig instead of the recorded rig")
    p.add_argument("--synthetic", metavar="OBJECT", help="generate a synthetic demonstration")
    p.add_argument("--participant", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save", type=Path, help="with --synthetic: write the MCAP file and exit")
    p.add_argument("--wait-for", action="append", metavar="SERVICE",
                   help="wait for this service's liveliness token before publishing")
    p.add_argument("--wait-timeout", type=float, default=30.0)

    p = add("get", cmd_get, "query the current kinematic model")
    p.add_argument("what", choices=("model",))
    p.add_argument("--json", action="store_true", help="print the JSON form")
    p.add_argument("--timeout", type=float, default=2.0)

    p = add("stats", cmd_stats, "print service statistics")
    p.add_argument("service", nargs="?")
    p.add_argument("--timeout", type=float, default=2.0)

    p = add("reset", cmd_reset, "reset a service (start a new demonstration)")
    p.add_argument("service")
    p.add_argument("--timeout", type=float, default=5.0)

    add("config", cmd_config, "print the effective configuration as TOML")

    p = add("demo", cmd_demo, "run every service on loopback on one synthetic demonstration")
    p.add_argument("--object", default="key", help="object preset (default key)")
    p.add_argument("--participant", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rate", type=float, default=1.0, help="replay speed factor (default 1)")
    p.add_argument("--no-robot", action="store_true",
                   help="stop after the estimate (skip the simulated articulation)")

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
    ("robot-trials", "services.robot_bridge.trials",
     "Table III in simulation: articulate key and window lock along each method's estimates"),
]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        return int(args.func(args))
    except (BusError, ConfigError) as exc:
        print(f"handkse {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
