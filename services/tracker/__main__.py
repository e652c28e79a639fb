"""``python -m services.tracker``: the tracker service, with the arguments of ``handkse tracker``."""

from __future__ import annotations

import sys

from services.common.entry import run_service
from services.tracker import service

if __name__ == "__main__":
    sys.exit(run_service("services.tracker", service.__doc__ or "", service.main,
                         getattr(service, "add_arguments", None)))
