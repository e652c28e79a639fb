"""The kinematics service's contact phases: what it publishes, what ``get`` and
``kinematics/models`` answer, on the in-memory bus and as a process over a real router (with a
kill and restart in the middle of a sequence)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from services.common.bus import Bus
from services.common.protocol import HandBody, KinematicModel, KinematicModelList, LandmarkStates
from services.synthetic.demonstration import Demonstration
from services.synthetic.generator import generate
from tests.conftest import Processes, wait_until
from tests.kinematics.test_service import KEYS, FakeKinematics, _kill, _start

POSE_COVARIANCE = np.diag([9e-6] * 3 + [1.2e-3] * 3 + [1e-4] * 6)


def truth_bodies(demo: Demonstration) -> list[HandBody]:
    """The demonstration's true hand poses and landmarks as the tracker would publish them."""
    tr = demo.truth
    return [HandBody(seq=i, stamp_ns=int(s), initialized=True, pose=tr.T_camera_hand[i],
                     twist=np.zeros(6), covariance=POSE_COVARIANCE,
                     motion_model="constant_velocity",
                     landmarks=LandmarkStates(points=tr.landmarks_true[i].astype("<f4"),
                                              variance=np.zeros(21, "<f4"),
                                              status=np.ones(21, "|u1")))
            for i, s in enumerate(demo.stamps_ns)]


def _models(node: FakeKinematics, parameters: str = "") -> bytes:
    selector = KEYS.kinematics_models + (f"?{parameters}" if parameters else "")
    replies = node.bus.get(selector)
    assert [key for key, _ in replies] == [KEYS.kinematics_models]
    return replies[0][1]


def test_get_after_the_release_and_withdrawal_answers_the_manipulated_joint() -> None:
    demo = generate("cabinet_door", 6, 0, variant="whole")
    truth = demo.truth.segments[0]
    node = FakeKinematics()
    node.bodies(*truth_bodies(demo))
    published = node.models
    assert len(published) == len(demo.stamps_ns)  # one model per accepted body
    reach = [m for m in published if m.stamp_ns < truth.onset_ns - 0.2e9]
    assert reach and all(m.phase == "free" and m.type == "unknown" for m in reach)
    assert published[-1].phase == "free"
    answer = node.model()
    assert answer.type == "revolute" and answer.probabilities["revolute"] > 0.9
    assert answer.segment == 0 and answer.segment_end_ns is not None
    assert abs(answer.segment_end_ns - truth.release_ns) < 0.15e9
    assert answer.stamp_ns == published[-1].stamp_ns and answer.phase == "free"


def test_kinematics_models_lists_every_phase_in_msgpack_and_json() -> None:
    demo = generate("cabinet_door", 7, 0, variant="regrasp")
    second = demo.truth.segments[1]
    bodies = truth_bodies(demo)
    node = FakeKinematics()
    empty = KinematicModelList.from_msgpack(_models(node))
    assert empty.models == ()
    during = [b for b in bodies if b.stamp_ns < second.onset_ns + 0.3e9]
    node.bodies(*during)
    listed = KinematicModelList.from_msgpack(_models(node)).models
    assert [m.segment for m in listed] == [0, 1]
    assert listed[0].segment_end_ns is not None and listed[1].segment_end_ns is None
    assert listed[1].phase == "contact"
    # the open phase has no verdict yet: get answers the closed one
    assert node.model().segment == 0 and node.model().type == "revolute"
    node.bodies(*bodies[len(during):])
    listed = KinematicModelList.from_msgpack(_models(node)).models
    assert [(m.segment, m.first_segment, m.type) for m in listed] == [
        (0, None, "revolute"), (1, 0, "revolute")]
    assert all(m.segment_end_ns is not None for m in listed)
    as_json = json.loads(_models(node, "format=json"))
    assert as_json["schema"] == "handkse.KinematicModelList/1"
    assert [m["segment"] for m in as_json["models"]] == [0, 1]
    assert as_json["models"][1]["first_segment"] == 0
    assert node.model().segment == 1


def _remote_models(bus: Bus) -> tuple[KinematicModel, ...]:
    return KinematicModelList.from_msgpack(bus.get(KEYS.kinematics_models)[0][1]).models


def _content(model: KinematicModel) -> bytes:
    """A phase's model without the envelope of the latest frame (stamp, seq, phase)."""
    return dataclasses.replace(model, seq=0, stamp_ns=0, phase=None).to_msgpack()


def test_kinematics_models_over_a_real_router_survive_a_restart_mid_sequence(
        procs: Processes, router: str, client_bus: Bus, tmp_path: Path) -> None:
    demo = generate("cabinet_door", 7, 0, variant="regrasp")
    bodies = truth_bodies(demo)
    between = int(np.searchsorted(demo.stamps_ns, demo.truth.segments[0].release_ns + 1.0e9))
    state = tmp_path / "kin.state"
    kin = _start(procs, router, state, client_bus)
    for b in bodies[:between]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    wait_until(lambda: KinematicModel.from_msgpack(
        client_bus.get(KEYS.kinematics_model)[0][1]).stamp_ns == bodies[between - 1].stamp_ns,
        30, what="the bodies before the second grasp")
    (first,) = _remote_models(client_bus)
    assert first.type == "revolute" and first.segment_end_ns is not None

    _kill(kin, client_bus)  # kill -9 between the phases; the restart keeps the closed one
    _start(procs, router, state, client_bus)
    (restored,) = _remote_models(client_bus)
    assert _content(restored) == _content(first)
    for b in bodies[between:]:
        client_bus.put(KEYS.hand_body, b.to_msgpack())
    wait_until(lambda: len(_remote_models(client_bus)) == 2
               and _remote_models(client_bus)[1].segment_end_ns is not None, 30,
               what="the second phase closed")
    listed = _remote_models(client_bus)
    assert _content(listed[0]) == _content(first)
    assert (listed[1].type, listed[1].first_segment) == ("revolute", 0)
    as_json = json.loads(client_bus.get(KEYS.kinematics_models + "?format=json")[0][1])
    assert [m["segment"] for m in as_json["models"]] == [0, 1]
    assert as_json["models"][0]["segment_end_ns"] == first.segment_end_ns
