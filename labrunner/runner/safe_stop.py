"""The one safe stop: table stopped, chamber to the remount temperature, retried until reached.

Used by the sequencer's safe_stop state and by `labrunner abort` when no process runs the
campaign, so both persist the same way against an instrument that does not answer.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from labrunner.clock import Clock
from labrunner.drivers.protocols import Chamber, RateTable

log = logging.getLogger(__name__)

SAFE_STOP_PERSIST_S = 600.0  # keep trying to reach the safe state this long (clock time) before giving up
SAFE_STOP_RETRY_S = 15.0


@dataclass
class SafeStopResult:
    reached: bool
    problems: list[str] = field(default_factory=list)  # one sentence per action that never succeeded
    attempts: int = 0


def safe_stop(table: RateTable, chamber: Chamber, remount_c: float, clock: Clock, *,
              persist_s: float = SAFE_STOP_PERSIST_S, retry_s: float = SAFE_STOP_RETRY_S,
              on_retry: Callable[[list[str]], None] | None = None, connect: bool = False) -> SafeStopResult:
    """Bring the lab to its safe state; each action is retried until it succeeds or persist_s runs out.

    `on_retry(problems)` is called before each retry (the sequencer logs it as an event).
    `connect=True` connects each instrument first (for `labrunner abort` with no process running).
    Never raises for an instrument failure: the result says what was not reached.
    """
    def stop_table() -> None:
        if connect:
            table.connect()
        table.stop()

    def park_chamber() -> None:
        if connect:
            chamber.connect()
        chamber.set_setpoint(remount_c)

    actions: dict[str, Callable[[], None]] = {
        "stop the table": stop_table,
        f"set the chamber to the remount temperature {remount_c:g} C": park_chamber,
    }
    problems: dict[str, str] = {}
    deadline = clock.now() + persist_s
    attempts = 0
    while True:
        attempts += 1
        for what, action in list(actions.items()):
            try:
                action()
                actions.pop(what)
                problems.pop(what, None)
            except Exception as exc:  # any failure of an instrument: keep trying the others
                problems[what] = f"could not {what}: {exc}"
                log.warning("safe stop: %s", problems[what])
        if not actions or clock.now() >= deadline:
            break
        if on_retry is not None:
            on_retry(list(problems.values()))
        clock.sleep(retry_s)
    return SafeStopResult(reached=not actions, problems=list(problems.values()), attempts=attempts)
