"""``LinkProxy``: forwards, blackholes on cut, refuses new connections, recovers on restore."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Iterator

import pytest

from services.evaluation.drills.linkproxy import LinkProxy


@pytest.fixture
def echo() -> Iterator[tuple[str, int]]:
    """A TCP echo server on loopback."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(0.1)
    stop = threading.Event()

    def serve(conn: socket.socket) -> None:
        with conn:
            while data := conn.recv(4096):
                conn.sendall(data)

    def accept() -> None:
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except OSError:
                continue
            conn.settimeout(None)
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    yield server.getsockname()
    stop.set()
    t.join(2.0)
    server.close()


def _connect(proxy: LinkProxy) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", proxy.port), timeout=2.0)
    s.settimeout(2.0)
    return s


def test_forwards_then_blackholes_then_recovers(echo: tuple[str, int]) -> None:
    with LinkProxy(echo) as proxy:
        assert proxy.endpoint == f"tcp/127.0.0.1:{proxy.port}"
        a = _connect(proxy)
        a.sendall(b"hello")
        assert a.recv(16) == b"hello"

        proxy.cut()
        assert not proxy.is_up
        a.sendall(b"lost")
        a.settimeout(0.3)
        with pytest.raises(TimeoutError):  # no echo and no close: a silent link
            a.recv(16)
        with pytest.raises(ConnectionRefusedError):
            socket.create_connection(("127.0.0.1", proxy.port), timeout=1.0)
        assert proxy.dropped_bytes >= len(b"lost")

        proxy.restore()
        a.settimeout(2.0)
        with contextlib.suppress(ConnectionResetError):  # what lived through the cut is closed
            assert a.recv(16) == b""
        b = _connect(proxy)
        b.sendall(b"again")
        assert b.recv(16) == b"again"
        assert proxy.accepted == 2
        a.close()
        b.close()


def test_cut_with_reset_closes_at_once(echo: tuple[str, int]) -> None:
    with LinkProxy(echo) as proxy:
        a = _connect(proxy)
        a.sendall(b"x")
        assert a.recv(4) == b"x"
        proxy.cut(reset=True)
        with contextlib.suppress(ConnectionResetError):
            assert a.recv(4) == b""
        a.close()


def test_unreachable_target_closes_the_client() -> None:
    with socket.socket() as s:  # a port with nothing listening
        s.bind(("127.0.0.1", 0))
        target = s.getsockname()
    with LinkProxy(target) as proxy:
        a = _connect(proxy)
        with contextlib.suppress(ConnectionResetError):
            assert a.recv(4) == b""
        a.close()
        assert proxy.refused == 1 and proxy.accepted == 0
