"""Chamber time against accuracy (issue 16): the strict, predictive and ramp campaigns side by side.

Usage: nice python bench/bench_chamber_time.py [--seed 3] [--workdir DIR] [--only strict,fast,ramp] [--refit]
       [--hog]

Runs on the simulated lab, one seed and one IMU for all (the paper's IMU plus a thermal lag of the
sensing element behind its temperature sensor and a non-cubic step in the temperature law):

- strict: procedures/paper_campaign.yaml (soak until the IMU spread is <= 0.1 C over 10 min)
- predictive: procedures/paper_campaign_fast.yaml (soak.criterion: predictive)
- ramp: procedures/ramp_campaign.yaml (one slow ramp per orientation, the rate schedule along it)

each with the end-of-run polynomial fit (rbf off, so every campaign exports the same kind of model),
and two held-out campaigns no calibration saw: soaks at temperatures between the calibrated ones (six
orientations, three rates) and the paper's static heating test (z up, table at rest, the chamber
heating at 1 C/min). Each exported polynomial.json is applied to the held-out rows (record rows only);
the error is the RMS over x, y, z and over the held-out records of each record's mean compensated minus
true specific force / angular rate (per sample the sensor noise would hide every difference). PX4's method
(`labrunner.calibration.px4_reference`, offsets only, one cubic per orientation from a temperature
sweep) is fitted on the ramp campaign's static rows: the reference row. PX4 has the sensor's temperature
only, so it is fitted and scored on the logged temperature, also when the campaigns' models take the
lag-corrected one (a line after the table says which).

A --workdir keeps the stores; a campaign whose store holds a finished run is not run again (its
models are fitted again from the store when they are missing; `--refit` fits the campaigns of --only
again, with the code as it is now). Without one, the stores go to a temporary directory removed at the
end. `--hog` runs everything beside a process spinning on one core (`bench.common.cpu_hog`): the
simulated lab's clock is virtual, so lab time and errors must not move with the machine's load.
Prints lab time, samples and held-out errors, each campaign's ratios to the strict one, which
temperature each row was scored on, then issue 16's targets, one line each with the measured value and its ratio
to the target (`bench.common.report`: ratio <= 1 is met). Exits 0 whether or not a target is met;
non-zero only when something crashed (a campaign run that failed).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import cpu_hog, load_line, report  # noqa: E402

IMU_EFFECTS = {
    "thermal_lag": {"tau_s": 240.0, "channels": ["accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z"]},
    "temperature_nonlinearity": {"amplitude": {"accel_z": 0.004, "gyro_x": 0.08, "gyro_z": 0.08},
                                 "center_c": 12.0, "width_c": 6.0},
}

HELDOUT_SOAKS = """\
name: heldout_soaks
description: held-out soaks between the calibrated temperatures
temperatures: {list_c: [-22.5, -7.5, 7.5, 22.5, 37.5, 52.5], order: serpentine}
soak: {tolerance_c: 0.1, stable_window_s: 600, max_wait_s: 10800, on_timeout: pause, sensor: imu, poll_s: 30}
orientations: [x_up, x_down, y_up, y_down, z_up, z_down]
rates: {list_dps: [-50, 0, 50]}
settle_s: 5
record_s: 60
fit: {run: false}
"""

HELDOUT_HEATING = """\
name: heldout_heating
description: the paper's static heating test (table at rest, the chamber heating)
temperatures: {start_c: -20, stop_c: 50, step_c: 10}
soak: {tolerance_c: 0.1, stable_window_s: 600, max_wait_s: 10800, on_timeout: pause, sensor: imu, poll_s: 30}
ramp: {c_per_min: 1.0}
orientations: [z_up]
rates: {list_dps: [0]}
settle_s: 0
record_s: 60
fit: {run: false}
"""

CAMPAIGNS = {"strict": "paper_campaign.yaml", "fast": "paper_campaign_fast.yaml", "ramp": "ramp_campaign.yaml"}


@dataclass
class Run:
    name: str
    db: Path
    fit_dir: Path
    lab_h: float
    samples: int
    wall_s: float


def _shipped(name: str) -> str:
    return resources.files("labrunner.procedures").joinpath(name).read_text()


def _finished(db: Path) -> bool:
    if not db.exists():
        return False
    from labrunner.store import Store

    with Store.open_existing(db) as s:
        return s.campaign(1).status == "done"


def run_campaign(name: str, text: str, work: Path, sim: Path, seed: int, refit: bool = False) -> Run:
    from labrunner.store import Store

    proc = work / f"{name}.yaml"
    proc.write_text(text.replace("rbf: true", "rbf: false"))
    db, fit_dir = work / f"{name}.db", work / f"{name}_fit"
    wall = 0.0
    if not _finished(db):
        db.unlink(missing_ok=True)
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "labrunner.cli", "run", str(proc), "--sim", "--sim-config", str(sim),
                            "--seed", str(seed), "--db", str(db), "--fit-out", str(fit_dir), "--force", "--quiet"],
                           capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if p.returncode != 0:
            raise SystemExit(f"{name}: labrunner run exited {p.returncode}:\n{p.stderr[-3000:]}")
    with Store.open_existing(db) as s:
        info = s.campaign(1)
        steps = s.steps_frame(1)
        run = Run(name, db, fit_dir, (info.clock_last - info.clock_t0) / 3600.0, int(steps.n_samples.sum()), wall)
        if name in CAMPAIGNS and (refit or not (fit_dir / "polynomial.json").exists()):
            if refit:
                shutil.rmtree(fit_dir, ignore_errors=True)
            _refit(s, fit_dir)
        return run


def _refit(store, fit_dir: Path) -> None:
    """The end-of-run fit again, as the stored procedure says (a kept store whose models are gone)."""
    from labrunner.campaign_fit import fit_and_store
    from labrunner.procedure import parse_procedure

    proc = parse_procedure(store.campaign(1).procedure_text, "stored procedure", stored=True)
    fit_and_store(store, 1, proc.model.fit, fit_dir)


def _filter_tau(model_path: Path) -> float | None:
    """tau of the model file's temperature filter (None: the model takes the logged temperature)."""
    from labrunner.calibration.apply import read_model

    f = read_model(model_path).temperature_filter
    return None if f is None else f.tau_s


