"""Cost that grows no faster than the work: `fit`, `export` and `diagnose` on stores 1x to 10x the paper campaign.

Usage: python bench/bench_scaling.py [--scales 1,2,5,10] [--base-fraction 1.0] [--commands fit,export,diagnose]
                                     [--hog] [--keep] [--workdir DIR] [--max-rss-gb 10] [--seed 0]

The paper campaign (procedures/paper_campaign.yaml: 4080 record steps of 3000 samples, 12.24 M
samples) is synthesised once by the simulated lab's physics (sims.campaign.synthesize: the same
IMU model, temperatures, rates, six orientations, and the ramps and soaks as 1 s means), then
written into a store per scale through the store's real write path, as the sequencer writes a
dry run: `Store.commit_record` per record step (int16 counts with their LSBs), `Store.save_monitor`
per 30 s chamber poll of the ramps and soaks. Scale k keeps the plan (the same 4080 steps) and
makes every record k times as long (the synthesised record repeated), so 10x is 122.4 M samples;
the monitor rows stay those of one campaign. `--base-fraction F` makes the unit F of the paper
campaign (records of F x 60 s; for trying the bench out on small stores).

Each command runs as a child process (`labrunner fit DB --out DIR --json FILE --no-store`: the fit,
its evaluation and its exported model files; `labrunner export DB --csv FILE`; `labrunner diagnose
DB --json FILE`), timed with its CPU time and its own peak RSS. Printed per command: a line per
scale and the target lines (issue 15, target 3): the per-sample CPU time at the largest scale
against the smallest (limit 1.2: linear growth), the least-squares slope and intercept of CPU
time against samples, and the peak RSS at the largest scale against the smallest (limit 1.2:
flat memory). `--hog` runs every command a second time beside a process spinning on one core
and prints the busy/quiet wall-time ratio (target 1: no worse than 1.5x).

A scale whose projected peak RSS (extrapolated from the scales measured before it, linearly
through the last two; proportional to the samples from one) would exceed the memory bound (the
smaller of --max-rss-gb and 90 % of the memory available now) is skipped with a message, and a
command is killed if its resident memory passes that bound anyway.

With --workdir DIR the stores are built in DIR and stay there: a later run with the same scale,
unit, seed and procedure reuses them (each store's manifest, written when its build finished,
records what it holds), so several command sets pay for one build. Building is never part of a
command's figures (each command is a separate child process, started after its store is complete
and read through once, so reused and fresh stores start equally warm). Without --workdir the
stores live in a temporary directory deleted at the end unless --keep; the commands' outputs
(model files, JSON, the exported CSV) are deleted after each command unless --keep. Exit 0 when
the bench ran (targets missed are printed as MISSED); non-zero when a command failed or nothing
could be measured.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import shutil
import signal
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import (  # noqa: E402
    Measured,
    available_memory_bytes,
    cpu_hog,
    load_line,
    report,
    run_measured,
)

log = logging.getLogger("bench_scaling")

LSB = (0.001, 0.00875, 0.01)  # accel g, gyro deg/s, temperature C per count: the simulated IMU's
COMMANDS = ("fit", "export", "diagnose")
COUNT_LSB = np.array(LSB)[[0, 0, 0, 1, 1, 1, 2]]  # per column of (accel xyz, gyro xyz, temp)
MEMORY_SHARE = 0.9  # of MemAvailable a command may be projected (and allowed) to take
MAX_RSS_GB = 10.0  # and never more than this: the machine is shared with others' 2 GB fits
MANIFEST = "store.json"  # beside a finished store: what it holds (a store without one is rebuilt)


@dataclass
class Campaign:
    """One synthesised campaign in compact form: records and the monitor rows before each."""

    records: list[np.ndarray]  # per synthesised record: (n, 7) float (accel g, gyro deg/s, temp C)
    record_chamber: np.ndarray  # (records, 2): chamber C at the record's start and end
    record_run: np.ndarray  # (records,) int
    record_key: dict[tuple[str, float, int], int]  # (orientation, setpoint C, rate index) -> record index
    rates: list[float]  # the rate schedule (a triangular one holds each rate twice: keyed by position)
    gaps: list[tuple[np.ndarray, np.ndarray, int, str]]  # before record k: (rows (m, 7), chamber (m,), run, orient)
    rate_hz: float


def synthesise(base_fraction: float, seed: int) -> Campaign:
    """The paper campaign by the simulated lab's physics, records of `base_fraction` x 60 s."""
    from labrunner.sims.campaign import CampaignPlan, synthesize, triangular_rates
    from labrunner.sims.world import SimLabConfig

    temps = [float(t) for t in range(-25, 56, 5)]
    rates = triangular_rates(100.0, 10.0)
    plan = CampaignPlan(temperatures_c=temps, rates_dps=rates, record_s=60.0 * base_fraction, log_ramps=True,
                        ramp_row_s=1.0)
    frame = synthesize(plan, SimLabConfig(seed=seed))
    t = frame["t_s"].to_numpy()
    values = frame[["ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps", "imu_temp_c"]].to_numpy()
    chamber = frame["chamber_c"].to_numpy()
    run = frame["run"].to_numpy()
    orient = frame["orientation"].astype(str).to_numpy()
    del frame
    # Record rows are 1/fs apart, ramp and soak rows 1 s: a row is a record's when a neighbour is close.
    dt = np.diff(t)
    close = dt < 0.5 / plan.ramp_row_s
    is_rec = np.zeros(t.size, dtype=bool)
    is_rec[:-1] |= close
    is_rec[1:] |= close
    edges = np.flatnonzero(np.diff(np.concatenate([[0], is_rec.astype(np.int8), [0]])))
    starts, stops = edges[::2], edges[1::2]
    keys = [(o, temp, j) for i, o in enumerate(plan.orientations)
            for temp in (sorted(temps)[::-1] if i % 2 else sorted(temps)) for j in range(len(rates))]
    if len(starts) != len(keys):
        raise RuntimeError(f"synthesised campaign: {len(starts)} records found, {len(keys)} expected")
    records, gaps = [], []
    prev = 0
    for a, b in zip(starts, stops):
        counts = np.rint(values[a:b] / COUNT_LSB)  # whole counts, as stored
        records.append(counts.astype(np.int16))
        gaps.append((values[prev:a].astype(np.float32), chamber[prev:a], int(run[a]), str(orient[a])))
        prev = b
    return Campaign(records=records, record_chamber=np.column_stack([chamber[starts], chamber[stops - 1]]),
                    record_run=run[starts].astype(int), record_key={k: i for i, k in enumerate(keys)},
                    rates=list(rates), gaps=gaps,
                    rate_hz=plan.sample_rate_hz)


