"""Benchmark: `labrunner compensate` on the paper campaign's 12 M samples.

    python bench/bench_compensate.py              # synthesize the paper's campaign, fit it, compensate it
    python bench/bench_compensate.py --rows 2e6   # a slice of it
    python bench/bench_compensate.py --in-memory  # compensation only, without the CSV read and write
    python bench/bench_compensate.py --hog        # the timed part beside a process spinning on one core

Times the phases of the command as it runs them (read the CSV, compensate with the exported model,
write the CSV with the compensated columns and the extrapolation flag), then the whole command
through `labrunner.cli.main`. Data generation and the fit that makes the model are not timed.
Target: compensation > 1 M samples/s (the whole command, CSV in and out; in memory with --in-memory).
The CSVs are written to a temporary directory, deleted at the end. Not part of the test run.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import cpu_hog, load_line, report  # noqa: E402
from labrunner.calibration import FitOptions, fit_campaign, save_model  # noqa: E402
from labrunner.calibration.apply import compensate_data, read_model  # noqa: E402
from labrunner.campaign_csv import write_campaign  # noqa: E402
from labrunner.cli import main as cli_main  # noqa: E402
from labrunner.data_source import load_campaign_data  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=float, default=None, help="compensate only the first N rows")
    ap.add_argument("--in-memory", action="store_true", help="time the compensation of the frame only")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hog", action="store_true", help="time beside a process spinning on one core")
    args = ap.parse_args()

    from labrunner.imu.model import default_imu_model
    from labrunner.sims.campaign import CampaignPlan, synthesize, triangular_rates
    from labrunner.sims.world import SimLabConfig

    t0 = time.perf_counter()
    plan = CampaignPlan(temperatures_c=range(-25, 56, 5), rates_dps=triangular_rates(100, 10))
    frame = synthesize(plan, SimLabConfig(imu_model=default_imu_model(), seed=args.seed))
    if args.rows:
        frame = frame.iloc[:int(args.rows)].reset_index(drop=True)
    print(f"data generation (not timed): {time.perf_counter() - t0:.1f} s, {len(frame):,} rows")
    t0 = time.perf_counter()
    result = fit_campaign(frame, FitOptions(rbf_variants=("hybrid",), rbf_export="hybrid", evaluate=False))
    exported = result.rbf if result.rbf is not None else result.polynomial
    print(f"fit (not timed): {time.perf_counter() - t0:.1f} s; exported "
          f"{'rbf_' + result.rbf.variant if result.rbf is not None else 'polynomial'}")

    with tempfile.TemporaryDirectory(prefix="bench-compensate-") as tmp, cpu_hog(args.hog):
        d = Path(tmp)
        save_model(exported, d / "model.json")
        model = read_model(d / "model.json")
        if args.in_memory:
            t = time.perf_counter()
            out = compensate_data(model, frame)
            dt = time.perf_counter() - t
            print(f"compensate (in memory): {dt:.1f} s, {out.n_rows / dt / 1e6:.2f} M rows/s "
                  f"[{load_line()}{', CPU hog' if args.hog else ''}]")
            report("compensation in memory", out.n_rows / dt, 1e6, "samples/s", lower_is_better=False)
            return 0
        t = time.perf_counter()
        write_campaign(frame, d / "data.csv")
        print(f"input CSV written (not timed): {time.perf_counter() - t:.1f} s, "
              f"{(d / 'data.csv').stat().st_size / 1e9:.2f} GB")
        del frame
        t = time.perf_counter()
        data = load_campaign_data(d / "data.csv")
        t_read = time.perf_counter() - t
        t = time.perf_counter()
        out = compensate_data(model, data.frame)
        t_comp = time.perf_counter() - t
        t = time.perf_counter()
        out.frame.to_csv(d / "phases.csv", index=False, float_format="%.9g")
        t_write = time.perf_counter() - t
        n = out.n_rows
        print(f"phases: read {t_read:.1f} s, compensate {t_comp:.1f} s ({n / t_comp / 1e6:.2f} M rows/s), "
              f"write {t_write:.1f} s; {n:,} rows, {out.n_extrapolated:,} flagged")
        del data, out
        t = time.perf_counter()
        rc = cli_main(["compensate", str(d / "model.json"), str(d / "data.csv"), "--csv", str(d / "out.csv")])
        dt = time.perf_counter() - t
        print(f"labrunner compensate (whole command): {dt:.1f} s for {n:,} rows ({n / dt / 1e6:.2f} M rows/s), "
              f"exit {rc} [{load_line()}{', CPU hog' if args.hog else ''}]")
        if rc != 0:
            return rc
        report("labrunner compensate, CSV to CSV", n / dt, 1e6, "samples/s", lower_is_better=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
