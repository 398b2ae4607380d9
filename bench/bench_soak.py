"""A faulty night: a full-night dry run in virtual time with at least 100 random faults.

Usage: python bench/bench_soak.py [--faults 120] [--seed 7] [--hog] [--keep]

Runs the same night twice, fault-free and with N seeded random faults (auto-resuming
where the fault policy pauses, as the operator would), and prints faults injected,
faults survived, pauses resumed, steps recorded again, rows lost and rows duplicated
(each step's samples against the fault-free run, and record blocks per step).
Targets: at least 100 faults survived, no row lost, no row duplicated. `--hog` runs both
nights beside a process spinning on one core. The databases are deleted unless --keep.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sqlalchemy import text

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import cpu_hog, load_line, report  # noqa: E402

NIGHT = """\
name: night
description: a night of calibration steps (about 12 h of lab time)
temperatures: {list_c: [-10, 5, 20, 35, 50], order: serpentine}
soak: {tolerance_c: 0.3, stable_window_s: 300, max_wait_s: 5400, on_timeout: pause, sensor: imu, poll_s: 30}
orientations: [x_up, x_down, z_up]
remount_s: 300
rates: {triangular: {max_dps: 100, step_dps: 25}}
settle_s: 5
record_s: 30
record_poll_s: 10
faults: {policy: pause, max_dropped_frames: 0, max_rerecords: 3}
fit: {run: false}
"""


def run(args: list[str]) -> tuple[float, str]:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "labrunner.cli", *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"labrunner {' '.join(args)} exited {proc.returncode}:\n{proc.stderr[-3000:]}")
    return time.perf_counter() - t0, proc.stderr


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--faults", type=int, default=120)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--hog", action="store_true", help="run beside a process spinning on one core")
    ap.add_argument("--keep", action="store_true", help="keep the two databases")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="labrunner-soak-"))
    try:
        night(tmp, args)
    finally:
        if args.keep:
            print(f"kept: {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


def night(tmp: Path, args: argparse.Namespace) -> None:
    from labrunner.store import Store

    proc = tmp / "night.yaml"
    proc.write_text(NIGHT)
    with cpu_hog(args.hog):
        wall_clean, _ = run(["run", str(proc), "--sim", "--db", str(tmp / "clean.db"), "--quiet"])
        wall_faulty, err = run(["run", str(proc), "--sim", "--faults", str(args.faults), "--seed", str(args.seed),
                                "--db", str(tmp / "faulty.db"), "--quiet"])
    with Store.open_existing(tmp / "clean.db") as a, Store.open_existing(tmp / "faulty.db") as b:
        sa, sb = a.steps_frame(1).set_index("idx"), b.steps_frame(1).set_index("idx")
        ev = b.events_frame(1)
        info = b.campaign(1)
        hours = (info.clock_last - info.clock_t0) / 3600
        with b.engine.connect() as conn:
            blocks = conn.execute(text("SELECT step_idx, COUNT(*) FROM sample_blocks WHERE kind='record' "
                                       "GROUP BY step_idx")).fetchall()
        rows_faulty = len(b.samples_frame(1))
        rows_clean = len(a.samples_frame(1))
    per_step_lost = (sa.n_samples - sb.n_samples.reindex(sa.index).fillna(0)).clip(lower=0).sum()
    duplicated_blocks = sum(n - 1 for _, n in blocks if n > 1)
    duplicated_rows = max(0, rows_faulty - int(sb.n_samples.sum()))
    injected = int((ev.kind == "injected").sum())
    pauses = int(ev.message.str.contains("-> paused").sum())
    resumed = int(ev.message.str.contains("resuming after a fault pause").sum())
    survived = injected if info.status == "done" else 0
    print(f"night: {len(sa)} steps, {rows_clean:,} samples, {hours:.1f} h of lab time with faults "
          f"(wall {wall_clean:.1f} s clean, {wall_faulty:.1f} s faulty; {load_line()}"
          f"{', CPU hog' if args.hog else ''})")
    print(f"faults injected:        {injected}")
    print(f"faults survived:        {survived} (campaign {info.status}; {pauses} pauses, {resumed} auto-resumed)")
    print(f"fault/recovery events:  {int((ev.kind == 'fault').sum())} / {int((ev.kind == 'recovery').sum())}")
    print(f"steps recorded again:   {int((sb.attempts > 1).sum())} ({int(sb.attempts.sum() - len(sb))} extra attempts)")
    lost = int(per_step_lost) + max(0, rows_clean - rows_faulty)
    print(f"rows lost:              {lost}")
    print(f"rows duplicated:        {duplicated_rows + duplicated_blocks}")
    print(err.strip().splitlines()[-1] if err.strip() else "")
    report("faults survived", survived, 100, "faults", lower_is_better=False)
    report("rows lost", lost, 0, "rows")
    report("rows duplicated", duplicated_rows + duplicated_blocks, 0, "rows")


if __name__ == "__main__":
    sys.exit(main())
