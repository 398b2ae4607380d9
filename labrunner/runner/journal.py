"""The campaign's events on their way to the store, held back while the lab is being made safe.

A safe stop must not depend on the store: the database may be what failed (disk full, lost
connection, read-only file). While the sequencer holds the journal (from the moment it leaves for
the safe stop) events are kept in memory, in order, with the wall time they happened; `flush`
writes them in one transaction once the lab is safe, and says whether it could.

A store failure met by another thread (the IMU reader logging a link event, a fault injected on a
clock listener) is not raised there: the event is kept and the failure is left for the sequencer,
which raises it at its next safe point (`raise_failure`).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from labrunner.store import Store, StoreError

log = logging.getLogger(__name__)


class Journal:
    def __init__(self, store: Store, campaign_id: int) -> None:
        self.store = store
        self.campaign_id = campaign_id
        self.held = False
        self.failure: StoreError | None = None  # the first store failure not yet acted on
        self._pending: list[dict[str, Any]] = []
        self._lock = threading.Lock()

    @property
    def pending(self) -> int:
        return len(self._pending)

    def hold(self) -> None:
        """Keep every event in memory from now until `flush` (the store is not touched meanwhile)."""
        with self._lock:
            self.held = True

    def write(self, t_s: float, kind: str, message: str, *, state: str | None, step_idx: int | None,
              detail: dict[str, Any] | None, raise_failure: bool = True) -> None:
        """Log one event, or keep it while held or while an earlier one waits (the order is kept).

        A failed write keeps the event and remembers the failure; it is raised when `raise_failure`
        (the sequencer's own thread) and only remembered otherwise."""
        row: dict[str, Any] = {"t_s": t_s, "kind": kind, "message": message, "state": state, "step_idx": step_idx,
               "detail": detail, "wall": time.time()}
        with self._lock:
            if self.held or self._pending:
                self._pending.append(row)
                failure = None if self.held else self.failure
                if failure is not None and raise_failure:
                    raise failure
                return
        try:
            self.store.event(self.campaign_id, **row)
        except StoreError as exc:
            with self._lock:
                self._pending.append(row)
                self.failure = self.failure or exc
            log.info("campaign %d: event kept in memory, the store failed: %s", self.campaign_id, exc)
            if raise_failure:
                raise

    def raise_failure(self) -> None:
        """At a safe point of the sequencer: a store failure another thread met, unless held already."""
        with self._lock:
            failure = None if self.held else self.failure
        if failure is not None:
            raise failure

    def flush(self) -> StoreError | None:
        """Write what was kept, in order, and stop holding; the store's error if it still cannot be
        written (the events stay kept)."""
        while True:
            with self._lock:
                rows = list(self._pending)
                if not rows:
                    self.held = False
                    self.failure = None
                    return None
            try:
                self.store.write_events(self.campaign_id, rows)
            except StoreError as exc:
                return exc
            with self._lock:
                del self._pending[:len(rows)]
