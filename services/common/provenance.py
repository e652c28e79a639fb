"""Who answered a query: keep a service's reply only if it came from the session that runs it.

Zenoh reports with every reply the id (zid) of the session that sent it, and every service
announces the session that runs it with the liveliness token
``handkse/{rig}/alive/{service}/{zid}`` (:class:`services.common.service.Service`).
:func:`ask_service` queries a key that one service owns and keeps only the replies of a
session holding that service's token; the others are returned as ``untrusted`` for the caller
to count and log. If sessions of the service disagree (two hold the token and both answer),
nothing is chosen.

This is the second lock. The first is the router's access control
(``docker/zenoh/router.json5``): only the service's identity may declare its queryable, reply
on its keys and declare its tokens. Both rest on what the router enforces: a session id is
chosen by the session itself (Zenoh's ``id`` setting), so without access control a peer may
hold a token in a service's name, or, while the real service is down, take its id.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from services.common.bus import BusError, Reply
from services.common.keys import Keys


class UntrustedReply(BusError):
    """No reply came from a session that holds the service's token.

    ``untrusted`` holds the replies that were set aside (possibly none).
    """

    def __init__(self, message: str, untrusted: Sequence[Reply] = ()) -> None:
        super().__init__(message)
        self.untrusted = tuple(untrusted)


class AmbiguousReply(UntrustedReply):
    """Several sessions holding the service's token answered: which one is right is unknown."""


class QueryBus(Protocol):
    """What :func:`ask_service` needs from the bus (``services.common.bus.Bus``)."""

    def alive(self, key_expr: str, timeout: float = ...) -> list[str]: ...

    def get_replies(self, selector: str, payload: bytes | None = ...,
                    timeout: float = ...) -> list[Reply]: ...


@dataclass(frozen=True)
class Answer:
    """The reply kept, and the replies set aside because their session does not run the
    service (count and log them)."""

    reply: Reply
    untrusted: tuple[Reply, ...]


def sessions_of(bus: QueryBus, keys: Keys, service: str, timeout: float = 1.0) -> set[str]:
    """Ids of the sessions that currently hold ``service``'s session token."""
    prefix = keys.session(service, "")
    return {key[len(prefix):] for key in bus.alive(keys.sessions(service), timeout=timeout)
            if key.startswith(prefix)}


def choose(replies: Sequence[Reply], sessions: set[str], service: str,
           selector: str) -> Answer:
    """The reply of the one session in ``sessions`` that answered, and the untrusted rest.

    Raises :class:`UntrustedReply` when no reply is from such a session and
    :class:`AmbiguousReply` when replies come from more than one.
    """
    trusted = [r for r in replies if r.replier is not None and r.replier in sessions]
    untrusted = tuple(r for r in replies if r not in trusted)
    repliers = sorted({r.replier for r in trusted if r.replier is not None})
    if not trusted:
        holders = ", ".join(sorted(sessions)) or "none"
        others = ", ".join(sorted({str(r.replier) for r in untrusted}))
        raise UntrustedReply(
            f"get {selector!r}: {len(untrusted)} repl{'y' if len(untrusted) == 1 else 'ies'} "
            f"from session(s) {others}, none of which holds the {service} token (sessions "
            f"running {service}: {holders})", untrusted)
    if len(repliers) > 1:
        raise AmbiguousReply(
            f"get {selector!r}: sessions {', '.join(repliers)} all hold the {service} token "
            "and answered; refusing to choose between them", untrusted)
    return Answer(trusted[0], untrusted)


def ask_service(bus: QueryBus, keys: Keys, service: str, selector: str, *,
                timeout: float = 2.0) -> Answer:
    """Query ``selector`` (a key that ``service`` owns) and keep the reply of its session.

    Raises what :meth:`Bus.get_replies` raises when nothing answers, and
    :class:`UntrustedReply` (or :class:`AmbiguousReply`) as in :func:`choose`.
    """
    sessions = sessions_of(bus, keys, service, timeout=min(timeout, 1.0))
    replies = bus.get_replies(selector, timeout=timeout)
    return choose(replies, sessions, service, selector)
