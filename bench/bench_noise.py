"""The noise finding on a log-like 1 Hz log with white noise, bias instability and rate random walk hidden.

Usage: python bench/bench_noise.py [--seed 3] [--hours 48] [--seeds 3,4,5,...] [--table] [--hog]

Generates the log with tests/discrepancy/log_like.py (continuous, three orientations, jittery
quantised temperature; flicker made in the frequency domain, not the simulator's Markov sum), runs
`diagnose` on its rows and prints, per seed, the Allan mismatch of the fitted noise model (largest
|simulated / measured - 1| over the octaves, issue 11 target 20 %), the excess beyond the measured
curve's own 68 % interval where that is wider, and the recovered over the hidden parameters
(issue 11: within 25 %). With --table, every octave of every channel.

The curve of the noise hidden in the log is known here: the simulator's noise model at the hidden
parameters, seen through the same deterministic fit (`allan.bases`, the basis the fit uses). Per octave the
bench prints the measured and the fitted curve over it, and how often the measured curve's 68 % interval
covers it: a miss of the fitted model against the measured curve that the hidden curve does not share is
the measured curve's own scatter. With --hog a second process keeps one core busy (bench.common.cpu_hog).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import cpu_hog, load_line, report  # noqa: E402 (after the path insert)
from labrunner.discrepancy import Measurements, diagnose  # noqa: E402 (after the path insert)
from labrunner.discrepancy.allan import TARGET, bases, model_curve, octave_table, stretches  # noqa: E402
from labrunner.domain import CHANNELS  # noqa: E402 (after the path insert)
from tests.discrepancy.log_like import log_like  # noqa: E402 (after the path insert)


def run() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--seeds", type=str, default="", help="comma-separated seeds (overrides --seed)")
    parser.add_argument("--hours", type=float, default=48.0)
    parser.add_argument("--table", action="store_true", help="print every octave of every channel")
    parser.add_argument("--hog", action="store_true", help="run beside a process keeping one core busy")
    args = parser.parse_args()
    print(load_line())
    with cpu_hog(args.hog):
        code = _run(args)
    print(load_line())
    return code


def _run(args: argparse.Namespace) -> int:
    seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else [args.seed]
    worst = {"mismatch": 0.0, "excess": 0.0, "param": 0.0}
    per_octave: dict[float, list[float]] = {}  # tau -> |after / measured - 1| of every seed and channel
    half_width: dict[float, list[float]] = {}  # tau -> the measured interval's relative half-width
    hidden: dict[float, list[tuple[float, float, bool]]] = {}  # tau -> (measured, fitted) / hidden, covered
    fitted_ok = channels = 0  # channels whose fitted curve is within the target of the hidden one at every octave
    fitted_worst = 0.0  # largest |fitted / hidden - 1| over seeds, channels and octaves
    for seed in seeds:
        frame, truth = log_like(seed, args.hours, continuous=True)
        c0 = time.process_time()
        result = diagnose(frame)
        cpu = time.process_time() - c0
        fit = result.allan
        if fit is None:
            print(f"seed {seed}: no record long enough for an Allan deviation")
            continue
        taus = fit.measured.tau_s
        print(f"seed {seed}: {len(frame)} rows, octaves {taus[0]:g}-{taus[-1]:g} s, diagnose {cpu:.1f} s CPU")
        meas = Measurements.from_frame(frame)
        true_params = np.array([[truth.white[c], truth.bias_instability[c], truth.rate_random_walk[c]]
                                for c in CHANNELS])
        true_curve = model_curve(true_params, bases(meas, stretches(meas), taus), taus).adev
        low, high = fit.measured.low, fit.measured.high
        for j, tau in enumerate(taus):
            for i in range(len(CHANNELS)):
                covered = low is not None and high is not None and bool(low[j, i] <= true_curve[j, i] <= high[j, i])
                hidden.setdefault(float(tau), []).append(
                    (fit.measured.adev[j, i] / true_curve[j, i], fit.after.adev[j, i] / true_curve[j, i], covered))
        within = np.all(np.abs(fit.after.adev / true_curve - 1.0) <= TARGET, axis=0)
        fitted_ok += int(within.sum())
        fitted_worst = max(fitted_worst, float(np.max(np.abs(fit.after.adev / true_curve - 1.0))))
        channels += within.size
        if args.table:
            for c in CHANNELS:
                print(octave_table(fit, c))
        for j, tau in enumerate(taus):
            per_octave.setdefault(float(tau), []).extend(abs(fit.after.adev[j] / fit.measured.adev[j] - 1.0))
            if fit.measured.low is not None and fit.measured.high is not None:
                half_width.setdefault(float(tau), []).extend(
                    (fit.measured.high[j] - fit.measured.low[j]) / (2.0 * fit.measured.adev[j]))
        print("  channel   mismatch before  after  beyond-interval after   white  B  K (recovered / hidden)")
        for c in CHANNELS:
            ratios = (fit.white[c] / truth.white[c], fit.bias_instability[c] / truth.bias_instability[c],
                      fit.rate_random_walk[c] / truth.rate_random_walk[c])
            print(f"  {c:8s}  {fit.mismatch_before[c]:15.3f}  {fit.mismatch_after[c]:5.3f}  "
                  f"{fit.excess_after[c]:21.3f}   {ratios[0]:.3f} {ratios[1]:.3f} {ratios[2]:.3f}")
            worst["mismatch"] = max(worst["mismatch"], fit.mismatch_after[c])
            worst["excess"] = max(worst["excess"], fit.excess_after[c])
            worst["param"] = max(worst["param"], *(abs(r - 1.0) for r in ratios))
    print("per octave, over seeds and channels: |after / measured - 1| worst, median, share within the target; "
          "the measured curve's 68 % interval, median relative half-width")
    for tau, values in sorted(per_octave.items()):
        v = np.array(values)
        width = f"{np.median(half_width[tau]):.3f}" if tau in half_width else "-"
        print(f"  {tau:8g} s  {v.max():.3f}  {np.median(v):.3f}  {np.mean(v <= TARGET):.0%} of {v.size}  {width}")
    print(f"worst over seeds and channels: mismatch after {worst['mismatch']:.3f} (target {TARGET}), beyond the "
          f"measured interval {worst['excess']:.3f}, parameter error {worst['param']:.3f} (target 0.25)")
    print("against the curve of the hidden noise (through the same fit), per octave: measured / hidden mean, "
          "sd of its log, worst |.-1|; fitted / hidden worst |.-1|; share of the measured 68 % intervals covering it")
    for tau, rows in sorted(hidden.items()):
        m = np.array([r[0] for r in rows])
        f = np.array([r[1] for r in rows])
        cov = np.mean([r[2] for r in rows])
        print(f"  {tau:8g} s  {m.mean():.3f}  {np.std(np.log(m)):.3f}  {np.abs(m - 1).max():.3f}   "
              f"{np.abs(f - 1).max():.3f}   {cov:.0%}")
    if channels:
        print(f"fitted model within {TARGET:.0%} of the hidden noise's curve at every octave: {fitted_ok} of "
              f"{channels} channels")
        # Issue 11's targets: the fitted noise model within 20 % of the noise (here known), as written against
        # the measured curve (which scatters by itself at the top octaves), and the parameters within 25 %.
        report("noise_fitted_vs_hidden_worst", fitted_worst, TARGET, "relative")
        report("noise_fitted_vs_measured_worst", worst["mismatch"], TARGET, "relative")
        report("noise_parameter_error_worst", worst["param"], 0.25, "relative")
    return 0


if __name__ == "__main__":
    sys.exit(run())
