"""`labrunner fit DB|CSV [--json OUT] [--out DIR]`: fit, summarise, write models and tables."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from labrunner import api
from labrunner.commands.types import count
from labrunner.errors import UserError
from labrunner.output_paths import check_output
from labrunner.store_address import data_arg, is_store

from .evaluation import SPLITS
from .fit import FitOptions
from .outputs import write_outputs
from .rbf_model import VARIANTS
from .report import summary_markdown


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "fit", help="fit thermal calibration models (polynomial, RBF network) to a campaign",
        description="Fit the six-position calibration per temperature step, the thermal polynomial and the RBF "
                    "networks to a campaign (CSV or labrunner database), evaluate them on held-out data and "
                    "write the models (JSON, C header). A summary (markdown tables) goes to stdout; with a "
                    "database the fit is stored in it too. docs/calibration.md explains the models.",
        epilog="""\
examples:
  labrunner fit quick.db --out fit/ --json fit.json         # models, C header and tables in fit/
  labrunner fit quick.csv --order cv --rbf hybrid          # polynomial order by cross-validation
  labrunner fit quick.db --json - --quiet | jq .evaluation  # the JSON alone, on stdout""")
    p.add_argument("data", type=data_arg, metavar="DATA",
                   help="campaign CSV or labrunner store (DB: a SQLite file or a PostgreSQL URL)")
    p.add_argument("--campaign", type=int, default=None, metavar="N",
                   help="campaign id in a database holding several (default: the latest)")
    p.add_argument("--json", metavar="FILE", help="write models, evaluation and provenance as JSON ('-' for stdout)")
    p.add_argument("--out", metavar="DIR", help="write model JSON files, the C header and evaluation tables here")
    p.add_argument("--order", default="3", metavar="N",
                   help="polynomial order, or 'cv' to choose it by cross-validation")
    p.add_argument("--poly-method", choices=("joint", "two_stage"), default="joint",
                   help="joint one-stage fit or the paper's two-stage fit")
    p.add_argument("--rbf", default=",".join(VARIANTS), metavar="NAMES",
                   help=f"RBF variants to train, comma-separated from {', '.join(VARIANTS)}")
    p.add_argument("--export-rbf", default=None, metavar="NAME",
                   help="RBF variant exported to the model files (default: hybrid if trained, else the first "
                        "trained)")
    p.add_argument("--splits", default=",".join(SPLITS), metavar="NAMES",
                   help=f"evaluation splits, comma-separated (default: all: {', '.join(SPLITS)})")
    p.add_argument("--thermal-lag", default=None, metavar="S|auto",
                   help="the sensing element's thermal lag behind its temperature sensor: a time constant in s "
                        "(e.g. the diagnosis's thermal_lag finding) or 'auto' to search it; the lag-corrected "
                        "fit is used when it lowers the held-out error (default: the logged temperature)")
    p.add_argument("--no-eval", action="store_true", help="skip the held-out evaluation")
    p.add_argument("--seed", type=count, default=0, metavar="N", help="seed of the random held-out split")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--no-store", action="store_true",
                   help="with a database: do not store this fit in it (stored by default, with its provenance)")
    p.add_argument("--force", action="store_true",
                   help="overwrite an existing --json file and write into a non-empty --out directory")
    p.set_defaults(func=run)


def _options(args: argparse.Namespace) -> FitOptions:
    order: int | str
    if args.order == "cv":
        order = "cv"
    else:
        try:
            order = int(args.order)
        except ValueError:
            raise UserError(f"--order must be an integer or 'cv', not {args.order!r}") from None
    variants = tuple(v.strip() for v in args.rbf.split(",") if v.strip())
    export = args.export_rbf or ("hybrid" if "hybrid" in variants else (variants[0] if variants else ""))
    splits = tuple(s.strip() for s in args.splits.split(",") if s.strip())
    lag: float | str | None = args.thermal_lag
    if lag is not None and lag != "auto":
        try:
            lag = float(lag)
        except ValueError:
            raise UserError(f"--thermal-lag must be a time constant in s or 'auto', not {lag!r}") from None
    return FitOptions(poly_order=order, poly_method=args.poly_method, rbf_variants=variants, rbf_export=export,
                      evaluate=not args.no_eval, splits=splits, seed=args.seed, thermal_lag_s=lag)


def run(args: argparse.Namespace) -> int:
    options = _options(args)
    # Before the fit is computed and stored: a refused output leaves the store as it was. (The header
    # is read before anything here opens the store, so no SQLite lock can be dropped by it.)
    store = args.data if is_store(args.data) else None
    if args.json:
        check_output(args.json, store=store, inputs=[args.data], force=args.force, option="--json",
                     allow_stdout=True)
    if args.out:
        check_output(args.out, store=store, inputs=[args.data], force=args.force, directory=True, option="--out")
    start = time.perf_counter()

    def progress(msg: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    progress(f"loading {args.data}")
    result = api.fit(args.data, campaign=args.campaign, options=options, save=not args.no_store, progress=progress)
    # Said on stderr whatever --quiet says: a model of half the data must not pass unnoticed.
    for warning in ([result.unfinished] if result.unfinished else []) + result.not_exported:
        print(f"labrunner fit: warning: {warning}", file=sys.stderr, flush=True)
    text = summary_markdown(result)
    if args.json != "-":
        print(text)
    if args.json:
        payload = json.dumps(result.to_dict(), indent=1, allow_nan=False)
        if args.json == "-":
            sys.stdout.write(payload + "\n")
        else:
            Path(args.json).write_text(payload)
            progress(f"wrote {args.json}")
    if args.out:
        written = write_outputs(result, Path(args.out), text)
        progress(f"wrote {', '.join(written)} in {args.out}")
    return 0
