"""Command-line value types that refuse a bad value with the rule it breaks.

Each is an argparse ``type=``: it returns the parsed value or raises
``argparse.ArgumentTypeError`` whose text states the rule and the value given, so the ``handkse``
parser can print one line such as ``handkse replay: --participant: must be 1..3, got 99``.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from services.common.keys import SERVICES, check_rig


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def _bounded(parse: Callable[[str], float], test: Callable[[float], bool], rule: str
             ) -> Callable[[str], float]:
    def check(text: str) -> float:
        value = parse(text)
        if not test(value):
            raise argparse.ArgumentTypeError(f"must be {rule}, got {text}")
        return value

    return check


non_negative_float = _bounded(_float, lambda v: v >= 0, ">= 0")
positive_float = _bounded(_float, lambda v: v > 0, "> 0")
non_negative_int: Callable[[str], int] = _bounded(_int, lambda v: v >= 0, ">= 0")  # type: ignore[assignment]
positive_int: Callable[[str], int] = _bounded(_int, lambda v: v > 0, "> 0")  # type: ignore[assignment]


def topic_list(text: str) -> tuple[str, ...]:
    """``"camera/rgbd,hand/landmarks"`` -> the topics (keys below the rig)."""
    topics = tuple(t.strip().strip("/") for t in text.split(","))
    if not all(topics):
        raise argparse.ArgumentTypeError(
            f"expected comma-separated topics such as camera/rgbd,hand/landmarks, got {text!r}")
    return topics


def rig_name(text: str) -> str:
    """A rig name: one key chunk of letters, digits, ``_`` and ``-``."""
    try:
        return check_rig(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a rig name: use letters, digits, '_' or '-' only") from None


def service_name(text: str) -> str:
    """A service as its liveliness token names it; ``robot-bridge`` (the command) is accepted
    for ``robot_bridge``."""
    name = text.replace("-", "_")
    if name not in SERVICES:
        raise argparse.ArgumentTypeError(f"unknown service {text!r}; known: {', '.join(SERVICES)}")
    return name


def object_name(text: str) -> str:
    """A synthetic object preset of any split (``key``, ``cabinet_door``, ...) or ``free``."""
    from services.synthetic.splits import FREE_OBJECT, preset

    if text == FREE_OBJECT:
        return text
    try:
        preset(text)
    except ValueError as exc:  # its message lists the known objects
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def participant_id(text: str) -> int:
    """A participant of the synthetic demonstrations (1..3 the paper's, 4..7 household)."""
    from services.synthetic.splits import PARTICIPANTS

    value = _int(text)
    if value not in PARTICIPANTS:
        raise argparse.ArgumentTypeError(
            f"must be {min(PARTICIPANTS)}..{max(PARTICIPANTS)}, got {text}")
    return value
