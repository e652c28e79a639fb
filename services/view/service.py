"""``handkse view [FILE.mcap]``: a live 3-D view of the bus, or of a recording, in Rerun.

Live, it is one more subscriber (FIFO for landmarks, bodies, models and robot states; the newest
camera frame only, so images never hold up the rest) and declares the liveliness token
``handkse/{rig}/alive/view``. With ``FILE.mcap`` it logs the whole recording at once; Rerun's own
time controls then play it back.

Where the view goes:

- default (or ``--web-port PORT``): Rerun's web viewer and its data server, both run by the
  ``rerun`` program of the rerun-sdk wheel as a child process bound to 127.0.0.1 only; the URL is
  printed (``web viewer at http://127.0.0.1:PORT/?url=...``);
- ``--native``: the native Rerun viewer is spawned;
- ``--save FILE.rrd``: written to a file (alone, or beside a viewer).

Prints ``view: logged N messages`` once a second while the count changes, and the counts by kind
and the rejected payloads at the end.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import queue
import socket
import subprocess
import sys
import threading
import time
import urllib.parse
from pathlib import Path
from typing import Any

from services.common.bus import Bus, options_from_args
from services.common.config import section_from_args
from services.common.keys import Keys
from services.common.recording import read_recording
from services.common.service import stop_on_signals

log = logging.getLogger("handkse.view")

DEFAULT_WEB_PORT = 9090
DEFAULT_GRPC_PORT = 9876
_LOOPBACK = "127.0.0.1"
_EXTRA_HINT = "handkse view needs the 'view' extra: pip install 'handkse[view]' (rerun-sdk)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", nargs="?", type=Path, help="show this MCAP recording instead of the bus")
    parser.add_argument("--web-port", type=int, metavar="PORT",
                        help=f"serve the web viewer on 127.0.0.1:PORT (default {DEFAULT_WEB_PORT}; "
                             "the default view unless --native or --save alone is given)")
    parser.add_argument("--grpc-port", type=int, default=DEFAULT_GRPC_PORT, metavar="PORT",
                        help="port of the viewer's data server on 127.0.0.1 "
                             f"(default {DEFAULT_GRPC_PORT})")
    parser.add_argument("--native", action="store_true", help="spawn the native Rerun viewer")
    parser.add_argument("--save", type=Path, metavar="FILE.rrd", help="write the view to an .rrd file")
    parser.add_argument("--no-images", action="store_true",
                        help="leave camera images out (they dominate a recording's size)")
    parser.add_argument("--trail", type=int, default=300, help="hand body poses in the trail")
    parser.add_argument("--sigma", type=float, default=2.0,
                        help="uncertainties are drawn at this many standard deviations (default 2)")
    parser.add_argument("--force-limit-n", type=float, default=70.0,
                        help="force limit drawn beside the measured force (default 70 N)")
    parser.add_argument("--duration", type=float, help="live: stop after this many seconds")


def viewer_url(web_port: int, grpc_port: int) -> str:
    """The web viewer's address with its data server as the source to open."""
    source = f"rerun+http://{_LOOPBACK}:{grpc_port}/proxy"
    return f"http://{_LOOPBACK}:{web_port}/?url={urllib.parse.quote(source, safe='')}"


