"""Progress of a long job: a tqdm bar on a terminal, plain lines in a log.

A job has ``total`` units. :meth:`Progress.step` says a unit starts (sequential work: downloads,
conversions), :meth:`Progress.advance` says one finished (parallel work: evaluations coming back
from a process pool, in any order). On a terminal this is one tqdm bar,
``[3/9] ######--------------  33%  00:12<00:24  converting palm_lite``: units done, elapsed and
remaining time, and what is being done. In a log (CI, a pipe) tqdm would redraw its bar with
carriage returns, so there every call is one plain line instead,
``[3/9] converting palm_lite (12 s, about 24 s left)``: nothing is redrawn and nothing is lost.
Notes that are not units (a result, a warning) are lines of their own in both cases.

tqdm rather than our own drawing: it already sizes the bar to the terminal, estimates the time
left and keeps the bar below lines written while it runs.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import time
from collections.abc import Iterator
from types import TracebackType
from typing import TextIO

from tqdm import tqdm

# Fixed bar width, so the bar does not jump when the description changes length.
BAR_FORMAT = "[{n_fmt}/{total_fmt}] {bar:20} {percentage:3.0f}%  {elapsed}<{remaining}  {desc}"


class Progress:
    """``total`` units of a job, shown on ``stream`` (default stdout).

    ``tty`` None = whether ``stream`` is a terminal. ``total`` may be set later (e.g. once the
    job knows how many steps it has). Use as a context manager, or call :meth:`done` or
    :meth:`close`, so a terminal's bar is finished before anything else is printed.
    """

    def __init__(self, total: int, stream: TextIO | None = None, tty: bool | None = None) -> None:
        self.stream = stream or sys.stdout
        self.tty = _isatty(self.stream) if tty is None else tty
        self.current = 0
        self._total = max(int(total), 1)
        self._t0 = time.monotonic()
        self._bar: tqdm | None = None  # drawn at the first unit, so a job with none shows none

    @property
    def total(self) -> int:
        return self._total

    @total.setter
    def total(self, value: int) -> None:
        self._total = max(int(value), 1)
        if self._bar is not None:
            self._bar.total = self._total
            self._bar.refresh()

    def step(self, text: str) -> None:
        """The next unit starts (the ones before it are done)."""
        self.current = min(self.current + 1, self._total)
        self._show(self.current - 1, text)

    def advance(self, text: str) -> None:
        """One more unit is done; ``text`` says which (and its result)."""
        self.current = min(self.current + 1, self._total)
        self._show(self.current, text)

    def note(self, text: str) -> None:
        """A line of its own (above the bar on a terminal)."""
        if self._bar is not None:
            for line in text.split("\n"):  # tqdm.write keeps the bar below one line at a time
                tqdm.write(line, file=self.stream)
        else:
            self.stream.write(text + "\n")
            self.stream.flush()

    def done(self, text: str) -> None:
        """The job is finished: the bar (if any) is completed and ``text`` printed below it."""
        if self._bar is not None:
            self._bar.n = self._total
            self._bar.refresh()
        self.close()
        self.note(text)

    def close(self) -> None:
        """Finish the bar where it stands (e.g. when the job failed)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    @contextlib.contextmanager
    def redirect_stdout(self) -> Iterator[None]:
        """Within the block, lines printed to ``sys.stdout`` go above the bar, not into it."""
        if self._bar is None:
            yield
            return
        writer = _LinesAbove(self)
        with contextlib.redirect_stdout(writer):
            try:
                yield
            finally:
                writer.flush_partial()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def _show(self, finished: int, text: str) -> None:
        if self.tty:
            if self._bar is None:
                # mininterval 0: units are seconds apart, so every one is drawn; smoothing 0:
                # the time left from the mean rate, as in the plain lines.
                columns, lines = _terminal_size(self.stream)
                self._bar = tqdm(total=self._total, file=self.stream, bar_format=BAR_FORMAT,
                                 dynamic_ncols=columns > 0, ncols=None if columns > 0 else 100,
                                 nrows=None if lines > 0 else 24, mininterval=0, miniters=1,
                                 smoothing=0, ascii=" #", leave=True)
                self._bar.start_t -= time.monotonic() - self._t0  # the job began before the bar
            self._bar.n = finished
            self._bar.set_description_str(text, refresh=True)
            return
        elapsed = time.monotonic() - self._t0
        timing = f"{elapsed:.0f} s"
        if 0 < finished < self._total:
            timing += f", about {elapsed / finished * (self._total - finished):.0f} s left"
        self.stream.write(f"[{self.current}/{self._total}] {text} ({timing})\n")
        self.stream.flush()


class _LinesAbove(io.TextIOBase):
    """A text stream that hands each complete line to :meth:`Progress.note`."""

    def __init__(self, progress: Progress) -> None:
        self._progress = progress
        self._partial = ""

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        lines = (self._partial + text).split("\n")
        self._partial = lines.pop()
        for line in lines:
            self._progress.note(line)
        return len(text)

    def flush_partial(self) -> None:
        if self._partial:
            self._progress.note(self._partial)
            self._partial = ""


def _terminal_size(stream: TextIO) -> tuple[int, int]:
    """(columns, lines) of the terminal behind ``stream``; 0 where unknown. A pseudo-terminal
    nobody sized reports 0 x 0, and tqdm would then trim or hide the bar."""
    try:
        size = os.get_terminal_size(stream.fileno())
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        return 0, 0
    return size.columns, size.lines


def _isatty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False
