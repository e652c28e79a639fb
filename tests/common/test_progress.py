"""Progress of long jobs: plain lines in a log, a tqdm bar on a terminal."""

from __future__ import annotations

import fcntl
import io
import os
import pty
import struct
import subprocess
import sys
import termios
import textwrap
from pathlib import Path

import pytest

from services.common.progress import Progress

REPO = Path(__file__).resolve().parents[2]


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
    assert "s left)" in lines[2]  # one step done: the rest is estimated from it
    assert "left" not in lines[0]  # nothing done yet, nothing to estimate from


def test_finished_units_in_any_order_count_up() -> None:
    out = io.StringIO()
    with Progress(2, stream=out, tty=False) as progress:
        progress.advance("valve p3 s0: ours 3.2")
        progress.advance("key p3 s0: ours 27.8")
    lines = out.getvalue().splitlines()
    assert [line.split(" (")[0] for line in lines] == ["[1/2] valve p3 s0: ours 3.2",
                                                       "[2/2] key p3 s0: ours 27.8"]
    assert "left" in lines[0] and "left" not in lines[1]


def test_a_terminal_gets_a_redrawn_bar_with_what_is_left() -> None:
    out = io.StringIO()
    progress = Progress(4, stream=out, tty=True)
    progress.step("converting a")
    progress.step("converting b")
    text = out.getvalue()
    assert "\n" not in text and text.count("\r") >= 2  # one line, redrawn
    last = text.rsplit("\r", 1)[1]
    assert last.startswith("[1/4] #####") and " 25%" in last and last.endswith("converting b")
    assert "<" in last  # elapsed<remaining
    progress.note("a result")  # above the bar, the bar drawn again below it
    progress.done("ready")
    tail = out.getvalue()[len(text):]
    assert "a result\n" in tail
    assert "[4/4] " + "#" * 20 + " 100%" in tail
    assert tail.endswith("ready\n")


def test_printing_inside_a_job_goes_above_the_bar() -> None:
    out = io.StringIO()
    progress = Progress(2, stream=out, tty=True)
    progress.step("benchmark a")
    with progress.redirect_stdout():
        print("result of a:", 1)
        print("partial", end="")
    progress.done("all done")
    shown = _as_shown(out.getvalue())
    assert "result of a: 1" in shown and "partial" in shown  # lines of their own
    assert shown[-2:] == ["all done", ""]


def _as_shown(text: str) -> list[str]:
    """The lines a terminal ends up showing: each line's text after its last carriage return."""
    return [line.rsplit("\r", 1)[-1] for line in text.split("\n")]


SCRIPT = textwrap.dedent("""
    from services.common.progress import Progress
    with Progress(3) as p:
        for name in ("a", "b", "c"):
            p.step(f"working on {name}")
        p.done("finished")
""")


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO)}


def test_a_pipe_gets_plain_lines() -> None:
    piped = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                           env=_env(), timeout=60, check=True)
    assert [line.split(" (")[0] for line in piped.stdout.splitlines()] == [
        "[1/3] working on a", "[2/3] working on b", "[3/3] working on c", "finished"]
    assert "\r" not in piped.stdout


@pytest.mark.parametrize("columns", [100, 0])  # 0: a pseudo-terminal nobody gave a size
def test_a_real_terminal_gets_the_bar(columns: int) -> None:
    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24 if columns else 0,
                                                           columns, 0, 0))
    try:
        proc = subprocess.Popen([sys.executable, "-c", SCRIPT], stdout=follower,
                                stderr=subprocess.PIPE, env=_env())
        os.close(follower)
        follower = -1
        chunks = []
        while True:
            try:
                data = os.read(leader, 4096)
            except OSError:  # the terminal closed: the program ended
                break
            if not data:
                break
            chunks.append(data)
        assert proc.wait(timeout=60) == 0, proc.stderr.read() if proc.stderr else ""
    finally:
        os.close(leader)
        if follower >= 0:
            os.close(follower)
    shown = b"".join(chunks).decode()
    assert "\r" in shown and "working on c" in shown
    assert "[3/3] " + "#" * 20 + " 100%" in shown
    assert "finished" in shown
    assert "[1/3] working on a (" not in shown  # no plain lines on a terminal