def build_store(db: Path, campaign: Campaign, scale: float, procedure: Path) -> tuple[int, int]:
    """Write the campaign at `scale` into a new store through the sequencer's write calls; returns
    (record samples, monitor rows)."""
    from labrunner.procedure import load_procedure
    from labrunner.runner.lease import new_token
    from labrunner.store import SampleBlock, Store

    proc = load_procedure(procedure)
    plan = proc.steps()
    poll_s = int(proc.model.soak.poll_s)
    rate = campaign.rate_hz
    store = Store.create(db)
    cid = store.new_campaign(name=proc.name, procedure_text=proc.text, procedure_path=str(procedure),
                             procedure_sha256=proc.sha256, lab_config={}, mode="sim", sim_config=None, clock_t0=0.0,
                             plan=plan, lease_token=new_token())
    t = 0.0
    samples = monitor_rows = 0
    used: set[int] = set()
    for step in plan:
        k = campaign.record_key.get((step.orientation, float(step.temperature_c), step.rate_index))
        if k is None or campaign.rates[step.rate_index] != step.rate_dps:
            raise RuntimeError(f"{procedure}: step {step.index} ({step.orientation}, {step.temperature_c} C, "
                               f"{step.rate_dps} deg/s) is not in the synthesised paper campaign")
        if k in used:
            raise RuntimeError(f"{procedure}: step {step.index} repeats a record of the synthesised campaign")
        used.add(k)
        rows, chamber, run, orient = campaign.gaps[k]
        for a in range(0, len(rows), poll_s):  # the ramp/soak before the step, one block per chamber poll
            part = rows[a:a + poll_s].astype(float)
            m = len(part)
            store.save_monitor(cid, SampleBlock(
                kind="monitor", step_idx=None, run=run, orientation=orient, t0_s=t, rate_hz=1.0,
                counter=np.arange(m), accel_g=part[:, :3], gyro_dps=part[:, 3:6], temp_c=part[:, 6],
                chamber=np.array([[t, chamber[a]], [t + m - 1, chamber[a + m - 1]]]), table=np.array([[t, 0.0]])))
            t += m
            monitor_rows += m
        base = campaign.records[k]
        n = int(round(len(base) * scale))
        counts = base[np.arange(n) % len(base)]  # the record repeated to k times its length
        values = counts * COUNT_LSB
        c0, c1 = campaign.record_chamber[k]
        block = SampleBlock(kind="record", step_idx=step.index, run=int(campaign.record_run[k]),
                            orientation=step.orientation, t0_s=t, rate_hz=rate,
                            counter=np.arange(n) + int(round(t * rate)), accel_g=values[:, :3],
                            gyro_dps=values[:, 3:6], temp_c=values[:, 6],
                            chamber=np.array([[t, c0], [t + n / rate, c1]]), table=np.array([[t, step.rate_dps]]),
                            lsb=LSB)
        t += n / rate
        store.commit_record(cid, block, dropped=0, corrupt=0, t_end=t, event_message=f"step {step.index} recorded")
        samples += n
    store.set_status(cid, "done", clock_last=t, pid=None)
    store.release_lease(cid)
    store.close()
    return samples, monitor_rows


