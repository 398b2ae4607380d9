"""The fault policy: what an instrument failure, a lossy record or a fault pause leads to.

The drivers retry a failed exchange a bounded number of times; what reaches the sequencer has
used those up. The procedure's `faults` section then says whether the campaign pauses (to be
resumed by the operator, or automatically in a dry run) or aborts to the safe stop.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

from labrunner.procedure import Faults

log = logging.getLogger(__name__)

Action = Literal["pause", "abort", "fail"]
RecordVerdict = Literal["keep", "record_again", "give_up"]


class FaultPolicy:
    """Decisions of the procedure's `faults` section."""

    def __init__(self, faults: Faults) -> None:
        self.faults = faults

    def on_instrument_error(self, *, hard: bool, in_safe_stop: bool) -> Action:
        """After the bounded retries. `hard`: refused by a limit (retrying cannot help)."""
        if in_safe_stop:
            return "fail"  # the safe stop itself failed: nothing left to fall back on
        if hard or self.faults.policy == "abort":
            return "abort"
        return "pause"

    def on_record(self, dropped: int, attempts: int) -> RecordVerdict:
        """A record lost `dropped` frames on its `attempts`-th attempt at the step."""
        if dropped <= self.faults.max_dropped_frames:
            return "keep"
        if attempts > self.faults.max_rerecords:
            return "give_up"  # the loss is not transient: let the fault policy decide
        return "record_again"


@dataclass
class AutoResume:
    """Dry runs with injected faults: resume a fault pause after `delay_s` of clock time, as an
    operator would, at most `max_resumes` times. `delay_s=None`: a pause stays a pause."""

    delay_s: float | None
    max_resumes: int = 200
    resumes: int = 0
    armed: bool = False  # the current pause was caused by a fault (an operator's pause is not resumed)

    def fault_paused(self) -> None:
        self.armed = True

    def due(self) -> bool:
        return self.armed and self.delay_s is not None and self.resumes < self.max_resumes

    def take(self) -> int:
        """Count one auto-resume; returns its number."""
        self.resumes += 1
        self.armed = False
        log.info("auto-resume %d after a fault pause", self.resumes)
        return self.resumes
