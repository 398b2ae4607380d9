"""`labrunner compensate MODEL DATA --csv FILE`: a campaign's rows with compensated outputs and extrapolation flags."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from labrunner.commands.types import count
from labrunner.errors import UserError
from labrunner.output_paths import check_output
from labrunner.store_address import data_arg, is_store


def register(sub: Any) -> None:
    p = sub.add_parser(
        "compensate", help="compensate a campaign CSV or store with a calibration model file",
        description="Apply a calibration model (polynomial.json or rbf.json of `labrunner fit --out`, or a `fit "
                    "--json` document: its exported model) to every row of a campaign CSV or a store's campaign. "
                    "The rows come out as a campaign CSV with the compensated outputs added (ax_g_comp ... "
                    "gz_dps_comp) and `extrapolated` (1 where the temperature or a network input lies outside "
                    "what the model was fitted to: flagged, not refused). A summary goes to stderr.",
        epilog="""\
examples:
  labrunner compensate quick_fit/campaign-1/rbf.json quick.db --csv quick_comp.csv
  labrunner compensate fit/polynomial.json log.csv --csv - | head""")
    p.add_argument("model", metavar="MODEL", help="model JSON file (polynomial.json, rbf.json or a fit --json)")
    p.add_argument("data", type=data_arg, metavar="DATA", help="campaign CSV or labrunner store (file or URL)")
    p.add_argument("--campaign", type=count, default=None, metavar="N",
                   help="campaign id in a database holding several (default: the latest)")
    p.add_argument("--csv", required=True, metavar="FILE", help="the CSV to write ('-' for stdout)")
    p.add_argument("--ins", type=float, default=None, metavar="SECONDS", nargs="?", const=60.0,
                   help="also run the paper's INS test: strapdown navigation over windows of this many seconds "
                        "(default 60) of contiguous rows of one record, static or turning, raw and compensated; "
                        "errors at the windows' end on stderr")
    p.add_argument("--force", action="store_true", help="overwrite an existing --csv file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Here, not at the top: building the parser must not load the calibration package (scipy, pandas).
    from labrunner.calibration.apply import compensate_data, ins_of, read_model
    from labrunner.data_source import load_campaign_data

    if args.ins is not None and not args.ins > 0:
        raise UserError(f"--ins must be a positive number of seconds, not {args.ins:g}")
    store = args.data if is_store(args.data) else None
    out = check_output(args.csv, store=store, inputs=[args.data, args.model], force=args.force, option="--csv",
                       allow_stdout=True)
    start = time.perf_counter()
    model = read_model(args.model)  # before the data: a wrong model file costs nothing
    data = load_campaign_data(args.data, args.campaign)
    result = compensate_data(model, data.frame)
    result.frame.to_csv(sys.stdout if out is None else out, index=False, float_format="%.9g")
    print(f"{result.summary(model)}; {time.perf_counter() - start:.1f} s", file=sys.stderr)
    if args.ins is not None:
        ins = ins_of(model, data.frame, args.ins)
        if not ins:
            print(f"INS test: no window of {args.ins:g} s of contiguous rows of one record in the data",
                  file=sys.stderr)
        for name, e in ins.items():
            print(f"INS test, {name}: after {e.window_s:g} s, position error {e.position_m:.4g} m (max "
                  f"{e.position_m_max:.4g} m), attitude error {e.attitude_deg:.4g} deg; mean over {e.n_windows} "
                  "windows", file=sys.stderr)
    return 0
