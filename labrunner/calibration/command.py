"""`labrunner fit DB|CSV [--json OUT] [--out DIR]`: fit, summarise, write models and tables.

The arguments are registered by `labrunner.commands.fit` (argparse only, so that building the parser loads
no analysis); `run` is called when the command runs."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from labrunner import api
from labrunner.errors import UserError
from labrunner.output_paths import check_output
from labrunner.store_address import is_store

from .fit import FitOptions
from .outputs import write_outputs
from .report import summary_markdown
from .thermal_lag_fit import DIAGNOSIS_PREFIX, lag_from_diagnosis


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
    if isinstance(lag, str) and lag.startswith(DIAGNOSIS_PREFIX):
        found = lag_from_diagnosis(lag[len(DIAGNOSIS_PREFIX):])
        if not args.quiet:
            print(f"labrunner fit: {found.sentence()}", file=sys.stderr, flush=True)
        lag = found.tau_s
    elif lag is not None and lag != "auto":
        try:
            lag = float(lag)
        except ValueError:
            raise UserError(f"--thermal-lag must be a time constant in s, 'auto' or {DIAGNOSIS_PREFIX}DIAG.json "
                            f"(the thermal_lag finding of `labrunner diagnose --json`), not {lag!r}") from None
    return FitOptions(poly_order=order, poly_method=args.poly_method, rbf_variants=variants, rbf_export=export,
                      evaluate=not args.no_eval, splits=splits, seed=args.seed, thermal_lag_s=lag,
                      branch_fit=args.hysteresis)


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
