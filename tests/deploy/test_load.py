"""Two rigs at 5x real time through one router: the count-based half of the load benchmark.

Every landmark frame yields a HandBody, every initialised body a model, nothing is rejected or
dropped, and each rig's model is learnt from its own rig's data only (the rigs end on objects of
different joint types). The frames keep their capture spacing (shifted to the wall clock) so
that the filters see the recorded time steps however loaded the machine is; the timing half,
with frames stamped at sending, lives in ``bench/load.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

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
