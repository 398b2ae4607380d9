"""Benchmark (issue 15, target 4): loading a campaign at the limit of the raw read.

    python bench/bench_load.py --data paper.db          # a recorded store (default: /tmp/paper/paper.db)
    python bench/bench_load.py --data paper.db --csv-rows 2000000 --repeat 3

Store: `load_campaign_data(DB)` (what `labrunner fit` reads: the open's damage check, samples with the IMU
channels kept as int16 counts and the chamber column, validation, steps, events, power-on marks) against
the floor of the same read: the SQL fetch of the record blobs and the columns the fit reads built from
them in their stored types (the int16 counts of each channel; the float64 time axis from the counters;
the table rate per row from its readings; run and orientation per row), no frame, no validation, no
chamber column. The bare fetch (`np.frombuffer` views of every blob, nothing copied) is printed too.
The store ratio is of CPU time (user + sys of this process: the waits of a busy machine are not the
reader's cost); the sys part (the kernel's page faults for fresh memory, which a busy machine varies
most) and wall times are printed beside it. CSV: the store's first `--csv-rows` rows written as a
campaign CSV in a temporary directory, `read_campaign(CSV)` against `pandas.read_csv` of the same file
(wall time). Runs alternate (floor, ours, floor, ours, ...) so both see the same load; medians are
compared. Limit: 2.0 for both. The temporary directory is removed at the end.
"""

from __future__ import annotations

import argparse
import resource
import shutil
import sqlite3
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import cpu_hog, load_line, report  # noqa: E402
from labrunner.campaign_csv import read_campaign, write_campaign  # noqa: E402
from labrunner.data_source import load_campaign_data  # noqa: E402

LIMIT = 2.0


