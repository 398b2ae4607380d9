"""Ending a campaign from outside (`labrunner abort`): ask the process running it to stop safely, or,
when none is running, bring a real lab to its safe state from here with the one safe stop
(`labrunner.runner.safe_stop`, with its retries). The campaign stays resumable.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from labrunner.database import process_alive
from labrunner.errors import UserError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AbortResult:
    """What `abort` did: `outcome` is "already" (done or aborted before), "requested" (the running
    process was asked and answered with `status`), or "direct" (none was running: made safe here)."""

    campaign_id: int
    outcome: str
    status_before: str
    status: str

    @property
    def ok(self) -> bool:
        return self.outcome != "requested" or self.status in ("aborted", "failed", "paused")


def abort_campaign(db: str | Path, *, campaign: int | None = None, wait_s: float = 60.0,
                   notify: Callable[[str], None] | None = None) -> AbortResult:
    """Bring a campaign's lab to its safe state and end the run (resumable afterwards).

    If a process is running the campaign, it is asked through the store and given `wait_s` to
    stop safely; otherwise a real lab is made safe from here (`runner.safe_stop`, with retries).
    `notify` receives progress messages ("waiting for process ...", retries)."""
    from labrunner.store import Store

    say = notify or (lambda _msg: None)
    with Store.open_existing(db) as store:
        cid = store.resolve(campaign)
        info = store.campaign(cid)
        if info.status in ("done", "aborted"):
            return AbortResult(cid, "already", info.status, info.status)
        if info.status == "running" and process_alive(info.pid, info.host, info.lease_wall):
            store.request(cid, "abort")
            say(f"abort requested; waiting for process {info.pid} to bring the lab to its safe state...")
            deadline = time.time() + wait_s
            while time.time() < deadline:
                time.sleep(0.2)
                if store.campaign(cid).status != "running":
                    break
            return AbortResult(cid, "requested", info.status, store.campaign(cid).status)
        # Nobody is running it: make the lab safe ourselves (a real lab), then mark it aborted.
        if info.mode == "lab":
            _safe_state_directly(info, say)
        store.event(cid, info.clock_last - info.clock_t0, "operator", "aborted by labrunner abort (no process running)")
        store.set_status(cid, "aborted", pid=None)
        log.info("campaign %d aborted with no process running", cid)
        return AbortResult(cid, "direct", info.status, "aborted")


def _safe_state_directly(info: Any, say: Callable[[str], None]) -> None:
    from labrunner.lab import lab_config_from_dict, real_lab
    from labrunner.procedure import parse_procedure
    from labrunner.runner.safe_stop import safe_stop

    procedure = parse_procedure(info.procedure_text, "stored procedure", stored=True)
    lab = real_lab(lab_config_from_dict(info.lab_config, "stored lab configuration"),
                   max_rate_dps=procedure.model.safety.max_rate_dps)
    try:
        result = safe_stop(lab.table, lab.chamber, procedure.model.remount_c, lab.clock, connect=True,
                           on_retry=lambda problems: say("safe state not reached yet, trying again: "
                                                         + "; ".join(problems)))
    finally:
        lab.close()
    if not result.reached:
        err = UserError("safe state NOT reached: " + "; ".join(result.problems))
        err.exit_code = 1
        raise err
