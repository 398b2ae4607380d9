"""`labrunner` whose database disk fills up after N record steps, for the store-failure tests.

    python tests/campaign/full_disk_cli.py N STATE.json labrunner-arguments...

After the N-th record step of the process is committed, every connection the store checks out gets
`PRAGMA max_page_count` set to the database's page count: SQLite then refuses to grow the file with
SQLITE_FULL, "database or disk is full", as on a full disk. When the simulated lab is closed, what
its rate table was commanded (time, deg/s) and the chamber's setpoint are written to STATE.json, so
the test sees the lab's last state from outside.

The hooks are installed here, around the production code, so that no production signature or
environment variable carries a test seam.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from sqlalchemy import event
from sqlalchemy.engine import Engine

from labrunner.sims.lab import SimLab
from labrunner.sims.table_plant import TablePlant
from labrunner.store import Store


def install(after_records: int, state_path: Path) -> None:
    armed = {"on": after_records <= 0, "records": 0}
    commands: list[tuple[float, float]] = []

    original_commit = Store.commit_record

    def commit_record(self: Store, *args: Any, **kwargs: Any) -> None:
        original_commit(self, *args, **kwargs)
        armed["records"] += 1
        if armed["records"] >= after_records:
            armed["on"] = True

    def on_checkout(dbapi_conn: Any, _record: Any, _proxy: Any) -> None:
        if armed["on"]:
            cur = dbapi_conn.cursor()
            pages = cur.execute("PRAGMA page_count").fetchone()[0]
            cur.execute(f"PRAGMA max_page_count = {int(pages)}")
            cur.close()

    original_command = TablePlant.command

    def command(self: TablePlant, t: float, rate_dps: float) -> None:
        commands.append((float(t), float(rate_dps)))
        original_command(self, t, rate_dps)

    original_close = SimLab.close

    def close(self: SimLab) -> None:
        state_path.write_text(json.dumps({
            "table_commands": commands, "table_commanded_dps": self.world.table.commanded_dps,
            "chamber_setpoint_c": self.world.chamber.setpoint_c}))
        original_close(self)

    Store.commit_record = commit_record  # type: ignore[method-assign]
    TablePlant.command = command  # type: ignore[method-assign]
    SimLab.close = close  # type: ignore[method-assign]
    event.listen(Engine, "checkout", on_checkout)


def main(argv: list[str]) -> int:
    if len(argv) < 3:
        raise SystemExit(__doc__)
    install(int(argv[0]), Path(argv[1]))
    from labrunner.cli import main as labrunner_main

    return labrunner_main(argv[2:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
