"""A TCP forwarding proxy whose link can be cut: a network outage on one host, no privileges.

``LinkProxy((host, port))`` listens on ``127.0.0.1:<free port>`` (:attr:`LinkProxy.endpoint`
is its Zenoh endpoint) and forwards every accepted connection to the target. Put it between
some clients and their router, then:

- :meth:`LinkProxy.cut` (default) emulates a dead link: every byte in flight or sent later is
  discarded in both directions, a close is not passed on (each peer notices the outage only
  through its own lease, as with a pulled cable), and new connections are refused (the
  listening socket is closed). ``cut(reset=True)`` instead closes every connection at once
  (peers notice immediately, like a link that goes down with a TCP reset).
- :meth:`LinkProxy.restore` closes what survived the cut (those streams lost bytes and cannot
  continue) and listens again on the same port, so the clients' reconnect attempts succeed.

Threads: one accepting, two per connection (one per direction). Nothing is buffered beyond the
kernel's socket buffers.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading

log = logging.getLogger(__name__)

_CHUNK = 65536
_ACCEPT_POLL_S = 0.05


class _Connection:
    """One proxied connection: the accepted socket and the one to the target."""

    def __init__(self, downstream: socket.socket, upstream: socket.socket, epoch: int) -> None:
        self.sockets = (downstream, upstream)
        self.epoch = epoch  # the proxy's cut count when it was opened
        self._closed = False
        self._lock = threading.Lock()

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for s in self.sockets:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)  # wakes the pump blocked in recv
            s.close()


class LinkProxy:
    """Forward ``127.0.0.1:<port>`` to ``target``; :meth:`cut` and :meth:`restore` the link."""

    def __init__(self, target: tuple[str, int], host: str = "127.0.0.1", port: int = 0) -> None:
        self.target = target
        self.host = host
        self._lock = threading.Lock()
        self._up = threading.Event()
        self._closed = threading.Event()
        self._epoch = 0
        self._connections: list[_Connection] = []
        self.accepted = 0      # connections forwarded so far
        self.refused = 0       # connections closed because the target was unreachable
        self.dropped_bytes = 0  # bytes discarded while the link was cut
        self._listener = self._listen(port)
        self.port = int(self._listener.getsockname()[1])
        self._up.set()
        self._acceptor = threading.Thread(target=self._accept_loop, name="linkproxy-accept",
                                          daemon=True)
        self._acceptor.start()

    @property
    def endpoint(self) -> str:
        """The Zenoh endpoint clients connect to instead of the target."""
        return f"tcp/{self.host}:{self.port}"

    @property
    def is_up(self) -> bool:
        return self._up.is_set()

    def _listen(self, port: int) -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((self.host, port))
        s.listen(64)
        s.settimeout(_ACCEPT_POLL_S)
        return s

    # --- link control ---

    def cut(self, reset: bool = False) -> None:
        """Take the link down: blackhole open connections (``reset``: close them), refuse new."""
        with self._lock:
            if not self._up.is_set():
                return
            self._up.clear()
            self._epoch += 1
            listener, self._listener = self._listener, None
            doomed = list(self._connections) if reset else []
            if reset:
                self._connections.clear()
        if listener is not None:
            listener.close()
        for c in doomed:
            c.close()
        log.info("link %s -> %s:%d cut%s", self.endpoint, *self.target,
                 " (reset)" if reset else "")

    def restore(self) -> None:
        """Bring the link back: close what lived through the cut, accept connections again."""
        with self._lock:
            if self._up.is_set() or self._closed.is_set():
                return
            stale, self._connections = self._connections, []
        for c in stale:
            c.close()
        listener = self._listen(self.port)
        with self._lock:
            self._listener = listener
            self._up.set()
        log.info("link %s -> %s:%d restored", self.endpoint, *self.target)

    def close(self) -> None:
        """Stop accepting and close every connection (idempotent)."""
        self._closed.set()
        with self._lock:
            listener, self._listener = self._listener, None
            conns, self._connections = self._connections, []
            self._up.set()  # release the acceptor if it waits for a restore
        if listener is not None:
            listener.close()
        for c in conns:
            c.close()
        self._acceptor.join(2.0)

    def __enter__(self) -> LinkProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- forwarding ---

    def _accept_loop(self) -> None:
        while not self._closed.is_set():
            self._up.wait()
            with self._lock:
                listener = self._listener
            if listener is None:
                if not self._closed.is_set():
                    self._up.wait(_ACCEPT_POLL_S)  # cut between the wait and the lock
                continue
            try:
                downstream, _ = listener.accept()
            except TimeoutError:
                continue
            except OSError:  # closed by cut() or close()
                continue
            self._open(downstream)

    def _open(self, downstream: socket.socket) -> None:
        downstream.settimeout(None)
        try:
            upstream = socket.create_connection(self.target, timeout=2.0)
        except OSError:
            self.refused += 1
            downstream.close()
            return
        upstream.settimeout(None)
        for s in (downstream, upstream):
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            if not self._up.is_set() or self._closed.is_set():
                conn = None
            else:
                conn = _Connection(downstream, upstream, self._epoch)
                self._connections.append(conn)
                self.accepted += 1
        if conn is None:  # cut while connecting: this connection never existed
            downstream.close()
            upstream.close()
            return
        for src, dst in ((downstream, upstream), (upstream, downstream)):
            threading.Thread(target=self._pump, args=(conn, src, dst), name="linkproxy-pump",
                             daemon=True).start()

    def _live(self, conn: _Connection) -> bool:
        return self._up.is_set() and conn.epoch == self._epoch

    def _pump(self, conn: _Connection, src: socket.socket, dst: socket.socket) -> None:
        while True:
            try:
                data = src.recv(_CHUNK)
            except OSError:
                data = b""
            if not data:
                if self._live(conn):
                    conn.close()  # an ordinary close travels through a live link
                # through a dead link it does not: the other side keeps its half open
                return
            if not self._live(conn):
                self.dropped_bytes += len(data)
                continue
            try:
                dst.sendall(data)
            except OSError:
                conn.close()
                return
