"""The count-based half of the load benchmark (the timing half lives in ``bench/``).

Two rigs at 5x real time through one router: every landmark frame yields a HandBody, every
initialised body a model, nothing is rejected or dropped, and each rig's model is learnt from
its own rig's data only (the rigs end on objects of different joint types). The frames keep
their capture spacing (shifted to the wall clock) so that the filters see the recorded time
steps however loaded the machine is; ``bench/load.py`` stamps them at sending.

A flood of 5,000 landmark messages/s (``bench/flood.py``, here 2 s of it): whatever the services
manage to handle, nothing is lost without a count, the flood of stale copies is refused, never
used, and the model of a demonstration after the flood is the clean run's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.flood import phase_counts, run_flood, silent_losses
from bench.load import dropped, rig_counts, run_scenario
from services.synthetic.generator import generate

# each rig ends on its own object of another joint type; the first demonstrations exercise the
# reset between demonstrations
RIGS = {"a": [("roll", 2), ("window_lock", 3)], "b": [("valve", 2), ("slider", 2)]}


def test_two_rigs_at_5x_lose_nothing_and_do_not_mix(tmp_path: Path) -> None:
    # capture stamps: the filters see the recorded time steps however loaded the machine is
    run = run_scenario("test", RIGS, rate=5.0, workdir=tmp_path, restamp=False)
    assert set(run.rigs) == set(RIGS)
    for rig, r in run.rigs.items():
        counts = rig_counts(r)
        assert counts["landmarks_sent"] == sum(len(generate(o, p, 0).stamps_ns)
                                               for o, p in RIGS[rig])
        # every frame yields a body, every initialised body a model, all from this rig
        assert dropped(counts) == 0 and counts["tracker_no_body"] == 0, counts
        assert counts["hand_bodies"] == counts["landmarks_sent"], counts
        assert counts["landmarks_without_body"] == 0, counts
        assert counts["initialised_bodies_without_model"] == 0, counts
        assert counts["bodies_not_from_this_rig"] == 0, counts
        assert counts["models_not_from_this_rig"] == 0, counts
        assert counts["settle_timeouts"] == 0, counts
        for service, stats in r.stats.items():
            assert stats.dropped == 0 and dict(stats.rejected) == {}, (rig, service, stats)
        assert r.stats["kinematics"].received == r.stats["tracker"].published

        # the final model: this rig's last object, learnt from exactly its last demonstration
        name, participant = RIGS[rig][-1]
        truth = generate(name, participant, 0).truth.joint
        final = r.models[-1][1]
        last_demo = set(r.sent_stamps[-1])
        assert final.updates == sum(b.initialized and b.stamp_ns in last_demo
                                    for _, b in r.bodies)
        assert final.type == truth.type, (rig, final.type, final.probabilities)
        params = final.revolute if final.type == "revolute" else final.prismatic
        assert params is not None
        angle = np.degrees(np.arccos(min(1.0, abs(float(params.axis @ truth.axis)))))
        assert angle < 15.0, (rig, name, angle)


def test_a_flood_loses_nothing_silently_and_leaves_the_model_as_the_clean_run(
        tmp_path: Path) -> None:
    run = run_flood(tmp_path, rate=5000.0, seconds=2.0)
    phases = {p.name: p for p in run.phases}
    assert list(phases) == ["clean", "absorbed flood", "refused flood during the demonstration",
                            "after"]
    frames = len(generate("key", 3, 0).stamps_ns)
    for phase in run.phases:
        counts = phase_counts(phase)
        assert phase.settled, (phase.name, counts)
        # at each subscriber every message sent was handled or counted as dropped, and every
        # handled one has an outcome (a body or model, a refusal, a skip)
        assert silent_losses(counts) == dict.fromkeys(silent_losses(counts), 0), (phase.name,
                                                                                  counts)
        assert counts["flood_sent"] == (10_000 if "flood" in phase.name else 0)
        assert counts["bodies_observed"] == counts["tracker_published"]
        assert counts["kinematics_rejected"] == 0, (phase.name, phase.after["kinematics"])
        if phase.name != "absorbed flood":
            assert len(phase.demonstration_stamps) == frames
            assert counts["landmarks_sent"] == frames + counts["flood_sent"]

    # the refused flood: copies of the first frame are refused as stale, never used; a real
    # frame without a body is one the tracker counted as dropped
    refused = phases["refused flood during the demonstration"]
    counts = phase_counts(refused)
    before = refused.before["tracker"].rejected
    rejected = {k: v - before.get(k, 0) for k, v in refused.after["tracker"].rejected.items()
                if v != before.get(k, 0)}
    assert set(rejected) <= {"duplicate_stamp", "out_of_order_stamp"}, rejected
    assert counts["tracker_published"] <= frames
    stamps = set(refused.demonstration_stamps)
    assert all(b.stamp_ns in stamps for b in refused.bodies)
    missing = len(stamps - {b.stamp_ns for b in refused.bodies})
    assert missing <= counts["tracker_dropped"]
    # each landmark message was published as a body, refused, skipped, or dropped
    outcomes = counts["tracker_published"] + sum(rejected.values()) + counts["tracker_skipped"]
    assert outcomes + counts["tracker_dropped"] == frames + counts["flood_sent"], counts

    # once the flood ended, the demonstration gives the clean run's model
    clean, after = phases["clean"].model, phases["after"].model
    assert clean is not None and after is not None
    assert clean.type == after.type == "revolute"
    assert after.updates == clean.updates
    assert clean.revolute is not None and after.revolute is not None
    angle = np.degrees(np.arccos(min(1.0, abs(float(clean.revolute.axis @ after.revolute.axis)))))
    assert angle < 2.0
