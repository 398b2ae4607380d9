"""The full paper campaign as a dry run in virtual time, and the logging path against raw SQLite.

Usage: python bench/bench_campaign.py [--procedure procedures/paper_campaign.yaml] [--db PATH] [--keep]

Prints the wall time of the whole dry run (sequencer + drivers + simulated lab over
sockets + store), samples per second, and the logging path's rate compared with raw
`sqlite3.executemany` of the same rows (one row per sample, tuples) measured in the
same run on the same machine. Targets (issue 3): the four-day campaign (~12 M
samples) in under 3 minutes, logging at no less than half the raw SQLite rate.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def raw_sqlite_rate(frame_rows: list[tuple], path: Path) -> float:
    """Rows per second for plain executemany of tuples into a fresh WAL database."""
    if path.exists():
        path.unlink()
    conn = sqlite3.connect(path)
    conn.execute("PRAGMA journal_mode=WAL")
    conn.execute("PRAGMA synchronous=NORMAL")
    conn.execute("CREATE TABLE samples (step INTEGER, t REAL, ax REAL, ay REAL, az REAL, gx REAL, gy REAL, gz REAL, "
                 "temp REAL, counter INTEGER)")
    per_step = 3000
    t0 = time.perf_counter()
    for i in range(0, len(frame_rows), per_step):
        conn.executemany("INSERT INTO samples VALUES (?,?,?,?,?,?,?,?,?,?)", frame_rows[i:i + per_step])
        conn.commit()  # committed per record step, like the logging path
    dt = time.perf_counter() - t0
    conn.close()
    return len(frame_rows) / dt


def logging_path_rate(store_path: Path, n_steps: int) -> tuple[float, int]:
    """Samples per second through Store.commit_record (the sequencer's logging path) for real record blocks."""
    from labrunner.store import SampleBlock, Store

    rng = np.random.default_rng(0)
    store = Store.create(store_path)

    class _S:
        def __init__(self, i: int) -> None:
            self.index, self.orientation, self.temperature_c, self.rate_dps = i, "z_up", 25.0, 10.0

    cid = store.new_campaign(name="bench", procedure_text="x", procedure_path=None, procedure_sha256="x",
                             lab_config={}, mode="sim", sim_config=None, clock_t0=0.0,
                             plan=[_S(i) for i in range(n_steps)])
    blocks = []
    for i in range(n_steps):
        n = 3000
        blocks.append(SampleBlock(kind="record", step_idx=i, run=1, orientation="z_up", t0_s=i * 70.0, rate_hz=50.0,
                                  counter=np.arange(n) + i * 3500, accel_g=rng.normal(size=(n, 3)),
                                  gyro_dps=rng.normal(size=(n, 3)), temp_c=rng.normal(size=n),
                                  chamber=np.array([[0.0, 25.0], [60.0, 25.0]]), table=np.array([[0.0, 10.0]])))
    t0 = time.perf_counter()
    for b in blocks:
        store.commit_record(cid, b, dropped=0, corrupt=0, t_end=b.t0_s + 60, event_message="bench")
    dt = time.perf_counter() - t0
    store.close()
    return n_steps * 3000 / dt, n_steps * 3000


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--procedure", default=str(ROOT / "procedures" / "paper_campaign.yaml"))
    ap.add_argument("--db", default=None)
    ap.add_argument("--keep", action="store_true", help="keep the database (e.g. for bench_fit.py --data)")
    ap.add_argument("--skip-run", action="store_true", help="only the logging comparison")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="labrunner-bench-"))
    db = Path(args.db) if args.db else tmp / "campaign.db"

    if not args.skip_run:
        if db.exists():
            db.unlink()
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "labrunner.cli", "run", args.procedure, "--sim", "--db", str(db),
                               "--quiet"], capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            print(proc.stderr[-3000:])
            raise SystemExit(f"dry run failed with exit code {proc.returncode}")
        from labrunner.store import Store

        with Store.open_existing(db) as store:
            cid = store.resolve(None)
            steps = store.steps_frame(cid)
            samples = int(steps.n_samples.sum())
            lab_h = (store.campaign(cid).clock_last - store.campaign(cid).clock_t0) / 3600
        size_mb = db.stat().st_size / 1e6
        print(f"dry run of {Path(args.procedure).name}: {len(steps)} steps, {samples:,} samples, "
              f"{lab_h:.1f} h of lab time ({lab_h / 24:.2f} days)")
        print(f"  wall time {wall:.1f} s  ->  {samples / wall:,.0f} samples/s end to end, "
              f"realtime factor {lab_h * 3600 / wall:,.0f}x; database {size_mb:.0f} MB")
        print(f"  target: under 180 s -> {'OK' if wall < 180 else 'MISSED'}")

    n_steps = 400  # 1.2 M samples: enough for stable rates
    log_rate, n = logging_path_rate(tmp / "log.db", n_steps)
    rng = np.random.default_rng(1)
    rows = [(i // 3000, i * 0.02, *map(float, rng.normal(size=7)), i) for i in range(n)]
    raw_rate = raw_sqlite_rate(rows, tmp / "raw.db")
    print(f"logging path (Store.commit_record, blobs per record step): {log_rate:,.0f} samples/s")
    print(f"raw sqlite3.executemany of the same rows (tuples, committed per step): {raw_rate:,.0f} rows/s")
    print(f"  ratio logging/raw = {log_rate / raw_rate:.2f} (target >= 0.5)")
    if not args.keep and not args.db:
        shutil.rmtree(tmp)  # the database, its WAL files and the <db>_fit/ folder of the end-of-run fit
    elif args.keep:
        print(f"  database kept: {db}")


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