def _wait_port(port: int, proc: subprocess.Popen[bytes], timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"handkse view: the rerun web viewer exited with {proc.returncode}")
        try:
            with socket.create_connection((_LOOPBACK, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise SystemExit(f"handkse view: the rerun web viewer did not listen on port {port} "
                     f"within {timeout:.0f} s")


def rerun_program() -> str:
    """The ``rerun`` program of the rerun-sdk wheel (``RERUN_CLI_PATH`` overrides it), run
    directly: its Python launcher would leave the program running when the launcher is ended."""
    if os.environ.get("RERUN_CLI_PATH"):
        return os.environ["RERUN_CLI_PATH"]
    spec = importlib.util.find_spec("rerun_cli")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit(f"{_EXTRA_HINT} (no rerun_cli package)")
    return str(Path(next(iter(spec.submodule_search_locations))) / "rerun")


# Starts a program that gets SIGTERM when its parent dies, even by SIGKILL (Linux prctl
# PR_SET_PDEATHSIG, kept across exec), so that no viewer is left holding its ports. A launcher
# process rather than ``preexec_fn``, which is unsafe in this multi-threaded process.
_LAUNCH_TIED_TO_PARENT = """
import ctypes, os, signal, sys
ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
if os.getppid() != int(sys.argv[1]):
    sys.exit(1)
os.execv(sys.argv[2], sys.argv[2:])
"""


def tied_to_this_process(cmd: list[str]) -> list[str]:
    """``cmd`` run so that it ends when this process ends (on Linux; unchanged elsewhere)."""
    if not sys.platform.startswith("linux"):
        return cmd
    return [sys.executable, "-c", _LAUNCH_TIED_TO_PARENT, str(os.getpid()), *cmd]


def _check_free(port: int, option: str) -> None:
    with socket.socket() as s:
        try:
            s.bind((_LOOPBACK, port))
        except OSError as exc:
            raise SystemExit(f"handkse view: port {port} on {_LOOPBACK} is taken ({exc.strerror}); "
                             f"choose another with {option}") from exc


def start_web_viewer(web_port: int, grpc_port: int) -> subprocess.Popen[bytes]:
    """Run ``rerun --serve-web`` bound to loopback: the web viewer on ``web_port`` and the data
    server (which buffers everything for late viewers) on ``grpc_port``."""
    _check_free(web_port, "--web-port")
    _check_free(grpc_port, "--grpc-port")
    cmd = [rerun_program(), "--serve-web", "--bind", _LOOPBACK, "--port", str(grpc_port),
           "--web-viewer-port", str(web_port)]
    proc = subprocess.Popen(tied_to_this_process(cmd), stdin=subprocess.DEVNULL)
    _wait_port(grpc_port, proc)
    _wait_port(web_port, proc)
    return proc


class View:
    """A Rerun recording with its sinks and the scene that fills it; ``close()`` flushes."""

    def __init__(self, args: argparse.Namespace) -> None:
        try:
            import rerun as rr

            from services.view.rerun_scene import RerunScene, SceneOptions, blueprint
        except ImportError as exc:
            raise SystemExit(f"{_EXTRA_HINT} ({exc})") from exc
        self.viewer: subprocess.Popen[bytes] | None = None
        web = not args.native and (args.web_port is not None or args.save is None)
        if web:
            web_port = args.web_port or DEFAULT_WEB_PORT
            self.viewer = start_web_viewer(web_port, args.grpc_port)
        self.rec = rr.RecordingStream("handkse")
        sinks: list[Any] = []
        if args.native:
            self.rec.spawn(port=args.grpc_port, connect=False)
            sinks.append(rr.GrpcSink(f"rerun+http://{_LOOPBACK}:{args.grpc_port}/proxy"))
        elif web:
            sinks.append(rr.GrpcSink(f"rerun+http://{_LOOPBACK}:{args.grpc_port}/proxy"))
            print(f"web viewer at {viewer_url(web_port, args.grpc_port)}", flush=True)
        if args.save is not None:
            sinks.append(rr.FileSink(str(args.save)))
        self.rec.set_sinks(*sinks, default_blueprint=blueprint())
        self.scene = RerunScene(self.rec, SceneOptions(
            trail_length=args.trail, n_sigma=args.sigma, force_limit_n=args.force_limit_n,
            images=not args.no_images))

    def close(self) -> None:
        self.rec.flush(timeout_sec=10.0)
        self.rec.disconnect()

    def stop_viewer(self) -> None:
        if self.viewer is not None and self.viewer.poll() is None:
            self.viewer.terminate()
            try:
                self.viewer.wait(5)
            except subprocess.TimeoutExpired:
                self.viewer.kill()
                self.viewer.wait(5)


def show_recording(view: View, path: Path) -> None:
    for message in read_recording(path):
        view.scene.handle(message.key, message.payload)


def show_live(view: View, bus: Bus, keys: Keys, stop: threading.Event,
              duration: float | None) -> None:
    """Subscribe and log until ``stop`` (or ``duration``); logging happens on this thread only."""
    inbox: queue.Queue[tuple[str, bytes]] = queue.Queue()
    for key in (keys.hand_landmarks, keys.hand_body, keys.kinematics_model, f"{keys.root}/robot/**"):
        bus.subscribe(key, lambda k, p: inbox.put((k, p)))
    frames = bus.subscribe_latest(keys.camera_rgbd)
    bus.declare_token(keys.alive("view"))
    print(f"view: subscribed to {keys.root}", flush=True)
    deadline = None if duration is None else time.monotonic() + duration
    reported, next_report = -1, time.monotonic()
    while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
        try:
            key, payload = inbox.get(timeout=0.05)
            view.scene.handle(key, payload)
        except queue.Empty:
            pass
        frame = frames.take(timeout=0)
        if frame is not None:
            view.scene.handle(*frame)
        total = view.scene.counters.total
        if time.monotonic() >= next_report and total != reported:
            print(f"view: logged {total} messages", flush=True)
            reported, next_report = total, time.monotonic() + 1.0
    frames.close()
    while True:  # what arrived before the stop is still shown
        try:
            view.scene.handle(*inbox.get_nowait())
        except queue.Empty:
            break


def main(args: argparse.Namespace) -> int:
    stop = threading.Event()
    stop_on_signals(stop)
    view = View(args)
    try:
        if args.file is not None:
            show_recording(view, args.file)
            print(f"view: logged {view.scene.counters.total} messages from {args.file}", flush=True)
            if view.viewer is not None or args.native:
                print("view: showing the recording; Ctrl-C to quit", flush=True)
                while not stop.wait(0.2):
                    pass
        else:
            with Bus(options_from_args(args, section_from_args(args, "zenoh"))) as bus:
                show_live(view, bus, Keys(args.rig), stop, args.duration)
    finally:
        view.close()
        view.stop_viewer()
    counters = view.scene.counters
    print(f"view: logged {counters.total} messages {dict(sorted(counters.logged.items()))}; "
          f"rejected {counters.rejected}", flush=True)
    return 0
