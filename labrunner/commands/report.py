"""`labrunner report DB --html OUT`: a campaign as one HTML file that opens offline."""

from __future__ import annotations

import argparse
from pathlib import Path

from labrunner.commands.types import count
from labrunner.store_address import store_arg


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="a campaign as one self-contained HTML file (figures, tables, provenance)",
                       description="Write a campaign's report as one HTML file that opens offline in any browser: "
                                   "a headline (status, lab time, samples, the exported model and its held-out "
                                   "gain, faults), an overview of temperatures and rates over the campaign, the "
                                   "steps and events (filterable), the calibration figures and tables of the "
                                   "stored fit, and provenance. Works on a finished, paused or failed campaign; "
                                   "a section without data says why.",
                       epilog="""\
examples:
  labrunner report quick.db --html quick.html
  labrunner report c1.db --campaign 2 --html c2.html --force    # the second campaign, replacing c2.html""")
    p.add_argument("db", type=store_arg, metavar="DB", help="labrunner store")
    p.add_argument("--campaign", type=count, default=None, metavar="N",
                   help="campaign id (default: the latest in the database)")
    p.add_argument("--html", type=Path, required=True, metavar="FILE", help="the HTML file to write")
    p.add_argument("--force", action="store_true", help="overwrite an existing --html file")
    p.set_defaults(func=cmd_report)


def cmd_report(args: argparse.Namespace) -> int:
    from labrunner import api  # here, not at the top: building the parser must not load the report's figures

    result = api.report(args.db, html=args.html, campaign=args.campaign, force=args.force)
    explained = "".join(f"; {section}: {why}" for section, why in result.explained.items())
    print(f"campaign {result.campaign_id} ({result.status}): report written to {args.html} in "
          f"{result.seconds:.1f} s{explained}")
    return 0
