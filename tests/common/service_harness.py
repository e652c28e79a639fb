"""A :class:`Service` on the fake bus, driven from a test deterministically and without sleeps.

With the fake bus a ``put`` lands in the service's inbox at once; :func:`drain` then handles
everything queued so far in the test's thread. A control
query (``reset``) waits on a bus thread for the loop, so it needs the loop running meanwhile
(:func:`serving`). :class:`ServiceHarness` bundles the two with the wire-level reads a node test
makes: what the node published, its ``stats``, a ``reset``.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TypeVar

from services.common.keys import Keys
from services.common.protocol import Ack, Message, ServiceStats
from services.common.service import Service
from tests.common.fake_bus import FakeBus

M = TypeVar("M", bound=Message)


def drain(service: Service) -> None:
    """Handle every event queued so far, in this thread; then return."""
    service.handle_pending()


@contextmanager
def serving(service: Service, timeout: float = 30.0) -> Iterator[None]:
    """Run the service loop on a thread for the body of the ``with``, then stop and join it."""
    stop = threading.Event()
    thread = threading.Thread(target=service.run, args=(stop,), name=f"{service.name}-loop",
                              daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout)
        if thread.is_alive():
            raise RuntimeError(f"the {service.name} loop did not stop within {timeout} s")


class ServiceHarness:
    """The ``name`` service of rig ``keys`` on a fake bus; bind a node to :attr:`service`."""

    def __init__(self, name: str, keys: Keys, bus: FakeBus | None = None) -> None:
        self.bus = bus or FakeBus()
        self.keys = keys
        self.service = Service(name, self.bus, keys)

    def record(self, key: str, message_type: type[M]) -> list[M]:
        """Every message published on ``key`` from now on, decoded, in order."""
        out: list[M] = []
        self.bus.subscribe(key, lambda _k, payload: out.append(message_type.from_msgpack(payload)))
        return out

    def send(self, key: str, *messages: Message | bytes) -> None:
        """Put each message (or raw payload) on ``key``, then let the service handle them all."""
        for m in messages:
            self.bus.put(key, m if isinstance(m, bytes) else m.to_msgpack())
        drain(self.service)

    def stats(self) -> ServiceStats:
        return ServiceStats.from_msgpack(self.bus.get(self.keys.stats(self.service.name))[0][1])

    def reset(self) -> Ack:
        """Call the ``reset`` queryable, as an operator would, while the loop runs."""
        with serving(self.service):
            return Ack.from_msgpack(self.bus.get(self.keys.reset(self.service.name))[0][1])
