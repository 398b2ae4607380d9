"""Where a paper campaign's chamber time goes, soak by soak, on the simulated lab's thermal physics.

Usage: python bench/soak_timeline.py [procedures/paper_campaign_fast.yaml ...] [--lag-s 240] [--seed N]
       [--set soak.KEY=VALUE ...] [--hog]

Replays what the sequencer does between records (ramp: setpoint, poll until the chamber is within
tolerance; soak: poll and judge with `SoakWindow`; remount: to `remount_c` within 2 C, power cycle)
on the dry run's own chamber and IMU-temperature model (`sims.world.SimWorld`: PI chamber, the case's
lag, the die's self-heating after power-on), and the records' duration from the rate schedule (the
table's spin-up, settle_s, record_s) without generating samples: seconds per procedure instead of the
dry run's tens of minutes. Prints the time per phase, per-soak statistics (time to decide against the
IMU's time constant, the remaining drift over the record after the decision) and, for each record, the
IMU temperature's rate (what a sensing element lagging its sensor by --lag-s turns into a temperature
error: rate x lag). `--set` replays variants of the soak section (e.g. `--set soak.predict_lag_s=240`);
`--hog` runs a CPU hog on a second core meanwhile (`bench.common.cpu_hog`: the replay's CPU time and wall
time under contention). Each procedure's line ends with the CPU time of its replay and the load.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PREDICTIVE_LIMIT_H = 96.0  # issue 16
BOOST_MARGIN_C = 0.3  # a boost ends this short of the step: the IMU still gains it while the air comes back
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import cpu_hog, load_line, report  # noqa: E402
from labrunner.errors import UserError  # noqa: E402
from labrunner.procedure import Procedure, load_procedure, parse_procedure  # noqa: E402
from labrunner.runner.soak import SoakWindow  # noqa: E402
from sims.world import SimLabConfig, SimWorld  # noqa: E402


@dataclass
class SoakRecord:
    orientation: str
    setpoint_c: float
    ramp_s: float  # setpoint given -> chamber within tolerance
    soak_s: float  # chamber within tolerance -> stable
    fallback: str | None
    tau_s: float  # the fit's dominant time constant (NaN: spread decided)
    drift_after_c: float  # the true IMU temperature's max - min over the horizon after the decision
    rates_c_per_s: list[float] = field(default_factory=list)  # |dT/dt| of the IMU at each record's middle


@dataclass
class Timeline:
    name: str
    total_s: float = 0.0
    remount_s: float = 0.0  # ramps to remount_c
    ramp_s: float = 0.0
    soak_s: float = 0.0
    records_s: float = 0.0
    soaks: list[SoakRecord] = field(default_factory=list)


def _rate_step_s(prev_dps: float, rate_dps: float, accel_dps2: float) -> float:
    """The sequencer's rate_settling: the table reaches the rate (polled every 0.5 s), then settle_s."""
    spin = abs(rate_dps - prev_dps) / accel_dps2
    return math.ceil(spin / 0.5) * 0.5 if spin > 0 else 0.0


def replay(proc: Procedure, config: SimLabConfig | None = None, boost_c: float = 0.0) -> Timeline:
    """The campaign's thermal timeline on the simulated lab (records as durations only).

    `boost_c` > 0 tries setpoint overshoot (not in the sequencer: what it would gain): a temperature
    step's setpoint is first `boost_c` past the target (within the procedure's chamber limits), until
    the IMU reading has covered the step less the ~0.3 C it still gains while the air comes back."""
    m = proc.model
    s = m.soak
    cfg = config or SimLabConfig()
    w = SimWorld(cfg, 0.0)
    t = 0.0
    tl = Timeline(m.name)

    def imu_at(tt: float) -> float:
        w.advance(tt)
        return float(w.imu_temperature_at(np.array([tt]))[0])

    def wait_chamber(target: float, tol: float) -> float:
        nonlocal t
        t0 = t
        while True:
            w.advance(t)
            if abs(w.chamber.air_c - target) <= tol or t - t0 > s.max_wait_s:
                return t - t0
            t += s.poll_s

    steps = proc.steps()
    k = 0
    while k < len(steps):
        step = steps[k]
        w.chamber.set_setpoint(m.remount_c)
        tl.remount_s += wait_chamber(m.remount_c, max(2.0, s.tolerance_c))
        w.advance(t)
        w.remount(step.orientation, t)
        o = step.orientation_index
        while k < len(steps) and steps[k].orientation_index == o:
            temp = steps[k].temperature_c
            t_ramp = t
            if boost_c > 0 and k > 0 and steps[k - 1].orientation_index == o:
                prev = steps[k - 1].temperature_c
                sign = 1.0 if temp > prev else -1.0
                lim = m.safety.chamber_max_c if sign > 0 else m.safety.chamber_min_c
                w.chamber.set_setpoint(temp + sign * min(boost_c, abs(lim - temp)))
                goal = imu_at(t) + (temp - prev) - sign * BOOST_MARGIN_C
                while sign * (imu_at(t) - goal) < 0 and t - t_ramp < s.max_wait_s:
                    t += s.poll_s
            w.chamber.set_setpoint(temp)
            wait_chamber(temp, s.tolerance_c)
            ramp = t - t_ramp
            win = SoakWindow(s, temp, horizon_s=m.record_s)
            t_soak = t
            while True:
                w.advance(t)
                win.add(t, w.chamber.air_c, imu_at(t))
                if win.stable() or t - t_soak + ramp >= s.max_wait_s:
                    break
                t += s.poll_s
            soak = t - t_soak
            pred = win.prediction if win.fallback is None else None
            horizon = win.horizon_s
            ts = np.linspace(t, t + horizon, 31)
            after = [imu_at(v) for v in ts]
            rec = SoakRecord(step.orientation, temp, ramp, soak, win.fallback,
                             pred.tau_s if pred is not None else math.nan, max(after) - min(after))
            prev_rate = 0.0
            t_rec0 = t
            while k < len(steps) and steps[k].orientation_index == o and steps[k].temperature_c == temp:
                t += _rate_step_s(prev_rate, steps[k].rate_dps, cfg.table.accel_dps2) + m.settle_s
                mid = t + m.record_s / 2
                rec.rates_c_per_s.append(abs(imu_at(mid + 1.0) - imu_at(mid - 1.0)) / 2.0)
                t += m.record_s
                prev_rate = steps[k].rate_dps
                k += 1
            tl.records_s += t - t_rec0
            tl.ramp_s += ramp
            tl.soak_s += soak
            tl.soaks.append(rec)
    w.chamber.set_setpoint(m.remount_c)
    tl.total_s = t
    return tl


