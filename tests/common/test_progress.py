"""Progress of long jobs: plain lines in a log, one redrawn line on a terminal."""

from __future__ import annotations

import io

from services.common.progress import Progress


def test_plain_lines_when_not_a_terminal() -> None:
    out = io.StringIO()
    progress = Progress(3, stream=out, tty=False)
    progress.step("downloading")
    progress.note("  12 MB")
    progress.step("converting a")
    progress.step("converting b")
    progress.step("one too many")  # counted as the last step, not past it
    progress.done("ready")
    lines = out.getvalue().splitlines()
    assert [line.split(" (")[0] for line in lines] == [
        "[1/3] downloading", "  12 MB", "[2/3] converting a", "[3/3] converting b",
        "[3/3] one too many", "ready"]
    assert "\r" not in out.getvalue() and "\033" not in out.getvalue()


def test_a_terminal_gets_one_redrawn_line_with_a_bar_and_what_is_left() -> None:
    out = io.StringIO()
    progress = Progress(4, stream=out, tty=True)
    progress.step("converting a")
    progress.step("converting b")
    text = out.getvalue()
    assert text.count("\r\033[K") == 2 and "\n" not in text
    assert "[2/4] #####---------------  25%  converting b" in text
    progress.note("a result")  # ends the redrawn line first
    progress.done("ready")
    tail = out.getvalue()[len(text):]
    assert tail.startswith("\na result\n")
    assert tail.endswith("ready\n")
