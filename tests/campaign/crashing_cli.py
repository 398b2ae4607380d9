"""`labrunner` that kills itself (SIGKILL) at a named point, for the kill/resume tests.

    python tests/campaign/crashing_cli.py POINT:N labrunner-arguments...

dies the N-th time the process reaches POINT:

- `record`: a record step's samples are read from the IMU, nothing of them is stored yet
  (on entry to `Store.commit_record`);
- `commit`: inside the transaction that stores a record step, after its rows are written and
  before SQLite commits them (an SQLAlchemy `commit` event on the engine fires just before the
  DBAPI commit);
- `monitor`: a monitor stretch (1 s means while ramping or soaking) is about to be stored; the
  earlier ones are (on entry to `Store.save_monitor`);
- `fit`: the end-of-run fit is stored and committed, the campaign not yet marked done (on return
  from `Store.save_fit`).

The hooks are installed here, around the production code, so that no production signature
or environment variable carries a test seam.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any

from sqlalchemy import event
from sqlalchemy.engine import Connection, Engine

from labrunner.store import Store

POINTS = ("record", "commit", "monitor", "fit")


def install(spec: str) -> Callable[[], None]:
    """Arm the kill described by `POINT:N`; returns a function that disarms it (for in-process use)."""
    point, _, nth = spec.partition(":")
    if point not in POINTS:
        raise SystemExit(f"crashing_cli: unknown point {point!r}; expected one of {', '.join(POINTS)}")
    target = int(nth or 1)
    seen = {"n": 0}
    # Only the thread storing a record is inside its transaction; events written meanwhile by the
    # IMU reader thread commit their own transactions and must not count.
    storing = threading.local()

    def reached(where: str) -> None:
        if where == point:
            seen["n"] += 1
            if seen["n"] == target:
                os.kill(os.getpid(), signal.SIGKILL)

    original = Store.commit_record

    def commit_record(self: Store, *args: Any, **kwargs: Any) -> None:
        reached("record")
        storing.active = True
        try:
            original(self, *args, **kwargs)
        finally:
            storing.active = False

    def on_commit(_conn: Connection) -> None:
        if getattr(storing, "active", False):
            reached("commit")

    original_monitor = Store.save_monitor
    original_fit = Store.save_fit

    def save_monitor(self: Store, *args: Any, **kwargs: Any) -> None:
        reached("monitor")
        original_monitor(self, *args, **kwargs)

    def save_fit(self: Store, *args: Any, **kwargs: Any) -> int:
        fit_id = original_fit(self, *args, **kwargs)
        reached("fit")
        return fit_id

    Store.commit_record = commit_record  # type: ignore[method-assign]
    Store.save_monitor = save_monitor  # type: ignore[method-assign]
    Store.save_fit = save_fit  # type: ignore[method-assign]
    event.listen(Engine, "commit", on_commit)

    def uninstall() -> None:
        Store.commit_record = original  # type: ignore[method-assign]
        Store.save_monitor = original_monitor  # type: ignore[method-assign]
        Store.save_fit = original_fit  # type: ignore[method-assign]
        event.remove(Engine, "commit", on_commit)

    return uninstall


def main(argv: list[str]) -> int:
    if not argv:
        raise SystemExit(__doc__)
    install(argv[0])
    from labrunner.cli import main as labrunner_main

    return labrunner_main(argv[1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
