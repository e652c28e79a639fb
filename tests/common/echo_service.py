"""A minimal real service for bus tests: republishes every valid HandLandmarks on test/echo.

Run: ``python -m tests.common.echo_service ENDPOINT RIG``.
"""

from __future__ import annotations

import sys
import threading

from services.common.bus import Bus, ZenohOptions
from services.common.keys import Keys
from services.common.protocol import HandLandmarks
from services.common.service import Service, stop_on_signals


def main(endpoint: str, rig: str) -> None:
    keys = Keys(rig)
    stop = threading.Event()
    stop_on_signals(stop)
    with Bus(ZenohOptions(mode="client", connect=(endpoint,), multicast_scouting=False)) as bus:
        service = Service("echo", bus, keys)
        service.subscribe(keys.hand_landmarks, HandLandmarks,
                          lambda m: service.publish(f"{keys.root}/test/echo", m))
        print("echo ready", flush=True)
        service.run(stop)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