@dataclass(frozen=True)
class StoreSpec:
    """What a built store holds: a store is reused only when all of it matches."""

    scale: float
    base_fraction: float
    seed: int
    procedure_sha256: str

    def dirname(self) -> str:
        return f"scale_{self.scale:g}x_unit_{self.base_fraction:g}_seed_{self.seed}"


def procedure_sha256(procedure: Path) -> str:
    return hashlib.sha256(procedure.read_bytes()).hexdigest()


def reusable_store(where: Path, spec: StoreSpec) -> tuple[int, int] | None:
    """(record samples, monitor rows) of the finished store in `where` built for `spec`, or None."""
    db, manifest = where / "campaign.db", where / MANIFEST
    try:
        info = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return None
    if (info.get("spec") != spec.__dict__ or not db.exists() or db.stat().st_size != info.get("db_bytes")):
        return None
    return int(info["samples"]), int(info["monitor_rows"])


def write_manifest(where: Path, spec: StoreSpec, samples: int, monitor_rows: int, build_s: float) -> None:
    db = where / "campaign.db"
    (where / MANIFEST).write_text(json.dumps({"spec": spec.__dict__, "samples": samples,
                                              "monitor_rows": monitor_rows, "db_bytes": db.stat().st_size,
                                              "build_s": round(build_s, 1)}, indent=1))


def read_through(path: Path) -> None:
    """Read a file once so the commands after it find it in the page cache, built now or long ago."""
    with path.open("rb") as f:
        while f.read(16 << 20):
            pass


def command_line(name: str, db: Path, out: Path) -> list[str]:
    cli = [sys.executable, "-m", "labrunner.cli"]
    if name == "fit":
        return [*cli, "fit", str(db), "--out", str(out / "fit"), "--json", str(out / "fit.json"), "--no-store",
                "--quiet", "--force"]
    if name == "export":
        return [*cli, "export", str(db), "--csv", str(out / "export.csv"), "--force"]
    return [*cli, "diagnose", str(db), "--json", str(out / "diagnosis.json"), "--force"]


def projected_rss(history: list[tuple[int, int]], samples: int) -> int | None:
    """Peak RSS expected at `samples` from (samples, peak RSS) measured before: the line through the last
    two points (never below the last), or proportional to the samples from one point."""
    if not history:
        return None
    if len(history) == 1:
        s0, r0 = history[0]
        return int(r0 * samples / s0)
    (s0, r0), (s1, r1) = history[-2], history[-1]
    slope = max(0.0, (r1 - r0) / (s1 - s0)) if s1 != s0 else 0.0
    return int(max(r1, r1 + slope * (samples - s1)))


@dataclass
class Row:
    scale: float
    samples: int
    quiet: Measured
    hogged: Measured | None


