"""Benchmark: fit time on the full paper campaign and compensation throughput.

    python bench/bench_fit.py                   # synthesize the paper's campaign (~12 M samples)
    python bench/bench_fit.py --data FILE       # a campaign CSV or labrunner database instead
    python bench/bench_fit.py --variants paper  # only the paper's networks
    python bench/bench_fit.py --evaluate        # also time the held-out evaluation
    python bench/bench_fit.py --hog             # the same beside a process spinning on one core

Prints data generation/loading time separately from fitting (targets: fit < 60 s on two
cores, compensation > 1 M samples/s), the CPU time of the fits and the process's peak RSS. These
phases run on the whole frame; `labrunner fit` reads a store in chunks, so with `--data DB` the
command itself is run first in a child process and its peak RSS is issue 15's target 2 (the fit
of the paper store within 1.5 GB). The numerical work runs on the fit's BLAS thread count
(`labrunner.blas_threads`), as `labrunner fit` does. Not part of the test run.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import cpu_hog, load_line, report, run_measured  # noqa: E402
from labrunner.blas_threads import analysis_threads  # noqa: E402
from labrunner.calibration import FitOptions, compensate  # noqa: E402
from labrunner.calibration.evaluation import evaluate  # noqa: E402
from labrunner.calibration.fit import fit_models  # noqa: E402
from labrunner.calibration.gain import check_models  # noqa: E402
from labrunner.calibration.records import frame_arrays, segment_records  # noqa: E402
from labrunner.campaign_csv import OUTPUT_COLUMNS  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="campaign CSV or database (default: synthesize the paper's campaign)")
    ap.add_argument("--variants", default="paper,triad,hybrid", help="RBF variants to train")
    ap.add_argument("--evaluate", action="store_true", help="also time the held-out evaluation")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--nonlinear", action="store_true",
                    help="synthesize an IMU whose temperature dependence is not cubic (a tanh step at 10 C)")
    ap.add_argument("--hog", action="store_true", help="run beside a second process spinning on one core")
    args = ap.parse_args()
    with cpu_hog(args.hog) as hog, analysis_threads():
        if hog is not None:
            print(f"cpu hog running (pid {hog})")
        return _bench(args)


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20  # kB on Linux


def _bench_command(data: str) -> None:
    """`labrunner fit DATA` as a user runs it (a store: read in chunks), in a child process."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="bench-fit-") as tmp:
        run = run_measured([sys.executable, "-m", "labrunner.cli", "fit", data, "--no-store", "--quiet",
                            "--out", Path(tmp) / "out", "--json", Path(tmp) / "fit.json"])
    if run.measured.returncode != 0:
        raise SystemExit(f"labrunner fit {data} failed (exit {run.measured.returncode}): "
                         f"{run.stderr.strip().splitlines()[-1:]}")
    print(f"labrunner fit {data}: {run.measured.line()}  [{load_line()}]")
    report("peak RSS of `labrunner fit`", run.measured.peak_rss_bytes / 2 ** 30, 1.5, "GB")


