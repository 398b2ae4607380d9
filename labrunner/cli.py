"""labrunner runs thermal-calibration campaigns of MEMS IMUs (a thermal chamber and a rate table, or
their simulation for a dry run), stores every sample, and fits and diagnoses the IMU's error models."""

from __future__ import annotations

import argparse
import errno
import importlib
import io
import logging
import os
import re
import sys
import textwrap
from collections.abc import Iterator, Sequence

from labrunner import __version__
from labrunner.errors import UserError
from labrunner.logs import LEVELS, configure

# Modules with `register(subparsers)`; each sets `func(args) -> int` on its parser. They import argparse-level
# modules only; each handler imports what its command needs when it runs, so `labrunner --help`, `status` or
# `list` do not load scipy, pandas, matplotlib or the sims (tests/test_startup_imports.py keeps it so).
COMMAND_MODULES = (
    "labrunner.commands.campaign",  # run, resume, status, abort, export
    "labrunner.commands.listing",  # list
    "labrunner.commands.sim",  # sim serve
    "labrunner.commands.check",  # check
    "labrunner.commands.fit",  # fit (labrunner.calibration.command runs it)
    "labrunner.commands.compensate",  # compensate
    "labrunner.commands.diagnose",  # diagnose (labrunner.discrepancy.command runs it)
    "labrunner.commands.report",  # report
)


# A reader that closes the output early (`labrunner export DB --csv - | head`) ends the command quietly
# with the status a Unix tool killed by SIGPIPE reports (128 + 13), so `set -o pipefail` scripts see
# a cut-short output as they do for `cat` or `grep`. SIGPIPE itself stays ignored (Python's default):
# dying on it in the middle of a campaign would skip the safe stop.
EXIT_BROKEN_PIPE = 141
EXIT_BUG = 1  # "failed", as for a run that failed

log = logging.getLogger(__name__)

EPILOG = """\
examples:
  labrunner check quick                              # the plan of the shipped quick procedure
  labrunner run quick --sim --db quick.db            # a dry run against the simulated lab
  labrunner status quick.db
  labrunner fit quick.db --out fit/ --json fit.json

exit codes: 0 done, 3 paused, 4 aborted (lab in safe state), 1 failed, 2 bad input, 130 interrupted,
141 output closed early (e.g. by `| head`). `labrunner COMMAND --help` explains each command, with an example."""


class HelpFormatter(argparse.HelpFormatter):
    """Wraps prose paragraphs to the terminal but keeps indented blocks (the examples) as written,
    and shows every meaningful default: "(default: ...)" unless the help already says it."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        paragraphs = re.split(r"\n\s*\n", text.strip("\n"))
        out = []
        for para in paragraphs:
            if "\n " in para or para.startswith(" "):
                out.append("\n".join(indent + line for line in para.splitlines()))
            else:
                out.append(textwrap.fill(" ".join(para.split()), width, initial_indent=indent,
                                         subsequent_indent=indent))
        return "\n\n".join(out)

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        # A flag (no value: store_true, -v counts) has nothing to show; 0 is a default worth showing.
        if "default" in text or action.required or action.nargs == 0 or action.default is None \
                or action.default is argparse.SUPPRESS:
            return text
        if action.option_strings or action.nargs in ("?", "*"):
            return f"{text} (default: %(default)s)"
        return text


def subparsers(parser: argparse.ArgumentParser) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """Every sub-command's parser, depth first, named as typed (`run`, `sim`, `sim serve`)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                full = f"{parser.prog.removeprefix('labrunner').strip()} {name}".strip()
                yield full, sub
                yield from subparsers(sub)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="labrunner", description=__doc__, epilog=EPILOG,
                                     formatter_class=HelpFormatter)
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
    for _, p in subparsers(parser):  # one look for every command, registered by whichever module
        p.formatter_class = HelpFormatter
    return parser


def log_level(args: argparse.Namespace) -> str:
    """--log-level, else -v (INFO) / -vv (DEBUG), else WARNING."""
    if args.log_level:
        return str(args.log_level)
    return {0: "WARNING", 1: "INFO"}.get(args.verbose, "DEBUG")


class _ClosedStream(io.TextIOBase):
    """What stdout is when the shell closed it (`>&-`; Python then sets sys.stdout to None): writing to it is a
    closed pipe (nothing printed, EXIT_BROKEN_PIPE), and a command that writes nothing runs as usual."""

    def writable(self) -> bool:
        return True

    def write(self, s: str) -> int:
        raise BrokenPipeError(errno.EPIPE, "standard output is closed")

    @property
    def buffer(self) -> io.TextIOBase:
        return self


def main(argv: Sequence[str] | None = None) -> int:
    """The command line; returns the exit code (README, "Commands"). Never raises but SystemExit."""
    if sys.stdout is None:
        sys.stdout = _ClosedStream()
    try:
        try:
            return _main(argv)
        finally:
            sys.stdout.flush()  # a closed pipe shows here, not as a message at interpreter exit
    except BrokenPipeError:
        # The reader is gone: say nothing more, and let nothing flush into the dead pipe later.
        devnull = os.open(os.devnull, os.O_WRONLY)
        for stream in (sys.stdout, sys.stderr):
            try:
                os.dup2(devnull, stream.fileno())
            except (OSError, ValueError):  # a stream replaced by one without a file descriptor
                pass
        return EXIT_BROKEN_PIPE


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure(log_level(args))
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    command = " ".join(["labrunner", args.command] + ([args.sim_command] if getattr(args, "sim_command", None) else []))
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"{command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"{command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        raise
    except OSError as exc:
        if exc.filename is None or exc.strerror is None:
            return _bug(command, exc)
        # A path the user gave that cannot be read or written (a directory, a missing folder, no
        # permission): bad input, named.
        log.debug("%s: %s", command, exc, exc_info=True)
        where = f"{exc.filename} -> {exc.filename2}" if exc.filename2 else str(exc.filename)
        print(f"{command}: error: {where}: {exc.strerror[:1].lower()}{exc.strerror[1:]}", file=sys.stderr)
        return 2
    except Exception as exc:  # the last line of defence: one line, the traceback at DEBUG
        return _bug(command, exc)


def _bug(command: str, exc: BaseException) -> int:
    log.debug("%s: unexpected error", command, exc_info=exc)
    print(f"{command}: error: {type(exc).__name__}: {exc}; this is a bug: please report it with "
          "`-v --log-level DEBUG` output", file=sys.stderr)
    return EXIT_BUG


if __name__ == "__main__":
    sys.exit(main())
