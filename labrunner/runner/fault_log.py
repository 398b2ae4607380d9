"""What the drivers report on the way: retries, link losses, and the instrument answering again.

A driver retries a failed exchange itself and tells the runner (`on_retry`); the IMU reader
tells it when its link is lost and restored (`on_event`). Each becomes an event row and a count;
an instrument that was retried and then answers is a recovery, noted at the next safe point.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from labrunner.drivers.errors import InstrumentError
from labrunner.runner.control import RunStats

log = logging.getLogger(__name__)

EventSink = Callable[..., None]  # event(kind, message, **detail)


class FaultLog:
    def __init__(self, stats: RunStats, event: EventSink, thread_event: EventSink | None = None) -> None:
        self.stats = stats
        self.event = event
        # The IMU reader's thread must not die of a store failure: its events go to a sink that
        # keeps them and leaves the failure to the sequencer (`runner.journal`).
        self.thread_event = thread_event or event
        self._retrying: dict[str, str] = {}  # instrument -> last retried error, until it answers again

    def attach(self, chamber: Any, table: Any, imu: Any) -> None:
        """Listen to the drivers that report retries (`on_retry`) and IMU link events (`on_event`);
        instruments without them (fakes, other drivers) are left alone."""
        for inst in (chamber, table):
            if hasattr(inst, "on_retry"):
                inst.on_retry = self.on_retry
        if hasattr(imu, "on_event"):
            imu.on_event = self.on_imu_event

    def on_retry(self, attempt: int, exc: InstrumentError) -> None:
        self.stats.faults += 1
        self._retrying[exc.instrument] = str(exc)
        self.event("fault", f"retry {attempt}: {exc}", instrument=exc.instrument)

    def on_imu_event(self, kind: str, message: str) -> None:
        # Called from the IMU reader thread; the store is safe to use from there.
        if kind == "imu_link_lost":
            self.stats.faults += 1
            self.thread_event("fault", message)
        else:
            self.stats.recoveries += 1
            self.thread_event("recovery", message)

    def note_recoveries(self) -> None:
        """At a safe point: every instrument retried since the last one has answered again."""
        for instrument in list(self._retrying):
            self._retrying.pop(instrument)
            self.stats.recoveries += 1
            self.event("recovery", f"{instrument} answers again")

    @property
    def retrying(self) -> bool:
        return bool(self._retrying)
