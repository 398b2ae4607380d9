"""Logging set-up for the command line (and for scripts that want the same output).

Modules log to their own `logging.getLogger(__name__)`; nothing configures logging at
import. `configure(level)` is called once by the CLI (`-v`, `--log-level`).
"""

from __future__ import annotations

import logging
import sys

LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
# Libraries that are chatty at INFO/WARNING about things labrunner reports itself
# (pymodbus logs every failed connection attempt that the driver retries).
_QUIET_LIBRARIES = ("pymodbus", "transitions", "matplotlib", "PIL")


def configure(level: str | int = "WARNING", stream: object = None) -> None:
    """Log labrunner's records at `level` to stderr; third-party libraries only from WARNING
    (or from DEBUG when level is DEBUG, to see pymodbus' own wire traffic)."""
    numeric = logging.getLevelName(level.upper()) if isinstance(level, str) else int(level)
    if not isinstance(numeric, int):
        raise ValueError(f"unknown log level {level!r}; expected one of {', '.join(LEVELS)}")
    handler = logging.StreamHandler(stream or sys.stderr)  # type: ignore[arg-type]
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s", "%H:%M:%S"))
    root = logging.getLogger("labrunner")
    root.handlers[:] = [handler]
    root.setLevel(numeric)
    root.propagate = False
    for name in _QUIET_LIBRARIES:
        lib = logging.getLogger(name)
        # pymodbus logs an ERROR for every refused connect and timed-out request, each of which the
        # chamber driver retries and reports itself: below DEBUG only its CRITICAL records are news.
        quiet = logging.CRITICAL if name == "pymodbus" else max(numeric, logging.ERROR)
        lib.setLevel(logging.DEBUG if numeric <= logging.DEBUG else quiet)
        lib.handlers[:] = [handler]
        lib.propagate = False
