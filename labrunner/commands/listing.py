"""`labrunner list DB`: the campaigns a store holds, one line each.

Campaign ids otherwise appear only in error messages; this is where a user finds the one to pass to
`--campaign`. Read through `labrunner.api.list_campaigns`, safe while a campaign runs.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from labrunner.store_address import StoreAddress, store_arg

if TYPE_CHECKING:  # the handler imports it: building the parser must not load the store (SQLAlchemy)
    from labrunner import api

HEADER = ("id", "name", "status", "steps", "samples", "mode", "process", "last heartbeat")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("list", help="the campaigns in a store: id, name, status, progress, mode, process",
                       description="List the campaigns of a labrunner store: id, name, status, steps recorded of "
                                   "planned, samples, mode (sim or lab), the process running it and the age of "
                                   "its last heartbeat. The ids are what --campaign N takes.",
                       epilog="""\
examples:
  labrunner list c1.db
  labrunner status c1.db --campaign 2                       # then one of them in detail""")
    p.add_argument("db", type=store_arg, metavar="DB", help="labrunner store: a SQLite file or a PostgreSQL URL")
    p.set_defaults(func=cmd_list)


def age_text(seconds: float) -> str:
    """A duration as a person reads it: 42 s, 7 min, 3.5 h, 2.1 d."""
    if seconds < 120:
        return f"{seconds:.0f} s ago"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min ago"
    if seconds < 2 * 86400:
        return f"{seconds / 3600:.1f} h ago"
    return f"{seconds / 86400:.1f} d ago"


def _process(s: api.CampaignSummary) -> str:
    from labrunner.runner.lease import STALE_AFTER_S

    holder = s.holder
    if holder is None:
        return "-"
    if s.process_alive is False:
        return f"{holder} (gone: resume it)"
    if s.process_alive is None and s.heartbeat_age_s > STALE_AFTER_S:
        # Another host's process cannot be looked at: only its heartbeat tells, and it stopped.
        return f"{holder} (stale: resume --take-over once it is stopped)"
    return holder


def table_text(db: StoreAddress, summaries: list[api.CampaignSummary]) -> str:
    rows = [HEADER] + [(str(s.campaign_id), s.name, s.status, f"{s.steps_done}/{s.steps_total}", f"{s.samples:,}",
                        s.mode, _process(s), age_text(s.heartbeat_age_s)) for s in summaries]
    widths = [max(len(r[i]) for r in rows) for i in range(len(HEADER))]
    right = {0, 3, 4}  # numbers line up on the right
    lines = ["  ".join(cell.rjust(w) if i in right else cell.ljust(w)
                       for i, (cell, w) in enumerate(zip(r, widths))).rstrip() for r in rows]
    return "\n".join([f"{db}: {len(summaries)} campaign{'s' if len(summaries) != 1 else ''}", *lines])


def cmd_list(args: argparse.Namespace) -> int:
    from labrunner import api

    summaries = api.list_campaigns(args.db)
    if not summaries:
        # A store with no campaign is not an error: `run --db` created it, or a first run was refused.
        print(f"{args.db}: a labrunner store with no campaigns yet")
        return 0
    print(table_text(args.db, summaries))
    return 0
