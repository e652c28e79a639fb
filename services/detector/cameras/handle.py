"""Closing an SDK handle that another thread may be reading from."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

S = TypeVar("S", bound="HandleOwner")


class ReleaseOnce:
    """Releases an SDK handle exactly once, never while another thread reads from it.

    :meth:`close` may come from any thread: it releases at once when nobody reads, else the
    reading thread releases when it leaves :meth:`reading` (it sees ``closed`` within one read
    timeout). A reader that ends on its own (the end of a recording) releases too.
    """

    def __init__(self, release: Callable[[], None]) -> None:
        self.closed = threading.Event()
        self._release = release
        self._lock = threading.Lock()
        self._reading = False
        self._released = False

    @contextmanager
    def reading(self) -> Iterator[None]:
        with self._lock:
            self._reading = True
        try:
            yield
        finally:
            with self._lock:
                self._reading = False
            self._release_if_idle()

    def close(self) -> None:
        self.closed.set()
        self._release_if_idle()

    def _release_if_idle(self) -> None:
        with self._lock:
            if self._released or self._reading:
                return
            self._released = True
        self._release()


class HandleOwner:
    """A camera or recording source that owns one :class:`ReleaseOnce` handle (``_handle``, set
    by the subclass): ``close`` and the context manager."""

    _handle: ReleaseOnce

    def close(self) -> None:
        """Stop: release the device or file at once when idle, else within one short wait of
        the reading thread."""
        self._handle.close()

    def __enter__(self: S) -> S:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["HandleOwner", "ReleaseOnce"]
