"""Benchmark (issue 15, target 4): loading a campaign at the limit of the raw read.

    python bench/bench_load.py --data paper.db          # a recorded store (default: /tmp/paper/paper.db)
    python bench/bench_load.py --data paper.db --csv-rows 2000000 --repeat 3

Store: `load_campaign_data(DB)` (what `labrunner fit` reads: samples, validation, power-on marks)
against the raw read of the same record blobs (SQL fetch and `np.frombuffer` of every counter,
accelerometer, gyro and temperature blob, nothing decoded). CSV: the store's first `--csv-rows`
rows written as a campaign CSV in a temporary directory, `read_campaign(CSV)` against
`pandas.read_csv` of the same file. Runs alternate (raw, ours, raw, ours, ...) so both see the same
load; medians are compared. Limit: 2.0 for both. The temporary directory is removed at the end.
"""

from __future__ import annotations

import argparse
import shutil
import sqlite3
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import load_line, report  # noqa: E402
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


def paired(a: Callable[[], object], b: Callable[[], object], repeat: int) -> tuple[float, float]:
    """Median wall times of a and b, run alternately."""
    ta: list[float] = []
    tb: list[float] = []
    for _ in range(repeat):
        for f, out in ((a, ta), (b, tb)):
            t = time.perf_counter()
            f()
            out.append(time.perf_counter() - t)
    return statistics.median(ta), statistics.median(tb)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="/tmp/paper/paper.db", help="a labrunner SQLite store (a recorded campaign)")
    ap.add_argument("--csv-rows", type=int, default=2_000_000, help="rows of the store written to the CSV")
    ap.add_argument("--repeat", type=int, default=3, help="paired runs of each (medians compared)")
    args = ap.parse_args()
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
    t_raw, t_ours = paired(lambda: raw_blob_read(db, cid), lambda: load_campaign_data(db), args.repeat)
    print(f"store: raw blob read {t_raw:.2f} s, load_campaign_data {t_ours:.2f} s")
    results = [report("store load / raw blob read", t_ours / t_raw, LIMIT, "x")]

    tmp = Path(tempfile.mkdtemp(prefix="bench_load_"))
    try:
        import pandas as pd

        csv = tmp / "campaign.csv"
        frame = load_campaign_data(db).frame.iloc[:args.csv_rows]
        write_campaign(frame, csv)
        del frame
        print(f"csv {csv}: {min(n, args.csv_rows):,} rows, {csv.stat().st_size / 1e6:.0f} MB")
        t_pd, t_csv = paired(lambda: pd.read_csv(csv), lambda: read_campaign(csv), args.repeat)
        print(f"csv: pandas.read_csv {t_pd:.2f} s, read_campaign {t_csv:.2f} s")
        results.append(report("csv load / pandas.read_csv", t_csv / t_pd, LIMIT, "x"))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(load_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
