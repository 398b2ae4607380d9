"""`labrunner diagnose DATA --json OUT [--report DIR] [--model PATH]`.

The arguments are registered by `labrunner.commands.diagnose` (argparse only, so that building the parser
loads no analysis); `handler` is called when the command runs."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from labrunner import api
from labrunner.errors import UserError
from labrunner.output_paths import check_output
from labrunner.store_address import is_store

from .diagnose import DiagnoseOptions, TooLittleData, diagnose
from .measurements import Measurements
from .summary import read_store_summary


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
