"""The paper campaign as a dry run in virtual time (issue 15, target 1), and the logging path against raw SQLite.

Usage: python bench/bench_campaign.py [--procedure procedures/paper_campaign.yaml] [--no-fit] [--hog]
                                      [--skip-run] [--keep] [--workdir DIR]

Runs `labrunner run PROCEDURE --sim --db DB --quiet` as a child process and prints its wall time, CPU
time and peak RSS (the kernel's count for that child; and the largest PSS of its process tree, sampled
every 0.2 s, which counts the end-of-run fit's forked children with their shared pages once), the
recording's own wall time (the campaign summary's) and the lab time, against the targets of issue 15: the dry run,
end-of-run fit included, in at most 45 s wall on a quiet machine (load <= 2) and at most 1.5x that with a
second process hogging a core (`--hog`: the run is repeated beside bench.common.cpu_hog), peak RSS at most
500 MB. `--no-fit` times the recording alone (a copy of the procedure with `fit: {run: false}`).

Then the logging path's rate (`Store.commit_record` of real record blocks) against raw
`sqlite3.executemany` of the same rows, measured in the same run (issue 3: at least half the raw rate).

Everything is written in a temporary directory, deleted at the end unless --keep (or --workdir, which
is kept). Exit 0 when the bench ran (targets missed are printed as MISSED); 1 when the dry run failed.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sqlite3
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import CommandRun, cpu_hog, load_line, report, run_measured  # noqa: E402

WALL_LIMIT_S = 45.0  # the dry run, end-of-run fit included, load <= 2
HOG_FACTOR = 1.5  # with a CPU hog: no worse than this times the limit
RSS_LIMIT_MB = 500.0
LOGGING_RATIO_MIN = 0.5
_SUMMARY = re.compile(r"lab time ([\d.]+) h, wall ([\d.]+) s")


def raw_sqlite_rate(frame_rows: list[tuple], path: Path) -> float:
    """Rows per second for plain executemany of tuples into a fresh WAL database."""
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


def procedure_copy(procedure: Path, workdir: Path, fit: bool) -> Path:
    """The procedure as given, or a copy with the end-of-run fit switched off (the recording alone)."""
    if fit:
        return procedure
    data = yaml.safe_load(procedure.read_text())
    data["fit"] = {**(data.get("fit") or {}), "run": False}
    out = workdir / f"{procedure.stem}_nofit.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def dry_run(procedure: Path, db: Path, label: str) -> CommandRun:
    """One dry run in a child process; its cost, with the recording's wall time from the campaign summary."""
    for stale in db.parent.glob(db.name + "*"):
        stale.unlink()
    load = load_line()
    run = run_measured([sys.executable, "-m", "labrunner.cli", "run", str(procedure), "--sim", "--db", str(db),
                        "--quiet"], cwd=ROOT)
    m = run.measured
    if m.returncode != 0:
        print(run.stderr[-3000:])
        raise SystemExit(f"dry run ({label}) failed with exit code {m.returncode}")
    found = _SUMMARY.search(run.stderr)
    rec = f"; recording {found.group(2)} s wall for {found.group(1)} h of lab time" if found else ""
    print(f"dry run ({label}), {load} at the start: {m.line()}{rec}")
    return run


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--procedure", type=Path, default=ROOT / "procedures" / "paper_campaign.yaml")
    ap.add_argument("--no-fit", action="store_true", help="the recording alone (fit: {run: false} in a copy)")
    ap.add_argument("--hog", action="store_true", help="run again beside a process hogging one core")
    ap.add_argument("--skip-run", action="store_true", help="only the logging comparison")
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory (database, fit)")
    ap.add_argument("--workdir", type=Path, default=None, help="work here instead (kept)")
    args = ap.parse_args()

    if args.workdir is not None:
        args.workdir.mkdir(parents=True, exist_ok=True)
        work = args.workdir
    else:
        work = Path(tempfile.mkdtemp(prefix="labrunner-bench-"))
    try:
        if not args.skip_run:
            procedure = procedure_copy(args.procedure.resolve(), work, fit=not args.no_fit)
            what = "recording alone" if args.no_fit else "end-of-run fit included"
            quiet = dry_run(procedure, work / "campaign.db", f"{args.procedure.name}, {what}")
            from labrunner.store import Store

            with Store.open_existing(work / "campaign.db") as store:
                cid = store.resolve(None)
                samples = int(store.steps_frame(cid).n_samples.sum())
            q = quiet.measured
            print(f"  {samples:,} samples recorded -> {samples / q.wall_s:,.0f} samples/s end to end")
            report(f"dry run wall ({what})", q.wall_s, WALL_LIMIT_S, "s")
            report("dry run peak RSS", q.peak_rss_mb, RSS_LIMIT_MB, "MB")
            # The fit's forked children share the parent's pages: what the tree took, shared pages once.
            report("dry run peak PSS, process tree", q.peak_tree_pss_bytes / 1e6, RSS_LIMIT_MB, "MB")
            if args.hog:
                with cpu_hog():
                    busy = dry_run(procedure, work / "campaign_hog.db", f"{args.procedure.name}, {what}, CPU hog")
                b = busy.measured
                report("dry run wall beside a CPU hog", b.wall_s, HOG_FACTOR * WALL_LIMIT_S, "s")
                print(f"  busy/quiet wall ratio {b.wall_s / q.wall_s:.2f} (CPU {b.cpu_s:.1f} s vs {q.cpu_s:.1f} s)")

        n_steps = 400  # 1.2 M samples: enough for stable rates
        log_rate, n = logging_path_rate(work / "log.db", n_steps)
        rng = np.random.default_rng(1)
        rows = [(i // 3000, i * 0.02, *map(float, rng.normal(size=7)), i) for i in range(n)]
        raw_rate = raw_sqlite_rate(rows, work / "raw.db")
        print(f"logging path (Store.commit_record, blobs per record step): {log_rate:,.0f} samples/s; "
              f"raw sqlite3.executemany of the same rows (tuples, committed per step): {raw_rate:,.0f} rows/s")
        report("logging path / raw executemany", log_rate / raw_rate, LOGGING_RATIO_MIN, "x", lower_is_better=False)
    finally:
        if args.workdir is None and not args.keep:
            shutil.rmtree(work)  # the databases, their WAL files and the <db>_fit/ folders of the end-of-run fit
        else:
            print(f"  kept: {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
