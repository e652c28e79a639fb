"""``handkse export IN.mcap OUT.mcap``: a copy of a recording that Foxglove can show.

OUT keeps every raw msgpack channel of IN unchanged (``handkse replay`` and ``handkse view`` read
it like IN) and adds the channels of :mod:`services.view.foxglove_scene` in Foxglove's own
protobuf schemas.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

from services.common.recording import McapRecorder, read_recording

_EXTRA_HINT = "handkse export needs the 'view' extra: pip install 'handkse[view]' (foxglove-sdk)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", type=Path, help="an MCAP recording (handkse record)")
    parser.add_argument("output", type=Path, help="the MCAP file to write")
    parser.add_argument("--trail", type=int, default=300, help="hand body poses in the trail")
    parser.add_argument("--sigma", type=float, default=2.0,
                        help="uncertainties are drawn at this many standard deviations (default 2)")


def export(input_path: Path, output_path: Path, trail_length: int = 300,
           n_sigma: float = 2.0) -> tuple[int, int, dict[str, int]]:
    """Copy ``input_path`` to ``output_path`` with Foxglove channels added; returns the number
    of raw messages, of Foxglove messages, and the payloads that did not decode by reason."""
    try:
        from services.view.foxglove_scene import FoxgloveChannels
    except ImportError as exc:
        raise SystemExit(f"{_EXTRA_HINT} ({exc})") from exc
    if input_path.resolve() == output_path.resolve():
        raise SystemExit("handkse export: OUT must be another file than IN")
    channels = FoxgloveChannels(trail_length=trail_length, n_sigma=n_sigma)
    with McapRecorder(output_path) as recorder:
        for message in read_recording(input_path):
            recorder.write(message.key, message.payload, message.log_time_ns)
            channels.write(recorder, message.key, message.payload, message.log_time_ns)
        return recorder.count, recorder.encoded_count, dict(channels.rejected)


def foxglove_writer(recorder: McapRecorder) -> Callable[[str, bytes], None]:
    """A bus callback for ``handkse record --foxglove``: each payload is recorded raw, then as
    Foxglove messages, with the same receive time."""
    try:
        from services.view.foxglove_scene import FoxgloveChannels
    except ImportError as exc:
        raise SystemExit(f"{_EXTRA_HINT} ({exc})") from exc
    channels = FoxgloveChannels()

    def write(key: str, payload: bytes) -> None:
        log_time = time.time_ns()
        recorder.write(key, payload, log_time)
        channels.write(recorder, key, payload, log_time)

    return write


def main(args: argparse.Namespace) -> int:
    raw, added, rejected = export(args.input, args.output, args.trail, args.sigma)
    print(f"exported {raw} messages and {added} Foxglove messages to {args.output}"
          + (f"; payloads that did not decode: {rejected}" if rejected else ""), flush=True)
    return 0
