"""``python -m services.view``: the live 3-D view (same as ``handkse view``)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from services.common.bus import add_zenoh_arguments
from services.common.keys import check_rig
from services.view.service import add_arguments, main


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m services.view", description=__doc__)
    add_zenoh_arguments(p)
    p.add_argument("--rig", default="default", type=check_rig)
    p.add_argument("--config", metavar="FILE", type=Path)
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   dest="overrides")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    add_arguments(p)
    return p


if __name__ == "__main__":
    args = parser().parse_args()
    logging.basicConfig(level=args.log_level,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    sys.exit(main(args))