def print_timeline(tl: Timeline, lag_s: float) -> None:
    h = 3600.0
    print(f"{tl.name}: {tl.total_s / h:.1f} lab h = remounts {tl.remount_s / h:.1f} + ramps {tl.ramp_s / h:.1f} + "
          f"soaks {tl.soak_s / h:.1f} + records {tl.records_s / h:.1f}")
    soak = np.array([r.soak_s for r in tl.soaks])
    ramp = np.array([r.ramp_s for r in tl.soaks])
    drift = np.array([r.drift_after_c for r in tl.soaks])
    first = np.array([r.setpoint_c for r in tl.soaks])
    fell = sum(r.fallback is not None for r in tl.soaks)
    taus = np.array([r.tau_s for r in tl.soaks])
    rates = np.concatenate([r.rates_c_per_s for r in tl.soaks])
    first_rates = np.array([r.rates_c_per_s[0] for r in tl.soaks])
    print(f"  {len(tl.soaks)} soaks: soak median {np.median(soak):.0f} s, max {soak.max():.0f} s; ramp median "
          f"{np.median(ramp):.0f} s, max {ramp.max():.0f} s; fallbacks {fell}; fitted tau median "
          f"{np.nanmedian(taus) if np.isfinite(taus).any() else math.nan:.0f} s")
    print(f"  drift over the horizon after the decision: median {np.median(drift):.3f} C, max {drift.max():.3f} C "
          f"(at {first[int(np.argmax(drift))]:g} C)")
    print(f"  IMU |dT/dt| x {lag_s:.0f} s lag over records: RMS {math.sqrt(np.mean((rates * lag_s) ** 2)):.4f} C, "
          f"first records RMS {math.sqrt(np.mean((first_rates * lag_s) ** 2)):.4f} C, "
          f"max {rates.max() * lag_s:.3f} C")
    orient_first = [r for i, r in enumerate(tl.soaks) if i == 0 or tl.soaks[i - 1].orientation != r.orientation]
    print("  orientations' first soaks (ramp + soak s): "
          + ", ".join(f"{r.orientation}@{r.setpoint_c:g} {r.ramp_s:.0f}+{r.soak_s:.0f}" for r in orient_first))


def with_settings(path: Path, settings: list[str]) -> Procedure:
    """The procedure at `path` with `soak.KEY=VALUE` settings applied (validated as the file would be)."""
    proc = load_procedure(path)
    if not settings:
        return proc
    import yaml

    data = yaml.safe_load(proc.text)
    for item in settings:
        key, sep, value = item.partition("=")
        section, _, name = key.partition(".")
        if not sep or section != "soak" or not name:
            raise UserError(f"--set {item!r}: expected soak.KEY=VALUE")
        data.setdefault("soak", {})[name] = yaml.safe_load(value)
    return parse_procedure(yaml.safe_dump(data, sort_keys=False), f"{path} with {' '.join(settings)}")


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("procedures", nargs="*", type=Path,
                    default=[ROOT / "procedures/paper_campaign.yaml", ROOT / "procedures/paper_campaign_fast.yaml"])
    ap.add_argument("--lag-s", type=float, default=240.0)
    ap.add_argument("--boost-c", type=float, default=0.0, help="try setpoint overshoot by this much (C)")
    ap.add_argument("--seed", type=int, default=None, help="the simulated lab's seed (default: its own)")
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="soak.KEY=VALUE",
                    help="replay with this soak setting changed (repeatable)")
    ap.add_argument("--hog", action="store_true", help="run a CPU hog on another core meanwhile")
    args = ap.parse_args()
    config = SimLabConfig(seed=args.seed) if args.seed is not None else None
    try:
        procs = [with_settings(path, args.settings) for path in args.procedures]
    except (UserError, OSError) as exc:
        print(f"soak_timeline: {exc}", file=sys.stderr)
        return 2
    with cpu_hog(args.hog) as hog:
        for proc in procs:
            c0 = time.process_time()
            w0 = time.perf_counter()
            tl = replay(proc, config, boost_c=args.boost_c)
            cpu, wall = time.process_time() - c0, time.perf_counter() - w0
            print_timeline(tl, args.lag_s)
            print(f"  replay: CPU {cpu:.1f} s, wall {wall:.1f} s{' (cpu hog ' + str(hog) + ')' if hog else ''}; "
                  f"{load_line()}")
            if proc.model.soak.criterion == "predictive":  # issue 16: the predictive paper campaign in <= 4 lab-days
                report(f"{tl.name} lab time (replay)", tl.total_s / 3600.0, PREDICTIVE_LIMIT_H, "lab h")
    return 0


if __name__ == "__main__":
    sys.exit(main())
