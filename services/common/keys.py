"""Key expressions of the wire protocol (docs/protocol.md), built from a rig name in one place."""

from __future__ import annotations

import re
from dataclasses import dataclass

PREFIX = "handkse"
SERVICES = ("camera", "detector", "tracker", "kinematics", "robot_bridge", "replay", "recorder", "router",
            "view")
_RIG_NAME = re.compile(r"^[A-Za-z0-9_-]+$")


def check_rig(rig: str) -> str:
    """Return ``rig`` if it is a valid single key chunk (letters, digits, ``_``, ``-``)."""
    if not _RIG_NAME.match(rig):
        raise ValueError(f"rig name {rig!r} must be letters, digits, '_' or '-' only")
    return rig


@dataclass(frozen=True)
class Keys:
    """All key expressions of one rig (``handkse/{rig}/...``)."""

    rig: str = "default"

    def __post_init__(self) -> None:
        check_rig(self.rig)

    @property
    def root(self) -> str:
        return f"{PREFIX}/{self.rig}"

    @property
    def camera_rgbd(self) -> str:
        return f"{self.root}/camera/rgbd"

    @property
    def hand_landmarks(self) -> str:
        return f"{self.root}/hand/landmarks"

    @property
    def hand_body(self) -> str:
        return f"{self.root}/hand/body"

    @property
    def kinematics_model(self) -> str:
        return f"{self.root}/kinematics/model"

    @property
    def kinematics_models(self) -> str:
        """Every contact phase's model of the current demonstration (``KinematicModelList``)."""
        return f"{self.root}/kinematics/models"

    @property
    def robot_state(self) -> str:
        return f"{self.root}/robot/state"

    @property
    def robot_body(self) -> str:
        """The robot's grasp pose as a HandBody (docs/protocol.md#robotbody)."""
        return f"{self.root}/robot/body"

    @property
    def robot_articulate(self) -> str:
        return f"{self.root}/robot/articulate"

    @property
    def all(self) -> str:
        """Every key of this rig (for recording)."""
        return f"{self.root}/**"

    def reset(self, service: str) -> str:
        return f"{self.root}/{service}/reset"

    def stats(self, service: str) -> str:
        return f"{self.root}/{service}/stats"

    def alive(self, service: str) -> str:
        return f"{self.root}/alive/{service}"

    def session(self, service: str, zid: str) -> str:
        """Liveliness token naming the Zenoh session (id ``zid``) that runs ``service``."""
        return f"{self.root}/alive/{service}/{zid}"

    def sessions(self, service: str) -> str:
        """Every session token of ``service`` (normally one)."""
        return f"{self.root}/alive/{service}/*"

    @property
    def alive_all(self) -> str:
        return f"{self.root}/alive/*"


def remap_rig(key: str, rig: str) -> str:
    """Replace the rig chunk of a ``handkse/{rig}/...`` key; other keys pass unchanged."""
    parts = key.split("/", 2)
    if len(parts) == 3 and parts[0] == PREFIX:
        return f"{PREFIX}/{check_rig(rig)}/{parts[2]}"
    return key
