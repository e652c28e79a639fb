"""A request that names a contact phase: the bridge articulates that phase's model from the
kinematics service's ``kinematics/models`` (docs/protocol.md#contact-phases)."""

from __future__ import annotations

from dataclasses import replace

from tests.robot_bridge.test_details import CONFIG, HALF_TURN, _model
from tests.robot_bridge.test_stale_model import Rig


def test_a_named_closed_phase_is_articulated_from_the_model_list() -> None:
    rig = Rig(CONFIG)
    try:
        closed = replace(_model(), segment=0, segment_start_ns=1, segment_end_ns=2)
        rig.serve_models = lambda: (closed, replace(_model(), segment=1, segment_start_ns=3))
        result = rig.articulate(replace(HALF_TURN, segment=0, dry_run=True))
        assert result.success, result.detail
        assert rig.fetches == 0  # the model came from the phase list, not from get
        refused = rig.articulate(replace(HALF_TURN, segment=1, dry_run=True))
        assert (refused.success, refused.reason) == (False, "open_segment")
    finally:
        rig.close()
