"""Record bus traffic to MCAP files and replay it with its original timing.

File layout: one MCAP channel per key expression, message encoding ``msgpack``, one schema per
message type named by the payload's ``schema`` string (``handkse.HandLandmarks/1``; schema
encoding ``handkse``, data pointing at the protocol page). Log time = receive time (ns, wall
clock), publish time = the message's ``stamp_ns``. MCAP tools list these channels, but none can
decode msgpack with a ``handkse`` schema: ``handkse export`` (or ``handkse record --foxglove``)
adds channels in Foxglove's own protobuf schemas beside them (:meth:`McapRecorder.write_encoded`,
:mod:`services.view.foxglove_scene`).

Replay publishes every message on its key (optionally remapped to another rig) at the
original pace, at ``rate`` times that pace, or as fast as possible (``rate=0``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.reader import make_reader
from mcap.writer import Writer

from services.common.keys import remap_rig
from services.common.protocol import peek_envelope

SCHEMA_ENCODING = "handkse"
MESSAGE_ENCODING = "msgpack"
PROFILE = "handkse"
_SCHEMA_DATA = b"handkse wire protocol v1: msgpack map, see docs/protocol.md"


@dataclass(frozen=True)
class EncodedSchema:
    """A channel's schema for :meth:`McapRecorder.write_encoded`: ``name``, schema ``encoding``
    (``protobuf``: ``data`` is a serialized FileDescriptorSet) and ``message_encoding``."""

    name: str
    encoding: str
    data: bytes
    message_encoding: str


@dataclass(frozen=True)
class RecordedMessage:
    key: str
    payload: bytes
    log_time_ns: int
    publish_time_ns: int
    schema: str


class McapRecorder:
    """Append messages to an MCAP file; thread-safe (bus callbacks arrive on several threads)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file)
        self._writer.start(profile=PROFILE, library="handkse")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self._lock = threading.Lock()
        self.count = 0  # handkse payloads (``write``)
        self.encoded_count = 0  # other messages (``write_encoded``)
        self._closed = False

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write(self, key: str, payload: bytes, log_time_ns: int | None = None) -> None:
        """Record one payload on ``key``; log time defaults to now."""
        log_time = time.time_ns() if log_time_ns is None else log_time_ns
        schema, stamp = peek_envelope(payload)
        schema = schema or "unknown"
        if stamp is None or not 0 <= stamp < 2**64:
            # MCAP times are uint64: a stamp outside that range (bad input) must not reach the
            # writer, which would fail half-way through the record and corrupt the chunk
            stamp = log_time
        with self._lock:
            if self._closed:
                return
            if schema not in self._schemas:
                self._schemas[schema] = self._writer.register_schema(
                    name=schema, encoding=SCHEMA_ENCODING, data=_SCHEMA_DATA)
            if key not in self._channels:
                self._channels[key] = self._writer.register_channel(
                    topic=key, message_encoding=MESSAGE_ENCODING,
                    schema_id=self._schemas[schema])
            seq = self._sequence.get(key, 0)
            self._sequence[key] = seq + 1
            self._writer.add_message(channel_id=self._channels[key], log_time=log_time,
                                     data=payload, publish_time=stamp, sequence=seq)
            self.count += 1

    def write_encoded(self, topic: str, schema: EncodedSchema, data: bytes, *, log_time_ns: int,
                      publish_time_ns: int) -> None:
        """Record one message that is not a handkse payload (e.g. a Foxglove protobuf message) on
        its own channel ``topic``, with its own schema; times in ns, clamped to MCAP's range."""
        publish = publish_time_ns if 0 <= publish_time_ns < 2**64 else log_time_ns
        with self._lock:
            if self._closed:
                return
            schema_key = f"{schema.encoding}:{schema.name}"
            if schema_key not in self._schemas:
                self._schemas[schema_key] = self._writer.register_schema(
                    name=schema.name, encoding=schema.encoding, data=schema.data)
            if topic not in self._channels:
                self._channels[topic] = self._writer.register_channel(
                    topic=topic, message_encoding=schema.message_encoding,
                    schema_id=self._schemas[schema_key])
            seq = self._sequence.get(topic, 0)
            self._sequence[topic] = seq + 1
            self._writer.add_message(channel_id=self._channels[topic], log_time=log_time_ns,
                                     data=data, publish_time=publish, sequence=seq)
            self.encoded_count += 1

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._writer.finish()
            self._file.close()


def read_recording(path: str | Path) -> Iterator[RecordedMessage]:
    """The handkse messages (msgpack channels) of an MCAP file in log-time order; channels in
    other encodings (the Foxglove channels of an exported file) are skipped."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            if channel.message_encoding != MESSAGE_ENCODING:
                continue
            yield RecordedMessage(key=channel.topic, payload=message.data,
                                  log_time_ns=message.log_time,
                                  publish_time_ns=message.publish_time,
                                  schema=schema.name if schema is not None else "")


def write_recording(path: str | Path, messages: Iterable[tuple[str, bytes, int]]) -> int:
    """Write ``(key, payload, log_time_ns)`` tuples to a new MCAP file; returns the count."""
    with McapRecorder(path) as rec:
        for key, payload, log_time in messages:
            rec.write(key, payload, log_time)
        return rec.count


_SPIN_S = 0.0005  # replay spins this long before each message, sleeps before that


def replay(messages: Iterable[RecordedMessage], publish: Callable[[str, bytes], None], *,
           rate: float = 1.0, rig: str | None = None, stop: threading.Event | None = None
           ) -> int:
    """Publish recorded messages with their original spacing scaled by ``1/rate``.

    ``rate=0`` publishes as fast as possible. ``rig`` remaps ``handkse/{rig}/...`` keys.
    Returns the number of messages published. Sleeps, then spins the last 0.5 ms (Linux sleeps
    overshoot by ~0.1 ms on an idle machine), so the spacing error stays well under a
    millisecond without a publisher at 150 Hz spinning a fifth of a core.
    """
    if rate < 0:
        raise ValueError(f"replay rate must be >= 0, got {rate}")
    count = 0
    t0_wall: float | None = None
    t0_log = 0
    for msg in messages:
        if stop is not None and stop.is_set():
            break
        if t0_wall is None:
            t0_wall, t0_log = time.perf_counter(), msg.log_time_ns
        elif rate > 0:
            target = t0_wall + (msg.log_time_ns - t0_log) * 1e-9 / rate
            while (remaining := target - time.perf_counter()) > 0:
                if stop is not None and stop.is_set():
                    return count
                if remaining > _SPIN_S:
                    time.sleep(min(remaining - _SPIN_S, 0.1))
        publish(remap_rig(msg.key, rig) if rig else msg.key, msg.payload)
        count += 1
    return count
