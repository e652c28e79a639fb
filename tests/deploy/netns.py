"""Linux network namespaces for multi-host tests: one hub namespace joined to leaf namespaces by
veth pairs, each pair on its own /30 subnet, with link cut and restore.

Needs root and iproute2 (``ip``); :func:`unavailable_reason` says why a machine cannot run them
(not root, no ``ip``, or ``ip netns add`` refused, as inside many containers). Namespace names
carry this process's pid (``hk<pid>x<n>-<role>``); :meth:`Topology.teardown` runs on every exit
path, and :func:`remove_stale` deletes what a killed earlier run left behind.
"""

from __future__ import annotations

import functools
import itertools
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass

NAME_PREFIX = "hk"
_STALE = re.compile(rf"^{NAME_PREFIX}(\d+)x\d+-")
_counter = itertools.count()

LEAF_IF = "eth0"  # the leaf's end of its veth pair, inside the leaf namespace


class NetnsError(RuntimeError):
    """An ``ip`` command failed; the message has its command line and error output."""


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    """Run ``ip <args>``; raise :class:`NetnsError` with its stderr when it fails and ``check``."""
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30,
                            check=False)
    if check and result.returncode != 0:
        raise NetnsError(f"ip {' '.join(args)}: {result.stderr.strip() or result.returncode}")
    return result


@functools.cache
def unavailable_reason() -> str | None:
    """Why network-namespace tests cannot run here, or None when they can.

    Probes the real operations once: namespace creation, loopback up, a veth pair between
    two namespaces and running a command inside one (``ip netns exec`` needs to remount
    ``/sys``, which some containers refuse).
    """
    if not sys.platform.startswith("linux"):
        return f"network namespaces need Linux (this is {sys.platform})"
    if os.geteuid() != 0:
        return "needs root to create network namespaces (run the tests as root)"
    if shutil.which("ip") is None:
        return "the `ip` command is missing (apt-get install iproute2)"
    try:
        with Topology(["probe"]) as topology:
            ip(*topology.prefix("probe")[1:], "true")
    except (NetnsError, OSError, subprocess.SubprocessError) as exc:
        return f"cannot create network namespaces and veth pairs here: {exc}"
    return None


def remove_stale() -> list[str]:
    """Delete namespaces named by this module whose creating process no longer exists."""
    listing = ip("netns", "list", check=False).stdout
    removed = []
    for line in listing.splitlines():
        name = line.split()[0] if line.split() else ""
        match = _STALE.match(name)
        if (match and not os.path.exists(f"/proc/{match.group(1)}")
                and ip("netns", "del", name, check=False).returncode == 0):
            removed.append(name)
    return removed


@dataclass(frozen=True)
class Leaf:
    """One leaf namespace and its link to the hub (IPv4, /30)."""

    role: str
    netns: str
    address: str       # the leaf's address on its link
    hub_address: str   # the hub's address on the same link: what the leaf connects to
    hub_if: str        # the hub's end of the veth pair, inside the hub namespace


class Topology:
    """A hub namespace with one veth link to each leaf namespace; a context manager.

    Leaf ``i`` (from 1) gets ``10.231.i.2/30`` on ``eth0``; the hub gets ``10.231.i.1/30`` on
    ``to-<role>``. Loopback is up everywhere. Nothing is connected to the host's own network.
    """

    def __init__(self, leaves: Sequence[str], hub: str = "router") -> None:
        if len(set(leaves)) != len(leaves) or hub in leaves:
            raise ValueError(f"roles must be distinct: hub {hub!r}, leaves {list(leaves)}")
        if len(leaves) > 250:
            raise ValueError("at most 250 leaves")
        tag = f"{NAME_PREFIX}{os.getpid()}x{next(_counter)}"
        self.hub_role = hub
        self.hub = f"{tag}-{hub}"
        self.leaves: dict[str, Leaf] = {}
        for i, role in enumerate(leaves, start=1):
            self.leaves[role] = Leaf(role=role, netns=f"{tag}-{role}",
                                     address=f"10.231.{i}.2", hub_address=f"10.231.{i}.1",
                                     hub_if=f"to-{role}"[:15])
        self._created: list[str] = []

    def __enter__(self) -> Topology:
        self.create()
        return self

    def __exit__(self, *exc: object) -> None:
        self.teardown()

    def create(self) -> None:
        """Create every namespace and link; on failure remove what was made, then raise."""
        try:
            for ns in (self.hub, *(leaf.netns for leaf in self.leaves.values())):
                ip("netns", "add", ns)
                self._created.append(ns)
                ip("-n", ns, "link", "set", "lo", "up")
            for leaf in self.leaves.values():
                # Both ends are created directly inside their namespaces: no name on the host.
                ip("link", "add", LEAF_IF, "netns", leaf.netns, "type", "veth",
                   "peer", "name", leaf.hub_if, "netns", self.hub)
                ip("-n", leaf.netns, "addr", "add", f"{leaf.address}/30", "dev", LEAF_IF)
                ip("-n", self.hub, "addr", "add", f"{leaf.hub_address}/30", "dev", leaf.hub_if)
                ip("-n", leaf.netns, "link", "set", LEAF_IF, "up")
                ip("-n", self.hub, "link", "set", leaf.hub_if, "up")
        except BaseException:
            self.teardown()
            raise

    def teardown(self) -> None:
        """Delete every namespace this topology created (their veth pairs go with them).

        Processes still running inside keep a namespace alive until they exit, so stop them
        first.
        """
        while self._created:
            ip("netns", "del", self._created.pop(), check=False)

    def namespace(self, role: str) -> str:
        """The namespace name of ``role`` (the hub's role or a leaf's)."""
        return self.hub if role == self.hub_role else self.leaves[role].netns

    def prefix(self, role: str) -> list[str]:
        """Command prefix that runs a command inside ``role``'s namespace."""
        return ["ip", "netns", "exec", self.namespace(role)]

    def link_down(self, role: str) -> None:
        """Cut ``role``'s link to the hub (its own end goes down; the peer loses carrier)."""
        ip("-n", self.leaves[role].netns, "link", "set", LEAF_IF, "down")

    def link_up(self, role: str) -> None:
        """Restore ``role``'s link to the hub (addresses stay configured while down)."""
        ip("-n", self.leaves[role].netns, "link", "set", LEAF_IF, "up")

    def link_state(self, role: str) -> str:
        """``UP``, ``DOWN`` or ``LOWERLAYERDOWN`` as ``ip`` reports the leaf's end."""
        out = ip("-n", self.leaves[role].netns, "-o", "link", "show", LEAF_IF).stdout
        match = re.search(r"state (\S+)", out)
        return match.group(1) if match else "UNKNOWN"