def _bench(args: argparse.Namespace) -> int:
    print(load_line())
    if args.data:
        _bench_command(args.data)
    t0 = time.perf_counter()
    if args.data:
        from labrunner.data_source import load_campaign_data

        frame = load_campaign_data(args.data).frame
        print(f"load: {time.perf_counter() - t0:.1f} s, {len(frame):,} rows")
    else:
        from labrunner.imu.model import default_imu_model
        from labrunner.sims.campaign import CampaignPlan, synthesize, triangular_rates
        from labrunner.sims.world import SimLabConfig

        model = default_imu_model()
        if args.nonlinear:
            amp = {"accel_x": 0.01, "accel_y": -0.008, "accel_z": 0.012, "gyro_x": 0.3, "gyro_y": -0.25, "gyro_z": 0.35}
            model = model.with_effects(temperature_nonlinearity={"amplitude": amp, "center_c": 10.0, "width_c": 4.0})
        plan = CampaignPlan(temperatures_c=range(-25, 56, 5), rates_dps=triangular_rates(100, 10))
        frame = synthesize(plan, SimLabConfig(imu_model=model, seed=args.seed))
        print(f"data generation (not timed below): {time.perf_counter() - t0:.1f} s, {len(frame):,} rows")

    variants = tuple(v for v in args.variants.split(",") if v)
    opt = FitOptions(rbf_variants=variants, rbf_export=variants[-1] if variants else "", evaluate=False)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    records = segment_records(frame, opt.records)
    timings["records"] = time.perf_counter() - t
    steps: list[tuple[str, float]] = []
    last = [time.perf_counter()]

    def progress(msg: str) -> None:
        now = time.perf_counter()
        steps.append((msg, now - last[0]))
        last[0] = now

    t, cpu0 = time.perf_counter(), time.process_time()
    models = fit_models(records, opt, progress)
    fit_cpu = time.process_time() - cpu0
    timings["fit (six-position, polynomials, networks)"] = time.perf_counter() - t
    total = timings["records"] + timings["fit (six-position, polynomials, networks)"]
    print(f"records: {len(records)} from {len(frame):,} rows in {timings['records']:.2f} s; "
          f"{len(models.steps)} temperature steps")
    print(f"fit: {timings['fit (six-position, polynomials, networks)']:.1f} s "
          f"(variants: {', '.join(variants) or 'none'})")
    for v, m in models.rbf.items():
        print(f"  rbf {v}: centres per network {[n.n_centres for n in m.networks]}")
    print(f"TOTAL fit time (records + fit, excluding data generation): {total:.1f} s  [target < 60 s]")
    report("records + fits", total, 60.0, "s")
    print(f"fit CPU time (six-position, polynomials, networks): {fit_cpu:.1f} s")
    t = time.perf_counter()
    gains = check_models(dict(models.compensators()), models.polynomial, records, args.seed)
    print(f"gain check of {len(gains)} models: {time.perf_counter() - t:.2f} s")
    for name, g in gains.items():
        print(f"  {name:22s} max departure from the fitted scale {100 * g.max_departure:9.3g} % "
              f"({'exportable' if g.passed else 'not exportable'})")

    if args.evaluate:
        t, cpu0 = time.perf_counter(), time.process_time()
        ev = evaluate(frame_arrays(frame), records, models.steps,
                      lambda tr: fit_models(tr, opt).compensators(), seed=args.seed)
        print(f"evaluation ({len(ev)} splits, refits and the px4 reference included): "
              f"{time.perf_counter() - t:.1f} s wall, {time.process_time() - cpu0:.1f} s CPU")
        # Issue 15, target 1: the end-of-run fit's share of the 45 s dry run (evaluation included).
        report("records + fits + evaluation", total + time.perf_counter() - t, 10.0, "s")
        for split in ev:
            if split.skipped:
                continue
            print(f"  {split.name}: RMS error per channel, samples | record means; improvement of the mean (%)")
            for name, st in split.samples.items():
                imp = split.improvement(name, "mean") if name != "raw" else np.full(6, np.nan)
                print(f"    {name:22s} " + " ".join(f"{v:9.3g}" for v in st.rms) + " | "
                      + " ".join(f"{v:9.3g}" for v in split.records[name].rms) + " | "
                      + " ".join(f"{v:7.2f}" for v in imp))
    # The whole-frame phases' memory (the command's, chunked, is measured first with --data DB); before the
    # throughput test below stacks the whole campaign's outputs, which the fit never does
    report("peak RSS of load + records + fits + evaluation (whole frame)", _peak_rss_gb(), 1.5, "GB")
    y = np.column_stack([frame[c].to_numpy(dtype=float) for c in OUTPUT_COLUMNS])
    temp = frame["imu_temp_c"].to_numpy(dtype=float)
    for name, model in [("polynomial", models.polynomial)] + [(f"rbf_{v}", m) for v, m in models.rbf.items()]:
        t = time.perf_counter()
        compensate(model, y, temp)
        dt = time.perf_counter() - t
        print(f"compensation {name}: {len(y) / dt / 1e6:.2f} M samples/s ({len(y):,} samples in {dt:.1f} s)  "
              "[target > 1 M/s]")
        report(f"compensation {name}", len(y) / dt / 1e6, 1.0, "M samples/s", lower_is_better=False)

    print(f"peak RSS with the throughput test: {_peak_rss_gb():.2f} GB")
    print(load_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
