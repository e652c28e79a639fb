"""``python -m services.robot_bridge``: the robot bridge, with the arguments of ``handkse robot-bridge``."""

from __future__ import annotations

import sys

from services.common.entry import run_service
from services.robot_bridge import service

if __name__ == "__main__":
    sys.exit(run_service("services.robot_bridge", service.__doc__ or "", service.main,
                         getattr(service, "add_arguments", None)))