def raw_blob_read(db: Path, campaign_id: int) -> int:
    """Fetch every record block's sample blobs and view them as arrays; returns the sample count."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        rows = con.execute("SELECT encoding, n, counter, accel_g, gyro_dps, temp_c FROM sample_blocks "
                           "WHERE campaign_id = ? AND kind = 'record' ORDER BY t0_s, id", (campaign_id,))
        total = 0
        for enc, n, counter, accel, gyro, temp in rows:
            dt = "<i2" if enc == "i16" else "<f4"
            np.frombuffer(counter, dtype="<i4")
            np.frombuffer(accel, dtype=dt).reshape(n, 3)
            np.frombuffer(gyro, dtype=dt).reshape(n, 3)
            np.frombuffer(temp, dtype=dt)
            total += n
        return total
    finally:
        con.close()


def column_floor(db: Path, campaign_id: int) -> int:
    """The record blobs fetched and made into the columns the fit reads, in their stored types (no frame,
    no validation, no chamber column): what any reader of this store must do; returns the sample count."""
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        (total,) = con.execute("SELECT coalesce(sum(n), 0) FROM sample_blocks WHERE campaign_id = ? "
                               "AND kind = 'record'", (campaign_id,)).fetchone()
        rows = con.execute('SELECT n, t0_s, rate_hz, run, orientation, counter, accel_g, gyro_dps, temp_c, "table" '
                           "FROM sample_blocks WHERE campaign_id = ? AND kind = 'record' ORDER BY t0_s, id",
                           (campaign_id,))
        t, rate = np.empty(total), np.empty(total)
        accel, gyro = np.empty((total, 3), dtype=np.int16), np.empty((total, 3), dtype=np.int16)
        temp, run = np.empty(total, dtype=np.int16), np.empty(total, dtype=np.int64)
        orient = np.empty(total, dtype=np.int8)
        labels: dict[str, int] = {}
        at = 0
        for n, t0, hz, r, o, counter, a, g, tc, table in rows:
            sl = slice(at, at + n)
            c = np.frombuffer(counter, dtype="<i4")
            t[sl] = t0 + (c - c[0]) / hz
            readings = np.frombuffer(table, dtype="<f8").reshape(-1, 2)
            if readings.shape[0] > 1:
                rate[sl] = np.interp(t[sl], readings[:, 0], readings[:, 1])
            else:
                rate[sl] = readings[0, 1] if readings.size else 0.0
            accel[sl] = np.frombuffer(a, dtype="<i2").reshape(n, 3)
            gyro[sl] = np.frombuffer(g, dtype="<i2").reshape(n, 3)
            temp[sl] = np.frombuffer(tc, dtype="<i2")
            run[sl] = r
            orient[sl] = labels.setdefault(o, len(labels))
            at += n
        return at
    finally:
        con.close()


@dataclass(frozen=True)
class Times:
    wall_s: float
    cpu_s: float  # user + sys
    sys_s: float  # of which the kernel's (page faults of fresh memory, file reads): the part a busy machine varies most

    def __str__(self) -> str:
        return f"{self.cpu_s:.2f} s CPU ({self.sys_s:.2f} s of it sys; {self.wall_s:.2f} s wall)"


def _clock() -> tuple[float, float, float]:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return time.perf_counter(), usage.ru_utime + usage.ru_stime, usage.ru_stime


def paired(a: Callable[[], object], b: Callable[[], object], repeat: int) -> tuple[Times, Times]:
    """Median wall, CPU and sys times of a and b, run alternately."""
    runs: tuple[list[tuple[float, ...]], list[tuple[float, ...]]] = ([], [])
    for _ in range(repeat):
        for f, out in zip((a, b), runs):
            start = _clock()
            f()
            out.append(tuple(e - s for e, s in zip(_clock(), start)))
    ta, tb = (Times(*(statistics.median(x[k] for x in out) for k in range(3))) for out in runs)
    return ta, tb


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="/tmp/paper/paper.db", help="a labrunner SQLite store (a recorded campaign)")
    ap.add_argument("--csv-rows", type=int, default=2_000_000, help="rows of the store written to the CSV")
    ap.add_argument("--repeat", type=int, default=3, help="paired runs of each (medians compared)")
    ap.add_argument("--hog", action="store_true", help="run beside a second process spinning on one core")
    args = ap.parse_args()
    with cpu_hog(args.hog) as hog:
        if hog is not None:
            print(f"cpu hog running (pid {hog})")
        return _bench(args)


def _bench(args: argparse.Namespace) -> int:
    db = Path(args.data)
    if not db.is_file():
        print(f"bench_load: {db}: no such store; record one (labrunner run procedures/paper_campaign.yaml --sim "
              f"--db {db}) or pass --data", file=sys.stderr)
        return 2
    print(load_line())
    data = load_campaign_data(db)
    cid = int(data.provenance["campaign_id"])
    n = raw_blob_read(db, cid)
    print(f"store {db}: campaign {cid}, {n:,} samples")
    del data
    t_bare, _ = paired(lambda: raw_blob_read(db, cid), lambda: None, args.repeat)
    t_floor, t_ours = paired(lambda: column_floor(db, cid), lambda: load_campaign_data(db), args.repeat)
    print(f"store: blob fetch alone {t_bare}; floor (fetch + the fit's columns in their stored types) {t_floor}; "
          f"load_campaign_data {t_ours}")
    results = [report("store load / floor (CPU)", t_ours.cpu_s / t_floor.cpu_s, LIMIT, "x")]
    print(f"store load / blob fetch alone (CPU, informative): {t_ours.cpu_s / t_bare.cpu_s:.2f}x")

    tmp = Path(tempfile.mkdtemp(prefix="bench_load_"))
    try:
        import pandas as pd

        csv = tmp / "campaign.csv"
        frame = load_campaign_data(db).frame.iloc[:args.csv_rows]
        write_campaign(frame, csv)
        del frame
        print(f"csv {csv}: {min(n, args.csv_rows):,} rows, {csv.stat().st_size / 1e6:.0f} MB")
        t_pd, t_csv = paired(lambda: pd.read_csv(csv), lambda: read_campaign(csv), args.repeat)
        print(f"csv: pandas.read_csv {t_pd}, read_campaign {t_csv}")
        results.append(report("csv load / pandas.read_csv", t_csv.wall_s / t_pd.wall_s, LIMIT, "x"))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(load_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
