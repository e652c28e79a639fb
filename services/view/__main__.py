"""``python -m services.view``: the live 3-D view, with the arguments of ``handkse view``."""

from __future__ import annotations

import sys

from services.common.entry import run_service
from services.view import service

if __name__ == "__main__":
    sys.exit(run_service("services.view", service.__doc__ or "", service.main,
                         getattr(service, "add_arguments", None)))
