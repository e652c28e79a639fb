"""``python -m services.kinematics``: the kinematics service, with the arguments of ``handkse kinematics``."""

from __future__ import annotations

import sys

from services.common.entry import run_service
from services.kinematics import service

if __name__ == "__main__":
    sys.exit(run_service("services.kinematics", service.__doc__ or "", service.main,
                         getattr(service, "add_arguments", None)))
