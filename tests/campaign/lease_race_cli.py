"""`labrunner` started ahead of time and let go at a barrier, for the lease race test.

    python tests/campaign/lease_race_cli.py BARRIER RESULT OTHER labrunner-arguments...

Imports everything first, writes RESULT.ready, then waits for the file BARRIER to appear, so two of these start the
command within a millisecond or so of each other. The command's exit code goes to the file RESULT.
A process that records a step (it won the lease) writes nothing more: it waits until the file OTHER
(the other racer's result) exists, so the loser decides while the winner is alive, then dies as
kill -9 would (`os._exit`), leaving the store as a killed campaign for the next trial.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any

import labrunner.campaign_session  # noqa: F401 - imported before the barrier: the race starts warm
import labrunner.lab  # noqa: F401
import labrunner.sequencer  # noqa: F401
import labrunner.sims.world  # noqa: F401
from labrunner import cli
from labrunner.store import Store


def main() -> None:
    barrier, result, other = (Path(a) for a in sys.argv[1:4])
    original = Store.commit_record

    def commit_then_wait(self: Store, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        deadline = time.monotonic() + 30.0
        while not other.exists() and time.monotonic() < deadline:
            time.sleep(0.005)
        _write(result, "recorded")
        os._exit(0)

    Store.commit_record = commit_then_wait  # type: ignore[method-assign]
    _write(result.with_name(result.name + ".ready"), "ready")
    deadline = time.monotonic() + 60.0
    while not barrier.exists() and time.monotonic() < deadline:
        time.sleep(0.0005)
    code = cli.main(sys.argv[4:])
    _write(result, f"exit {code}")
    sys.exit(code)


def _write(path: Path, text: str) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


if __name__ == "__main__":
    main()
