"""What reaches a running campaign from outside, and what it counts for its summary.

Pause and abort requests come from signal handlers in the same process (Ctrl-C) or from
another process through the store's control table (`labrunner abort`, a pause request); the
heartbeat lets `labrunner status` tell a running campaign from a killed one.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from labrunner.clock import Clock
from labrunner.store import Store

log = logging.getLogger(__name__)

REQUEST_POLL_S = 0.5  # real seconds between looks at the store's control table
HEARTBEAT_S = 2.0  # real seconds between heartbeats


@dataclass
class Control:
    """Requests reaching the runner: from signal handlers (same process) or the store (another one)."""

    pause: bool = False
    abort: bool = False
    reason: str = ""

    def request_pause(self, reason: str) -> None:
        self.pause = True
        self.reason = reason

    def request_abort(self, reason: str) -> None:
        self.abort = True
        self.reason = reason


@dataclass
class RunStats:
    steps_recorded: int = 0
    steps_rerecorded: int = 0
    faults: int = 0
    recoveries: int = 0
    samples: int = 0
    started_wall: float = field(default_factory=time.time)


class StoreRequests:
    """Reads requests from the store into `control` and writes the heartbeat, both throttled in real
    time (a virtual clock may run hours of lab time in a second)."""

    def __init__(self, store: Store, campaign_id: int, clock: Clock, control: Control) -> None:
        self.store = store
        self.campaign_id = campaign_id
        self.clock = clock
        self.control = control
        self._last_check = 0.0
        self._last_heartbeat = 0.0

    def poll(self) -> None:
        now = time.monotonic()
        if now - self._last_check <= REQUEST_POLL_S:
            return
        self._last_check = now
        req = self.store.pending_request(self.campaign_id)
        if req == "abort":
            self.control.request_abort("abort requested by labrunner abort")
        elif req == "pause":
            self.control.request_pause("pause requested by labrunner")
        if req:
            log.info("campaign %d: %s requested through the store", self.campaign_id, req)
        if now - self._last_heartbeat > HEARTBEAT_S:
            self._last_heartbeat = now
            self.store.heartbeat(self.campaign_id, self.clock.now())
