"""Multi-host deployment in Linux network namespaces (issue 8, items 3 and 4 across hosts).

A ``router`` namespace is joined by veth pairs to ``gpu`` (live synthetic replay standing in
for camera + detector, and the operator/observer), ``cpu`` (tracker + kinematics) and
``robot`` (robot bridge, MuJoCo); every process is a Zenoh client of ``handkse router`` with a
2 s lease (``bench/multihost.py`` runs them and records what the observer saw). Root only;
skipped with the reason otherwise. Timing goals live in ``bench/multihost.py``; the bounds here
only tell a 2 s lease from the 10 s default and a recovery from none.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.multihost import (
    LEASE_MS,
    PIPELINE,
    ROLES,
    STALE_REASONS,
    loopback_placement,
    netns_placement,
    run_demonstration,
    run_outage,
    stale_grace_s,
)
from tests.deploy.netns import Topology, remove_stale, unavailable_reason

pytestmark = [pytest.mark.netns, pytest.mark.slow]

LEASE_S = LEASE_MS / 1000
# Tokens must vanish this soon after the cut: the lease plus scheduling slack on a loaded
# 2-core machine; well under the 10 s default lease, so a lost lease setting fails.
VANISH_BOUND_S = LEASE_S + 2.0


@pytest.fixture
def topology() -> Iterator[Topology]:
    """Four fresh namespaces (router, gpu, cpu, robot), removed after the test."""
    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    pytest.importorskip("mujoco", reason="the robot bridge runs the MuJoCo backend")
    remove_stale()
    with Topology(ROLES) as topo:
        yield topo


def test_three_namespaces_give_the_same_model_as_one_host(topology: Topology,
                                                          tmp_path: Path) -> None:
    netns = run_demonstration(netns_placement(topology), tmp_path / "netns", "slider")
    one_host = run_demonstration(loopback_placement(), tmp_path / "loopback", "slider",
                                 robot=False)
    print(f"\ntangent error: namespaces {netns.tangent_error_deg:.3f} deg "
          f"({netns.model.updates} updates), one host {one_host.tangent_error_deg:.3f} deg "
          f"({one_host.model.updates} updates); robot dry run: {netns.dry_run}")
    assert netns.model.updates > 0 and one_host.model.updates > 0
    assert netns.model.type == one_host.model.type
    assert abs(netns.tangent_error_deg - one_host.tangent_error_deg) <= 0.5
    # The operator in gpu reaches the bridge in robot, which reaches kinematics in cpu: the
    # dry run is answered and not refused for want of a (live) model.
    assert "reason" in netns.dry_run, netns.dry_run
    assert netns.dry_run["reason"] not in STALE_REASONS, netns.dry_run


def test_cut_links_are_detected_refused_and_recovered(topology: Topology,
                                                       tmp_path: Path) -> None:
    outage = run_outage(topology, tmp_path / "outage", cuts=(3.0, 15.0))
    grace = stale_grace_s()
    for cut in outage.cuts:
        print(f"\n{cut.duration_s:g} s cut: {cut.to_json()}")
    assert not outage.crashed, outage.crashed
    # Before any cut the bridge answered on a live model (so the refusals below are news).
    assert outage.dry_run_before is not None
    for cut in outage.cuts:
        what = f"{cut.duration_s:g} s cut: {cut.to_json()}"
        # The observer in gpu saw both tokens vanish within the lease (before link up).
        for service in PIPELINE:
            vanished = cut.vanished[service]
            assert vanished is not None, what
            assert vanished <= VANISH_BOUND_S, what
        assert not cut.robot_token_lost, what  # the robot namespace was not cut
        # The bridge refused for want of a live model requests made while the link was down
        # (on a loaded machine the answer may arrive just after link up), and refused every
        # dry run it decided after its cached model had expired (started `grace` s or more
        # after the cut and answered before link up). In a 3 s cut that window is 1 s long and
        # the bridge may spend all of it waiting on a 2 s model query, so only a long cut is
        # sure to sample it.
        assert any(r in STALE_REASONS for r in cut.started_during()), what
        late = cut.answered_during(grace)
        assert all(r in STALE_REASONS for r in late), what
        if cut.duration_s >= 10.0:
            assert late, f"no dry run decided {grace:.1f} s or more into the outage; {what}"
        # The pipeline came back by itself: tokens, models continuing the same estimate
        # (update count not reset) and a dry run on a live model again.
        assert all(cut.back[s] is not None for s in PIPELINE), what
        assert cut.first_model_s is not None and cut.models_after >= 10, what
        assert cut.first_updates_after > cut.updates_before >= 1, what
        assert cut.dry_run_after is not None, what
