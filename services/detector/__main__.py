"""``python -m services.detector``: the detector service without the ``handkse`` CLI entry.

Same arguments as ``handkse detector``; ``python -m services.detector.camera`` and
``python -m services.detector.models prepare`` are the other two commands.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable

from services.common.bus import add_zenoh_arguments
from services.common.keys import check_rig


def standalone_parser(prog: str, doc: str, add_arguments: Callable[[argparse.ArgumentParser], None]
                      ) -> argparse.ArgumentParser:
    """A parser with the arguments every handkse command takes, plus the command's own."""
    parser = argparse.ArgumentParser(prog=prog, description=doc.strip().splitlines()[0])
    add_zenoh_arguments(parser)
    parser.add_argument("--rig", default="default", type=check_rig)
    parser.add_argument("--config", metavar="FILE", help="handkse TOML config file")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        dest="overrides", help="override one config value (repeatable)")
    parser.add_argument("--log-level", default="INFO",
                        choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    add_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    from services.detector import service

    parser = standalone_parser("python -m services.detector", service.__doc__ or "",
                               service.add_arguments)
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    return service.main(args)


if __name__ == "__main__":
    sys.exit(main())