def _rms(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(err ** 2)))


def record_labels(db: Path, frame) -> np.ndarray:
    """Each row's record step (-1: none), from the steps' start and end times."""
    from labrunner.store import Store

    with Store.open_existing(db) as s:
        steps = s.steps_frame(1)
    t = frame["t_s"].to_numpy(dtype=float)
    labels = np.full(t.size, -1, dtype=np.int64)
    for k, (a, b) in enumerate(zip(steps.t_start, steps.t_end, strict=True)):
        labels[(t >= a) & (t <= b)] = k
    return labels


def heldout_errors(model_path: Path | None, px4, frame, labels: np.ndarray) -> tuple[float, float]:
    """(accel g, gyro deg/s) RMS over x, y, z of the held-out records' mean errors (the sensor noise
    averages out of a record's mean: what is left is the calibration's error); model and px4 None: raw."""
    from labrunner.calibration.apply import compensate_data, read_model
    from labrunner.calibration.records import frame_arrays, reference_values
    from labrunner.campaign_csv import OUTPUT_COLUMNS

    a = frame_arrays(frame)
    if model_path is not None:
        out = compensate_data(read_model(model_path), frame).frame
        y = np.column_stack([out[c + "_comp"].to_numpy(dtype=float) for c in OUTPUT_COLUMNS])
    elif px4 is not None:
        y = px4.compensate_rows(a["y"], a["temp"], a["orientation"])
    else:
        y = a["y"]
    err = y - reference_values(a["orientation"], a["rate"])
    keep = labels >= 0
    n = int(labels.max()) + 1
    cnt = np.bincount(labels[keep], minlength=n)
    mean = np.column_stack([np.bincount(labels[keep], weights=err[keep, j], minlength=n) for j in range(6)])
    mean = mean[cnt > 0] / cnt[cnt > 0, None]
    return _rms(mean[:, :3]), _rms(mean[:, 3:])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--only", default="strict,fast,ramp", help="campaigns to run, from strict,fast,ramp")
    ap.add_argument("--refit", action="store_true",
                    help="with --workdir: fit the kept campaigns of --only again with the current code")
    ap.add_argument("--hog", action="store_true", help="run beside a process hogging one core")
    args = ap.parse_args()
    unknown = [n for n in args.only.split(",") if n and n not in CAMPAIGNS]
    if unknown:
        ap.error(f"--only: unknown campaign {unknown[0]!r}; expected some of {','.join(CAMPAIGNS)}")
    with cpu_hog(args.hog) as hog:
        if hog is not None:
            print(f"cpu hog: pid {hog} spinning on one core", flush=True)
        if args.workdir is not None:
            args.workdir.mkdir(parents=True, exist_ok=True)
            return bench(args, args.workdir)
        with tempfile.TemporaryDirectory(prefix="labrunner-chamber-time-") as tmp:
            return bench(args, Path(tmp))