def run_command(cmd: list[str], hog: bool, limit: int) -> Measured:
    with cpu_hog(hog):
        done = run_measured(cmd, memory_limit_bytes=limit)
    if done.killed_for_memory:
        raise MemoryError(f"killed when its resident memory passed the bound {limit / 1e9:.1f} GB")
    if done.measured.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[2:])} exited {done.measured.returncode}:\n{done.stderr[-3000:]}")
    return done.measured


def summarise(name: str, rows: list[Row]) -> None:
    if len(rows) < 2:
        print(f"{name}: fewer than two scales measured; no growth figures")
        return
    lo, hi = rows[0], rows[-1]
    s = np.array([r.samples for r in rows], dtype=float)
    cpu = np.array([r.quiet.cpu_s for r in rows])
    slope, intercept = np.polyfit(s, cpu, 1)
    fitted = slope * s + intercept
    r2 = 1 - float(np.sum((cpu - fitted) ** 2)) / max(float(np.sum((cpu - cpu.mean()) ** 2)), 1e-12)
    print(f"{name}: CPU time = {intercept:.2f} s + {slope * 1e6:.3f} s per M samples (R^2 {r2:.3f}); "
          f"wall per M samples {lo.quiet.wall_s / lo.samples * 1e6:.3f} s at {lo.scale:g}x, "
          f"{hi.quiet.wall_s / hi.samples * 1e6:.3f} s at {hi.scale:g}x")
    per_lo, per_hi = lo.quiet.cpu_s / lo.samples, hi.quiet.cpu_s / hi.samples
    report(f"{name} CPU per sample {hi.scale:g}x/{lo.scale:g}x", per_hi / per_lo, 1.2, "x")
    report(f"{name} peak RSS {hi.scale:g}x/{lo.scale:g}x", hi.quiet.peak_rss_bytes / lo.quiet.peak_rss_bytes, 1.2,
           "x")
    if lo.quiet.peak_tree_pss_bytes and hi.quiet.peak_tree_pss_bytes:  # the fit's forked children counted
        report(f"{name} peak tree PSS {hi.scale:g}x/{lo.scale:g}x",
               hi.quiet.peak_tree_pss_bytes / lo.quiet.peak_tree_pss_bytes, 1.2, "x")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scales", default="1,2,5,10", help="comma-separated multiples of the unit (default 1,2,5,10)")
    ap.add_argument("--base-fraction", type=float, default=1.0,
                    help="the unit as a fraction of the paper campaign (default 1: 12.24 M samples)")
    ap.add_argument("--commands", default=",".join(COMMANDS), help=f"from {', '.join(COMMANDS)}")
    ap.add_argument("--procedure", type=Path, default=ROOT / "procedures" / "paper_campaign.yaml")
    ap.add_argument("--hog", action="store_true", help="also run every command beside a CPU hog")
    ap.add_argument("--keep", action="store_true", help="keep the temporary stores and the commands' outputs")
    ap.add_argument("--workdir", type=Path, default=None,
                    help="build the stores here and keep them for later runs, which reuse them (default: a "
                         "temporary dir)")
    ap.add_argument("--max-rss-gb", type=float, default=MAX_RSS_GB,
                    help=f"skip or kill a command projected to or passing this peak RSS (default {MAX_RSS_GB:g}; "
                         f"never above {MEMORY_SHARE:.0%}% of the memory available)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    try:
        scales = sorted({float(s) for s in args.scales.split(",") if s.strip()})
    except ValueError:
        ap.error(f"--scales: not a list of numbers: {args.scales!r}")
    commands = [c.strip() for c in args.commands.split(",") if c.strip()]
    if not scales or min(scales) <= 0:
        ap.error("--scales: give positive multiples")
    if not 0.1 <= args.base_fraction <= 1:
        ap.error("--base-fraction must be in [0.1, 1] (records of 6 to 60 s; the fit needs stretches of 5 s)")
    if unknown := sorted(set(commands) - set(COMMANDS)):
        ap.error(f"--commands: unknown {', '.join(unknown)} (from {', '.join(COMMANDS)})")
    if args.max_rss_gb <= 0:
        ap.error("--max-rss-gb must be positive")
    if not args.procedure.is_file():
        ap.error(f"--procedure: no such file: {args.procedure}")
    logging.basicConfig(level=logging.WARNING)
    # A terminated bench unwinds like an interrupted one: children and hog killed, stores deleted.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))

    if args.workdir:
        args.workdir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="labrunner-bench-scaling-", dir=args.workdir))
    stores_root = args.workdir if args.workdir else work
    sha = procedure_sha256(args.procedure)
    results: dict[str, list[Row]] = {c: [] for c in commands}
    skipped = 0
    campaign: Campaign | None = None
    try:
        for scale in scales:
            spec = StoreSpec(scale, args.base_fraction, args.seed, sha)
            where = stores_root / spec.dirname()
            db = where / "campaign.db"
            found = reusable_store(where, spec)
            if found is not None:
                samples, monitor_rows = found
                print(f"\n{scale:g}x: reusing {db}: {samples:,} record samples + {monitor_rows:,} monitor rows; "
                      f"store {db.stat().st_size / 1e6:,.0f} MB")
            else:
                if campaign is None:  # synthesised only when a store has to be built
                    t0 = time.perf_counter()
                    campaign = synthesise(args.base_fraction, args.seed)
                    print(f"synthesised the paper campaign at {args.base_fraction:g}x ({len(campaign.records)} "
                          f"records) in {time.perf_counter() - t0:.1f} s")
                shutil.rmtree(where, ignore_errors=True)  # a build that did not finish
                where.mkdir(parents=True)
                t0 = time.perf_counter()
                samples, monitor_rows = build_store(db, campaign, scale, args.procedure)
                build_s = time.perf_counter() - t0
                write_manifest(where, spec, samples, monitor_rows, build_s)
                print(f"\n{scale:g}x: {samples:,} record samples + {monitor_rows:,} monitor rows stored in "
                      f"{build_s:.1f} s ({samples / build_s / 1e6:.2f} M samples/s); "
                      f"store {db.stat().st_size / 1e6:,.0f} MB")
            read_through(db)
            out = work / f"out_{scale:g}x"
            for name in commands:
                avail = available_memory_bytes()
                limit = int(min(avail * MEMORY_SHARE, args.max_rss_gb * 1e9))
                history = [(r.samples, r.quiet.peak_rss_bytes) for r in results[name]]
                projected = projected_rss(history, samples)
                if projected is not None and projected > limit:
                    print(f"  {name:8s} SKIPPED: projected peak RSS {projected / 1e9:.1f} GB > the bound "
                          f"{limit / 1e9:.1f} GB (--max-rss-gb {args.max_rss_gb:g}, {MEMORY_SHARE:.0%} of the "
                          f"{avail / 1e9:.1f} GB available)")
                    skipped += 1
                    continue
                out.mkdir(exist_ok=True)
                try:
                    quiet = run_command(command_line(name, db, out), False, limit)
                    print(f"  {name:8s} {quiet.line()}  [{load_line()}]", flush=True)
                    hogged = None
                    if args.hog:
                        hogged = run_command(command_line(name, db, out), True, limit)
                        print(f"  {name:8s} {hogged.line()}  with a CPU hog [{load_line()}]", flush=True)
                        report(f"  {name} {scale:g}x wall busy/quiet", hogged.wall_s / quiet.wall_s, 1.5, "x")
                except MemoryError as exc:
                    print(f"  {name:8s} SKIPPED: {exc}")
                    skipped += 1
                    continue
                finally:
                    if not args.keep:  # the exported CSV is up to 12 GB at 10x
                        shutil.rmtree(out, ignore_errors=True)
                results[name].append(Row(scale, samples, quiet, hogged))
            if not args.workdir and not args.keep:
                shutil.rmtree(where)
        print(f"\ntargets (issue 15, target 3: linear time, flat memory, {scales[0]:g}x to {scales[-1]:g}x "
              f"of {args.base_fraction:g} paper campaign; {load_line()}):")
        for name in commands:
            summarise(name, results[name])
        if skipped:
            print(f"{skipped} command run(s) skipped for memory: the growth figures cover the scales measured")
    except RuntimeError as exc:
        print(f"bench_scaling: {exc}", file=sys.stderr)
        return 1
    finally:
        if args.workdir:
            print(f"stores kept for reuse in {args.workdir}")
        if args.keep:
            print(f"kept: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    return 0 if any(results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
