"""Logging set-up for the command line (and for scripts that want the same output).

Modules log to their own `logging.getLogger(__name__)`; nothing configures logging at
import. `configure(level)` is called once by the CLI (`-v`, `--log-level`).
"""

from __future__ import annotations

import logging
import sys
from typing import TextIO

LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
# Libraries that are chatty at INFO/WARNING about things labrunner reports itself
# (pymodbus logs every failed connection attempt that the driver retries).
_QUIET_LIBRARIES = ("pymodbus", "transitions", "matplotlib", "PIL")


class _CurrentStderr(logging.StreamHandler):
    """Writes to whatever sys.stderr is when a record is emitted, not when configured: a daemon thread
    of a simulated lab may log after the stream it started with was replaced and closed (a test's
    captured stderr), which a plain StreamHandler reports as a logging error with a traceback."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, _value: TextIO) -> None:
        pass  # StreamHandler.__init__ and setStream assign it; the current sys.stderr always wins


def configure(level: str | int = "WARNING", stream: TextIO | None = None) -> None:
    """Log labrunner's records at `level` to stderr; third-party libraries only from WARNING
    (or from DEBUG when level is DEBUG, to see pymodbus' own wire traffic)."""
    numeric = logging.getLevelName(level.upper()) if isinstance(level, str) else int(level)
    if not isinstance(numeric, int):
        raise ValueError(f"unknown log level {level!r}; expected one of {', '.join(LEVELS)}")
    handler: logging.Handler = logging.StreamHandler(stream) if stream is not None else _CurrentStderr()
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