# Issue 16's targets: lab time, and held-out error against the strict campaign's (each column).
FAST_MAX_H = 4 * 24.0
FAST_ERROR_RATIO = 1.05
RAMP_MAX_H = 1.5 * 24.0
RAMP_ERROR_RATIO = 1.10
COLUMNS = ("soaks accel", "soaks gyro", "heating accel", "heating gyro")
UNITS = ("mg", "deg/s", "mg", "deg/s")


def bench(args: argparse.Namespace, work: Path) -> int:
    from labrunner.calibration.px4_reference import fit_px4
    from labrunner.calibration.records import frame_arrays
    from labrunner.data_source import load_campaign_data

    sim = work / "sim.json"
    sim.write_text(json.dumps({"seed": args.seed, "imu_model": {"effects": IMU_EFFECTS}}))
    names = [n for n in args.only.split(",") if n]
    runs = [run_campaign(n, _shipped(CAMPAIGNS[n]), work, sim, args.seed, args.refit) for n in names]
    held = [run_campaign("heldout_soaks", HELDOUT_SOAKS, work, sim, args.seed + 100),
            run_campaign("heldout_heating", HELDOUT_HEATING, work, sim, args.seed + 101)]
    frames = {h.name: load_campaign_data(h.db).frame for h in held}
    labels = {h.name: record_labels(h.db, frames[h.name]) for h in held}
    px4 = None
    ramp = next((r for r in runs if r.name == "ramp"), None)
    if ramp is not None:
        f = load_campaign_data(ramp.db).frame
        a = frame_arrays(f)
        px4 = fit_px4(a, np.ones(len(f), bool))

    print(f"work: {work if args.workdir else '(temporary)'}  (seed {args.seed}; IMU effects: "
          f"{', '.join(IMU_EFFECTS)}); {load_line()}")
    head = f"{'campaign':<12}{'lab h':>8}{'lab days':>9}{'samples':>13}{'wall s':>8}"
    cols = "".join(f"{h + ' ' + t:>22}" for h in ("soaks", "heating") for t in ("accel mg", "gyro dps"))
    print(head + cols)

    def row(label: str, lab_h: float | None, samples: int | None, wall: float | None, errs: list[float]) -> None:
        left = (f"{label:<12}{lab_h:>8.1f}{lab_h / 24:>9.2f}{samples:>13,}{wall:>8.0f}" if lab_h is not None
                else f"{label:<12}{'':>8}{'':>9}{'':>13}{'':>8}")
        print(left + "".join(f"{v:>22.4f}" for v in errs))

    def errs_for(model: Path | None, p4=None) -> list[float]:
        out: list[float] = []
        for name in ("heldout_soaks", "heldout_heating"):
            acc, gyr = heldout_errors(model, p4, frames[name], labels[name])
            out += [acc * 1000.0, gyr]
        return out

    row("raw", None, None, None, errs_for(None))
    results = {}
    lagged: list[str] = []
    for r in runs:
        e = errs_for(r.fit_dir / "polynomial.json")
        results[r.name] = (r, e)
        row(r.name, r.lab_h, r.samples, r.wall_s, e)
        tau = _filter_tau(r.fit_dir / "polynomial.json")
        if tau is not None:
            lagged.append(f"{r.name} (tau {tau:.0f} s)")
    px4_errs = errs_for(None, px4) if px4 is not None else None
    if px4_errs is not None:
        row("px4 (ramp)", None, None, None, px4_errs)
    print("temperatures scored: " + (f"lag-corrected for {', '.join(lagged)} (the model's temperature_filter), "
                                     if lagged else "") + "the logged sensor temperature for the others and for "
          "px4 (PX4 has the sensor's temperature only; fitted on the ramp's logged temperature too)")
    base = results.get("strict")
    if base is not None:
        for name, (r, e) in results.items():
            if name == "strict":
                continue
            ratios = ", ".join(f"{v / b:.3f}" for v, b in zip(e, base[1], strict=True))
            print(f"{name} / strict: lab time {r.lab_h / base[0].lab_h:.3f}, held-out error ratios {ratios}")

    print("targets (issue 16):")
    for name, max_h, max_ratio in (("fast", FAST_MAX_H, FAST_ERROR_RATIO), ("ramp", RAMP_MAX_H, RAMP_ERROR_RATIO)):
        if name not in results:
            continue
        r, e = results[name]
        report(f"{name} lab time", r.lab_h, max_h, "lab h")
        if base is not None:
            for col, v, b in zip(COLUMNS, e, base[1], strict=True):
                report(f"{name} {col} error / strict", v / b, max_ratio, "x")
        if px4_errs is not None:
            for col, unit, v, p in zip(COLUMNS, UNITS, e, px4_errs, strict=True):
                report(f"{name} {col} error (< px4)", v, p, unit)
    return 0


if __name__ == "__main__":
    sys.exit(main())
