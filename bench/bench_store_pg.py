"""A paper-size campaign's sample stream stored in PostgreSQL and in SQLite, in the same run.

Usage: nice python bench/bench_store_pg.py [--procedure procedures/paper_campaign.yaml] [--steps N] [--hog]

The paper campaign's plan (4080 record steps of 3000 samples: 12.24 M samples) goes through the real
store write path as the sequencer drives it: `Store.commit_record` per record step (int16 counts with
their LSBs, the step's status and event in one transaction, the lease renewed in it) and, between the
steps, `Store.save_monitor` for the ramp and soak stretches (one block of 1 s means per chamber poll,
as many as the procedure's estimated ramp and soak time holds). PostgreSQL is a throwaway cluster
started by the tests' helper (tests/pg_server.py) with its durable defaults (fsync, synchronous
commit); SQLite is the store's own configuration (WAL, synchronous=NORMAL). Prints samples/s for both
and the ratio, then deletes both databases and stops the server. Exit 0 unless something fails.

Targets (issue 15 measured 4.1 M samples/s for SQLite and called it good; this bench holds that line):
SQLite >= 4 M record samples/s, PostgreSQL >= half of SQLite's rate. `--hog` stores beside a process
spinning on one core.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # tests.pg_server: the same cluster helper as the tests

from bench.common import cpu_hog, load_line, report  # noqa: E402

LSB = (0.001, 0.00875, 0.01)  # accel g, gyro deg/s, temperature C per count, as the simulated IMU's


def _blocks(n: int, kinds: int = 8) -> list[dict[str, np.ndarray]]:
    """A few distinct sample sets in whole counts (reused: generating 12 M random samples is not the bench)."""
    rng = np.random.default_rng(0)
    out = []
    for _ in range(kinds):
        counts = rng.integers(-20000, 20000, size=(n, 7))
        out.append({"accel": counts[:, :3] * LSB[0], "gyro": counts[:, 3:6] * LSB[1], "temp": counts[:, 6] * LSB[2]})
    return out


def record_campaign(db: str, procedure_path: Path, n_steps: int | None) -> tuple[float, int, int, int]:
    """Store the campaign through the store's write path; returns (seconds, record samples, monitor rows,
    transactions)."""
    from labrunner.procedure import load_procedure
    from labrunner.runner.lease import new_token
    from labrunner.store import SampleBlock, Store

    proc = load_procedure(procedure_path)
    plan = proc.steps()[:n_steps] if n_steps else proc.steps()
    n = proc.frames_per_record
    rate = proc.model.sample_rate_hz
    poll_s = proc.model.soak.poll_s
    # Ramp and soak time the sequencer spends monitoring: the estimate, less the time records and settles take.
    busy_s = len(proc.steps()) * (proc.model.record_s + proc.model.settle_s)
    monitor_blocks = max(0, int((proc.estimated_duration_s() - busy_s) / poll_s)) * len(plan) // len(proc.steps())
    per_gap = monitor_blocks / max(len(plan), 1)
    pool = _blocks(n)
    m = int(poll_s)
    mon = _blocks(m, kinds=2)
    store = Store.create(db)
    cid = store.new_campaign(name=proc.name, procedure_text=proc.text, procedure_path=None,
                             procedure_sha256=proc.sha256, lab_config={}, mode="sim", sim_config=None, clock_t0=0.0,
                             plan=plan, lease_token=new_token())
    t = 0.0
    owed = 0.0
    monitor_rows = transactions = 0
    start = time.perf_counter()
    for k, step in enumerate(plan):
        owed += per_gap
        while owed >= 1.0:  # the ramp/soak before this step, poll by poll
            owed -= 1.0
            s = mon[transactions % 2]
            store.save_monitor(cid, SampleBlock(
                kind="monitor", step_idx=None, run=1, orientation=step.orientation, t0_s=t, rate_hz=1.0,
                counter=np.arange(m), accel_g=s["accel"], gyro_dps=s["gyro"], temp_c=s["temp"],
                chamber=np.array([[t, step.temperature_c], [t + m, step.temperature_c]]), table=np.array([[t, 0.0]])))
            t += poll_s
            monitor_rows += m
            transactions += 1
        s = pool[k % len(pool)]
        block = SampleBlock(kind="record", step_idx=step.index, run=1, orientation=step.orientation, t0_s=t,
                            rate_hz=rate, counter=np.arange(n) + int(t * rate), accel_g=s["accel"],
                            gyro_dps=s["gyro"], temp_c=s["temp"],
                            chamber=np.array([[t, step.temperature_c], [t + n / rate, step.temperature_c]]),
                            table=np.array([[t, step.rate_dps]]), lsb=LSB)
        t += n / rate
        store.commit_record(cid, block, dropped=0, corrupt=0, t_end=t, event_message=f"step {step.index} recorded")
        transactions += 1
    elapsed = time.perf_counter() - start
    assert store.next_step(cid) is None  # every step stored
    store.close()
    return elapsed, len(plan) * n, monitor_rows, transactions


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--procedure", type=Path, default=ROOT / "procedures" / "paper_campaign.yaml")
    ap.add_argument("--steps", type=int, default=None, help="only the first N record steps (default: all)")
    ap.add_argument("--hog", action="store_true", help="run beside a process spinning on one core")
    args = ap.parse_args()
    from tests.pg_server import pg_bin, start_server

    if pg_bin() is None:
        print("bench_store_pg: no PostgreSQL 15+ binaries (/usr/lib/postgresql/<major>/bin or LABRUNNER_PG_BIN)",
              file=sys.stderr)
        return 1
    tmp = Path(tempfile.mkdtemp(prefix="labrunner-bench-pg-"))
    server = None
    try:
        server = start_server(durable=True)
        url = server.url(server.new_database("bench"))
        results = {}
        with cpu_hog(args.hog):
            for name, db in (("PostgreSQL", url), ("SQLite", str(tmp / "bench.db"))):
                seconds, samples, monitor_rows, transactions = record_campaign(db, args.procedure, args.steps)
                results[name] = samples / seconds
                print(f"{name:10s}: {samples:,} record samples + {monitor_rows:,} monitor rows in "
                      f"{transactions:,} transactions, {seconds:.1f} s -> {samples / seconds:,.0f} samples/s "
                      f"[{load_line()}{', CPU hog' if args.hog else ''}]")
        report("SQLite store writes", results["SQLite"], 4e6, "samples/s", lower_is_better=False)
        report("PostgreSQL/SQLite write rate", results["PostgreSQL"] / results["SQLite"], 0.5, "x",
               lower_is_better=False)
    finally:
        if server is not None:
            server.destroy()
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
