"""Bad input at the boundary: random and mutated payloads to every subscribed key and queryable
of the running services. No service dies, every protocol rejection is counted, and valid
traffic after the fuzzing is processed in full."""

from __future__ import annotations

import contextlib
import json
import time

import msgpack
import numpy as np

from services.common.bus import Bus, BusError
from services.common.keys import Keys
from services.common.protocol import (
    HandBody,
    HandLandmarks,
    KinematicModel,
    Message,
    ProtocolError,
)
from services.synthetic.generator import generate
from services.synthetic.replay import landmark_messages
from tests.common import samples
from tests.conftest import Processes, output_of, wait_until, zenoh_args

KEYS = Keys("fuzz")
PER_KEY = 300
PROTOCOL_REASONS = ("bad_msgpack", "wrong_schema", "wrong_version", "bad_field")


def _random_structure(rng: np.random.Generator, depth: int = 0) -> object:
    kind = rng.integers(0, 8 if depth < 3 else 5)
    if kind == 0:
        return None
    if kind == 1:
        return bool(rng.integers(0, 2))
    if kind == 2:
        return int(rng.integers(-(2**40), 2**40))
    if kind == 3:
        return float(rng.normal() * 10.0 ** int(rng.integers(-3, 30)))
    if kind == 4:
        return rng.bytes(int(rng.integers(0, 40)))
    if kind == 5:
        return [_random_structure(rng, depth + 1) for _ in range(rng.integers(0, 4))]
    keys = ["schema", "seq", "stamp_ns", "frame_id", "hands", "pose", "dtype", "shape", "data",
            "type", "probabilities", "x"]
    return {str(rng.choice(keys)): _random_structure(rng, depth + 1)
            for _ in range(rng.integers(0, 6))}


def _mutate(rng: np.random.Generator, payload: bytes) -> bytes:
    b = bytearray(payload)
    op = rng.integers(0, 4)
    if op == 0 and b:  # flip bytes
        for _ in range(rng.integers(1, 6)):
            b[rng.integers(0, len(b))] = int(rng.integers(0, 256))
    elif op == 1:  # truncate
        b = b[: rng.integers(0, len(b) + 1)]
    elif op == 2:  # insert garbage
        pos = int(rng.integers(0, len(b) + 1))
        b[pos:pos] = rng.bytes(int(rng.integers(1, 20)))
    else:  # swap a field's value in the decoded map
        obj = msgpack.unpackb(payload, raw=False)
        key = str(rng.choice(sorted(obj)))
        obj[key] = _random_structure(rng)
        return msgpack.packb(obj, use_bin_type=True)
    return bytes(b)


def _corpus(rng: np.random.Generator, valid: Message) -> list[bytes]:
    out = []
    for i in range(PER_KEY):
        if i % 3 == 0:
            out.append(rng.bytes(int(rng.integers(0, 200))))
        elif i % 3 == 1:
            out.append(msgpack.packb(_random_structure(rng), use_bin_type=True))
        else:
            out.append(_mutate(rng, valid.to_msgpack()))
    return out


def _invalid(payloads: list[bytes], cls: type[Message]) -> int:
    n = 0
    for p in payloads:
        try:
            cls.from_msgpack(p)
        except ProtocolError:
            n += 1
    return n


def _stats(bus: Bus, service: str) -> dict[str, object]:
    return dict(json.loads(bus.get(KEYS.stats(service) + "?format=json")[0][1]))


def test_services_survive_fuzzing_and_keep_serving(procs: Processes, router: str,
                                                   client_bus: Bus, tmp_path) -> None:  # type: ignore[no-untyped-def]
    z = zenoh_args(router)
    tracker = procs.start("tracker", "--rig", KEYS.rig, *z, name="tracker")
    kinematics = procs.start("kinematics", "--rig", KEYS.rig, "--state-file",
                             str(tmp_path / "k.state"), *z, name="kinematics")
    for name, p in (("tracker", tracker), ("kinematics", kinematics)):
        wait_until(lambda n=name: KEYS.alive(n) in client_bus.alive(KEYS.alive_all), 30,
                   what=f"{name} alive; log: {output_of(p)}")
    rng = np.random.default_rng(7)
    targets = {  # key -> (message type, services that subscribe to it)
        KEYS.hand_landmarks: (HandLandmarks, samples.hand_landmarks(), ["tracker"]),
        KEYS.hand_body: (HandBody, samples.hand_body(), ["kinematics"]),
        KEYS.kinematics_model: (KinematicModel, samples.kinematic_model(), ["tracker"]),
    }
    expected_rejections = {"tracker": 0, "kinematics": 0}
    sent = {"tracker": 0, "kinematics": 0}
    deadline = time.monotonic() + 60.0  # bounded in time as well as in count
    for key, (cls, valid, subscribers) in targets.items():
        payloads = _corpus(rng, valid)
        bad = _invalid(payloads, cls)
        for payload in payloads:
            if time.monotonic() > deadline:
                break
            client_bus.put(key, payload)
        for s in subscribers:
            expected_rejections[s] += bad
            sent[s] += len(payloads)

    # queryables: random selector parameters and payloads must be answered or refused cleanly
    for service in ("tracker", "kinematics"):
        for i in range(20):
            params = f"?format={rng.choice(['json', 'x', ''])};p{i}={rng.integers(0, 99)}"
            for key in (KEYS.stats(service), KEYS.kinematics_model):
                with contextlib.suppress(BusError):  # an error reply is a clean refusal
                    client_bus.get(key + params, payload=rng.bytes(int(rng.integers(0, 50))))

    for service in ("tracker", "kinematics"):
        # >=: a mutated payload may be a valid HandBody, and then kinematics publishes a
        # (valid) model that the tracker also receives
        wait_until(lambda s=service: _stats(client_bus, s)["received"] >= sent[s], 60,
                   what=f"{service} received everything: {sent[service]} sent, stats "
                        f"{_stats(client_bus, service)}")
        stats = _stats(client_bus, service)
        rejected = stats["rejected"]
        assert isinstance(rejected, dict)
        assert all(isinstance(k, str) and k and v > 0 for k, v in rejected.items())
        protocol = sum(rejected.get(r, 0) for r in PROTOCOL_REASONS)
        assert protocol == expected_rejections[service], (service, rejected)
    assert tracker.poll() is None and kinematics.poll() is None

    # valid traffic after the fuzzing: nothing lost
    for service in ("tracker", "kinematics"):
        client_bus.get(KEYS.reset(service))
    bodies: list[HandBody] = []
    client_bus.subscribe(KEYS.hand_body, lambda k, p: bodies.append(HandBody.from_msgpack(p)))
    time.sleep(0.2)
    frames = landmark_messages(generate("slider", 3, 0))
    rejected_before = {s: dict(_stats(client_bus, s)["rejected"]) for s in sent}  # type: ignore[arg-type]
    for m in frames:
        client_bus.put(KEYS.hand_landmarks, m.to_msgpack())
    wait_until(lambda: bool(bodies) and bodies[-1].stamp_ns == frames[-1].stamp_ns, 30,
               what="last hand body")
    wait_until(lambda: KinematicModel.from_msgpack(client_bus.get(KEYS.kinematics_model)[0][1])
               .updates == sum(b.initialized for b in bodies), 10,
               what="kinematics absorbed every initialised hand body")
    for s in sent:
        assert _stats(client_bus, s)["rejected"] == rejected_before[s]
