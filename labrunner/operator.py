"""The operator: at the terminal, a remount prompt that only a fresh Enter confirms; in a dry run, simulated.

A stray Enter typed ahead (while the chamber was still ramping to room temperature, or an
extra one after the previous prompt) must not confirm the next remount. So before each
prompt the input already waiting is discarded — `termios.tcflush(TCIFLUSH)` on a terminal,
and on a pipe or file whatever can be read without blocking — and the answer is read from
the file descriptor itself (`os.read`), so nothing waits unseen in Python's stdin buffer
either. Whether the mount is right is then judged by gravity (`labrunner.runner.mount_check`).
"""

from __future__ import annotations

import logging
import os
import select
import sys
import termios
from typing import IO, TYPE_CHECKING, Any

from labrunner.clock import Clock
from labrunner.yaml_config import ConfigError

if TYPE_CHECKING:  # the sims are imported only when a dry run is built
    from labrunner.sims.lab import SimLab

log = logging.getLogger(__name__)


def discard_typeahead(fd: int) -> int:
    """Throw away input waiting on `fd`; returns the bytes discarded (-1: a terminal's queue, not counted)."""
    if os.isatty(fd):
        termios.tcflush(fd, termios.TCIFLUSH)
        return -1
    dropped = 0
    while select.select([fd], [], [], 0)[0]:
        data = os.read(fd, 4096)
        if not data:  # end of file: nothing more will come, the prompt's read says so
            break
        dropped += len(data)
    return dropped


def read_line(fd: int) -> bytes | None:
    """One line from `fd`, unbuffered (None at end of file before a newline)."""
    got = bytearray()
    while b"\n" not in got:
        chunk = os.read(fd, 1)  # one byte at a time: nothing past the newline is taken from the next prompt
        if not chunk:
            return None
        got += chunk
    return bytes(got)


class ConsoleOperator:
    """A person at the terminal: prints the prompt and waits for a fresh Enter."""

    def __init__(self, stream: Any = None, stdin: IO[Any] | int | None = None) -> None:
        self.stream = stream or sys.stderr
        self._stdin = stdin

    def _fd(self, orientation: str) -> int:
        source = self._stdin if self._stdin is not None else sys.stdin
        try:
            return source if isinstance(source, int) else source.fileno()
        except (AttributeError, ValueError, OSError):  # no stdin at all (a service), or a closed one
            raise ConfigError([f"operator prompt for {orientation}: no terminal to acknowledge it (no stdin); "
                               "run interactively or use --sim for a dry run"]) from None

    def remount(self, orientation: str, prompt: str) -> None:
        fd = self._fd(orientation)
        dropped = discard_typeahead(fd)
        if dropped:
            log.info("operator prompt for %s: discarded %d byte(s) typed ahead", orientation, dropped)
        print(f"\n>>> OPERATOR: {prompt}\n>>> Press Enter when the IMU is mounted {orientation} and powered on.",
              file=self.stream, flush=True)
        if read_line(fd) is None:
            raise ConfigError([f"operator prompt for {orientation}: no terminal to acknowledge it (stdin closed); "
                               "run interactively or use --sim for a dry run"])


class SimOperator:
    """The dry run's operator: acknowledges at once and remounts the simulated IMU.

    The sim configuration's `operator:` section (`SimOperatorParams`) can make the first
    `wrong_mounts` remounts of a session go wrong, to rehearse the mount check: the IMU is turned
    to `mounts_as`, or (without it) the remount is skipped and the IMU stays as it was.
    """

    def __init__(self, sim: SimLab, clock: Clock, remount_s: float = 300.0) -> None:
        self.sim = sim
        self.clock = clock
        self.remount_s = remount_s
        self.wrong_left = sim.config.operator.wrong_mounts
        self.mounts_as = sim.config.operator.mounts_as

    def remount(self, orientation: str, prompt: str) -> None:
        self.sim.power_off()
        self.clock.sleep(self.remount_s)  # the time a person takes to open the door and turn the IMU
        if self.wrong_left > 0:
            self.wrong_left -= 1
            actual = self.mounts_as or self.sim.mounted_orientation
            log.info("simulated operator: asked for %s, mounts the IMU %s (%d wrong mount(s) left)", orientation,
                     actual, self.wrong_left)
        else:
            actual = orientation
            log.info("simulated operator: remounting the IMU %s", orientation)
        self.sim.remount(actual)


__all__ = ["ConsoleOperator", "SimOperator", "discard_typeahead", "read_line"]
