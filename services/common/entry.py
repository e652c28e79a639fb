"""``python -m services.<service>``: run one service without the ``handkse`` command.

Every service package's ``__main__.py`` is one call of :func:`run_service`, so a service can be
started with nothing but its package (``python -m services.tracker -e tcp/...``) and takes the
same arguments as ``handkse <service>``.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable

from services.common.bus import add_zenoh_arguments
from services.common.keys import check_rig

AddArguments = Callable[[argparse.ArgumentParser], None]
Main = Callable[[argparse.Namespace], int]


def standalone_parser(prog: str, doc: str, add_arguments: AddArguments | None
                      ) -> argparse.ArgumentParser:
    """A parser with the arguments every handkse command takes, plus the service's own."""
    parser = argparse.ArgumentParser(prog=prog, description=doc.strip().splitlines()[0])
    add_zenoh_arguments(parser)
    parser.add_argument("--rig", default="default", type=check_rig)
    parser.add_argument("--config", metavar="FILE", help="handkse TOML config file")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        dest="overrides", help="override one config value (repeatable)")
    parser.add_argument("--log-level", default="INFO",
                        choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    if add_arguments is not None:
        add_arguments(parser)
    return parser


def run_service(package: str, doc: str, main: Main, add_arguments: AddArguments | None = None,
                argv: list[str] | None = None) -> int:
    """Parse ``argv`` (default: the command line) and run the service's ``main``."""
    parser = standalone_parser(f"python -m {package}", doc, add_arguments)
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    return main(args)

