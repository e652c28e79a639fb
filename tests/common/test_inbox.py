"""The service input queue: bounded, drop-oldest, counted; control calls first and never lost."""

from __future__ import annotations

import threading

import pytest

from services.common.bus import Bus, BusError
from services.common.inbox import Inbox
from services.common.keys import Keys
from services.common.protocol import HandLandmarks
from services.common.service import Service, ServiceLimits
from tests.common import samples
from tests.conftest import wait_until


def _event(tag: object) -> tuple:  # type: ignore[type-arg]
    return (print, (tag,))


def test_a_full_inbox_drops_the_oldest_sample_and_counts_it() -> None:
    inbox = Inbox(3)
    for i in range(5):
        inbox.put("a" if i % 2 else "b", _event(i))
    assert [inbox.take(0)[1][0] for _ in range(3)] == [2, 3, 4]  # type: ignore[index]
    assert inbox.dropped() == {"b": 1, "a": 1}
    assert inbox.take(0) is None


def test_control_calls_come_first_and_are_never_dropped() -> None:
    inbox = Inbox(1)
    inbox.put("a", _event("sample"))
    for i in range(10):
        inbox.call_soon(_event(f"control {i}"))
    taken = [inbox.take(0)[1][0] for _ in range(11)]  # type: ignore[index]
    assert taken == [f"control {i}" for i in range(10)] + ["sample"]
    assert inbox.dropped() == {}


def test_latest_inputs_keep_only_the_newest() -> None:
    inbox = Inbox(8)
    for i in range(4):
        inbox.put_latest("model", _event(i))
    inbox.put("lm", _event("landmarks"))
    assert inbox.take(0)[1][0] == 3  # type: ignore[index]
    assert inbox.take(0)[1][0] == "landmarks"  # type: ignore[index]
    assert inbox.dropped() == {}
    assert inbox.superseded() == {"model": 3}  # not lost: the newest is used


def test_take_waits_for_a_producer() -> None:
    inbox = Inbox(2)
    threading.Timer(0.05, inbox.put, ("a", _event("late"))).start()
    event = inbox.take(5.0)
    assert event is not None and event[1][0] == "late"


def test_capacity_must_be_positive() -> None:
    with pytest.raises(ValueError, match="capacity"):
        Inbox(0)
    with pytest.raises(ValueError, match=r"limits\.queue_size"):
        ServiceLimits(queue_size=0)


def _answers(bus: Bus, key: str) -> bool:
    try:
        return bool(bus.get(key, timeout=0.5))
    except BusError:
        return False


def test_a_service_behind_its_input_drops_and_counts_and_refuses_large_payloads(
        client_bus: Bus) -> None:
    keys = Keys("inbox")
    service = Service("probe", client_bus, keys, ServiceLimits(queue_size=4, max_payload_bytes=4096))
    handled: list[int] = []
    service.subscribe(keys.hand_landmarks, HandLandmarks, lambda m: handled.append(m.stamp_ns))
    wire = samples.hand_landmarks()
    with Bus(client_bus.options) as publisher:
        wait_until(lambda: _answers(publisher, keys.stats("probe")), timeout=5)  # routes are up
        for i in range(10):  # the loop is not running: the inbox fills
            publisher.put(keys.hand_landmarks, wire.__class__(
                seq=i, stamp_ns=i + 1, frame_id="camera", hands=wire.hands).to_msgpack())
        publisher.put(keys.hand_landmarks, b"\x80" * 10_000)
        wait_until(lambda: service.received + service.inbox_dropped() + len(service._inbox) >= 10
                   and service.rejected.get("too_large", 0) == 1, timeout=10)
    assert service.inbox_dropped() == 6
    assert service.stats().dropped == 6
    assert service.rejected == {"too_large": 1}
    stop = threading.Event()
    runner = threading.Thread(target=service.run, args=(stop,))
    runner.start()
    wait_until(lambda: len(handled) == 4, timeout=5)
    stop.set()
    runner.join()
    assert handled == [7, 8, 9, 10]  # the newest four survived, in order
