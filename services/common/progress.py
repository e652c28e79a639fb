"""Progress of a long job in steps: a redrawn line on a terminal, plain lines otherwise.

On a terminal each step redraws one line, ``[3/9] ####------ 33%  converting palm_lite  12 s``,
and the line is finished when the job ends; in a log (CI, a pipe) each step is one plain line
``[3/9] converting palm_lite (12 s)``, so nothing is lost and nothing is redrawn. Notes that are
not steps (a result, a warning) are printed as their own lines in both cases.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

_BAR = 20


class Progress:
    """``total`` steps of a job; ``step(text)`` starts the next one, ``note(text)`` prints a line,
    ``done(text)`` ends the job. ``tty`` None = whether ``stream`` is a terminal."""

    def __init__(self, total: int, stream: TextIO | None = None, tty: bool | None = None) -> None:
        self.stream = stream or sys.stdout
        self.tty = self.stream.isatty() if tty is None else tty
        self.total = max(int(total), 1)
        self.current = 0
        self._t0 = time.monotonic()
        self._line_open = False

    def _elapsed(self) -> str:
        return f"{time.monotonic() - self._t0:.0f} s"

    def step(self, text: str) -> None:
        self.current = min(self.current + 1, self.total)
        counter = f"[{self.current}/{self.total}]"
        if self.tty:
            filled = round(_BAR * (self.current - 1) / self.total)
            percent = round(100 * (self.current - 1) / self.total)
            self.stream.write(f"\r\033[K{counter} {'#' * filled}{'-' * (_BAR - filled)} "
                              f"{percent:3d}%  {text}  {self._elapsed()}")
            self._line_open = True
        else:
            self.stream.write(f"{counter} {text} ({self._elapsed()})\n")
        self.stream.flush()

    def note(self, text: str) -> None:
        if self._line_open:
            self.stream.write("\n")
            self._line_open = False
        self.stream.write(text + "\n")
        self.stream.flush()

    def done(self, text: str) -> None:
        if self.tty and self._line_open:
            self.stream.write(f"\r\033[K[{self.total}/{self.total}] {'#' * _BAR} 100%  "
                              f"{self._elapsed()}\n")
            self._line_open = False
        self.note(text)
