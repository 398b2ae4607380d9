"""labrunner runs thermal-calibration campaigns of MEMS IMUs (a thermal chamber and a rate table, or
their simulation for a dry run), stores every sample, and fits and diagnoses the IMU's error models."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from labrunner import __version__
from labrunner.errors import UserError
from labrunner.logs import LEVELS, configure

# Modules with `register(subparsers)`; each sets `func(args) -> int` on its parser.
COMMAND_MODULES = (
    "labrunner.commands.campaign",  # run, resume, status, abort, export
    "labrunner.commands.listing",  # list
    "labrunner.commands.sim",  # sim serve
    "labrunner.commands.check",  # check
    "labrunner.calibration.command",  # fit
    "labrunner.discrepancy.command",  # diagnose
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="labrunner", description=__doc__)
    parser.add_argument("--version", action="version", version=f"labrunner {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more on stderr: -v INFO, -vv DEBUG (wire traffic)")
    parser.add_argument("--log-level", type=str.upper, choices=LEVELS, default=None, metavar="LEVEL",
                        help=f"log level ({', '.join(LEVELS)}; default WARNING; overrides -v)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and name.startswith(exc.name):  # not written yet
                continue
            raise
        module.register(sub)
    return parser


def log_level(args: argparse.Namespace) -> str:
    """--log-level, else -v (INFO) / -vv (DEBUG), else WARNING."""
    if args.log_level:
        return str(args.log_level)
    return {0: "WARNING", 1: "INFO"}.get(args.verbose, "DEBUG")


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure(log_level(args))
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"labrunner {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"labrunner {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
