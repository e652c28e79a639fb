"""``python -m services.detector``: the detector service, with the arguments of ``handkse detector``."""

from __future__ import annotations

import sys

from services.common.entry import run_service
from services.detector import service

if __name__ == "__main__":
    sys.exit(run_service("services.detector", service.__doc__ or "", service.main,
                         getattr(service, "add_arguments", None)))
