"""`labrunner diagnose DATA --json OUT [--report DIR] [--model PATH]`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from labrunner import api
from labrunner.errors import UserError
from labrunner.output_paths import check_output
from labrunner.store_address import data_arg, is_store

from .diagnose import DiagnoseOptions, TooLittleData, diagnose
from .measurements import Measurements
from .summary import read_store_summary
from .terms import CAUSE_ORDER


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "diagnose", help="find what the simulated IMU model gets wrong in measured data, and extend it",
        description="Fit the simulator's IMU error model to a measured campaign (CSV or store), test every "
                    "candidate cause on held-out time blocks, name the ones the data supports, write the "
                    "extended model for the sims and the held-out gain. The verdict and the findings go to "
                    "stdout. It needs a campaign of some length (several held-out stretches of 30 s or more); "
                    "docs/diagnosis.md explains the method and the causes.",
        epilog="""\
examples:
  labrunner diagnose lab.csv --json diagnosis.json --report diagnosis/
  labrunner diagnose quick.db --json d.json --causes thermal_lag,hysteresis""")
    p.add_argument("data", type=data_arg, metavar="DATA",
                   help="campaign CSV or labrunner store (DB: a SQLite file or a PostgreSQL URL)")
    p.add_argument("--json", required=True, dest="json_out", metavar="FILE", help="write the diagnosis JSON here")
    p.add_argument("--report", metavar="DIR", help="also write plots, residuals.csv and summary.md here")
    p.add_argument("--model", metavar="FILE",
                   help="where to write the extended IMU model (default: the --json FILE with .imu_model.json)")
    p.add_argument("--campaign", type=int, metavar="N",
                   help="campaign id in a database holding several (default: the latest)")
    p.add_argument("--causes", metavar="NAMES", help="comma-separated subset of causes to test (default: all: "
                                                     + ", ".join(CAUSE_ORDER) + ")")
    p.add_argument("--min-evidence", type=float, default=10.0, metavar="SCORE",
                   help="held-out evidence a cause must exceed (2 x log-likelihood, after the parameter charge)")
    p.add_argument("--force", action="store_true",
                   help="overwrite existing --json and --model files and write into a non-empty --report directory")
    p.set_defaults(func=handler)


def handler(args: argparse.Namespace) -> int:
    json_out = Path(args.json_out)
    model_out = Path(args.model) if args.model else json_out.with_suffix(".imu_model.json")
    # All outputs checked before the (long) diagnosis: none may be the data, none overwritten unasked.
    store = args.data if is_store(args.data) else None  # read before anything here opens the store
    checked_json = check_output(json_out, store=store, inputs=[args.data], force=args.force, option="--json")
    if check_output(model_out, store=store, inputs=[args.data], force=args.force, option="--model") == checked_json:
        raise UserError(f"--model {model_out} and --json {json_out} are the same file; give two paths")
    if args.report:
        check_output(args.report, store=store, inputs=[args.data], force=args.force, directory=True,
                     option="--report")
    causes = tuple(c.strip() for c in args.causes.split(",") if c.strip()) if args.causes else None
    try:
        if store is not None:
            # A store is read block by block into 1 s summaries (bounded memory; docs/diagnosis.md).
            stored = read_store_summary(args.data, args.campaign)
            provenance = stored.provenance
            meas = Measurements.from_frame(stored.frame, stored.summary)
            del stored
            result = diagnose(meas, DiagnoseOptions(min_evidence=args.min_evidence, causes=causes))
        else:
            data = api.load_data(args.data, campaign=args.campaign, include_monitor=True)  # ramps and soaks too
            provenance = dict(data.provenance)
            result = api.diagnose(data, min_evidence=args.min_evidence, causes=causes)
    except TooLittleData as exc:  # the analysis sees rows, not files: name the data here
        raise UserError(f"{args.data}: {exc}") from None

    result.model.save(model_out)
    result.model_path = str(model_out)
    payload = result.to_json()
    payload["data"] = provenance
    try:
        json_out.write_text(json.dumps(payload, indent=2, default=str))
    except OSError as exc:
        raise UserError(f"cannot write {json_out}: {exc.strerror}") from None
    written = []
    if args.report:
        from .report import write_report

        try:
            written = write_report(result, args.report)
        except OSError as exc:
            raise UserError(f"cannot write the report to {args.report}: {exc.strerror}") from None
    lines = [f"verdict: {result.verdict}" + (" (uncertain)" if result.verdict_uncertain else "")]
    if result.verdict_note:
        lines.append(f"  {result.verdict_note}")
    for f in result.findings:
        conf = f" (confounded with {', '.join(f.confounded_with)})" if f.confounded_with else ""
        if f.stability is not None:
            conf += f", selected on {f.stability.selected_share:.0%} of resamples"
        lines.append(f"  {f.status:11s} {f.cause:26s} {', '.join(f.channels)}: held-out RMS "
                     f"-{f.gain.improvement_pct:.1f} %{conf}")
    lines.append(f"json: {json_out}")
    lines.append(f"extended model: {model_out}")
    if written:
        lines.append(f"report: {args.report} ({len(written)} files)")
    print("\n".join(lines), file=sys.stdout)
    return 0
