"""Where `labrunner diagnose DB` spends its memory and time, stage by stage.

Usage: python bench/bench_diagnose_stages.py DB [--frame] [--report] [--hog]

Runs the diagnosis of a store in this process with tracemalloc on and, for each stage (reading the
store, `Measurements.from_frame`, the coverage, the blocks, the drift filter, the candidate designs
and their per-fold Grams, the cause search, the held-out RMS, the residual table, the noise fit,
the report figures), prints the calls, the CPU time spent in it and the largest extra memory it
allocated at once (the tracemalloc peak above what was held when it was entered), then the
process's peak RSS. By default the store is read in 1 s summaries chunk by chunk, as the command
does; `--frame` reads it as one frame of every sample (the way before issue 15), for comparison.
Nested stages count in their callers too (the
cause search holds most of the designs).

Target lines (issue 15, target 2: `diagnose` of the paper store <= 30 s, <= 2 GB): the whole run's
CPU time and peak RSS against them. Both are upper bounds of the command's: tracemalloc's
bookkeeping costs CPU on every allocation and some memory (`labrunner diagnose` under
bench_diagnose.py --store gives the figures without it). `--hog` runs the diagnosis beside a
process spinning on one core (issue 15, target 5). Exit 0 when it ran, also when a target is
missed; 1 when the store cannot be read.
"""

from __future__ import annotations

import argparse
import functools
import resource
import sys
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.common import cpu_hog, load_line, report  # noqa: E402

TARGET_CPU_S = 30.0  # issue 15, target 2: diagnose of the paper store
TARGET_RSS_GB = 2.0

STATS: dict[str, list[float]] = {}  # name -> [calls, cpu_s, largest extra bytes]
_STACK: list[list[float]] = []  # per open stage: [bytes held at entry, highest traced bytes inside]


def _wrap(owner: Any, attr: str, name: str) -> None:
    fn: Callable[..., Any] = getattr(owner, attr)

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        held, peak = tracemalloc.get_traced_memory()
        if _STACK:
            _STACK[-1][1] = max(_STACK[-1][1], peak)
        tracemalloc.reset_peak()
        _STACK.append([held, held])
        c0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            _, peak = tracemalloc.get_traced_memory()
            entry, top = _STACK.pop()
            top = max(top, peak)
            s = STATS.setdefault(name, [0, 0.0, 0.0])
            s[0] += 1
            s[1] += time.process_time() - c0
            s[2] = max(s[2], top - entry)
            if _STACK:  # the enclosing stage saw this peak too
                _STACK[-1][1] = max(_STACK[-1][1], top)
            tracemalloc.reset_peak()

    setattr(owner, attr, wrapper)


def instrument() -> None:
    import importlib

    def mod(name: str) -> Any:
        return importlib.import_module(f"labrunner.discrepancy.{name}")

    summary, measurements, diagnose, engine = mod("summary"), mod("measurements"), mod("diagnose"), mod("engine")
    selection, report = mod("selection"), mod("report")

    _wrap(summary, "read_store_summary", "read store (1 s summaries)")
    _wrap(measurements.Measurements, "from_frame", "Measurements.from_frame")
    _wrap(diagnose, "assess", "coverage")
    _wrap(diagnose, "make_blocks", "blocks")
    _wrap(diagnose, "build_drift_filter", "drift filter")
    _wrap(diagnose, "envelope_columns", "envelope designs")
    _wrap(engine.Engine, "system", "designs + per-fold Grams (Engine.system)")
    _wrap(engine.Engine, "_heldout_rms", "held-out RMS on the rows")
    _wrap(selection.Searcher, "run", "cause search")
    _wrap(diagnose, "residual_table", "residual table")
    _wrap(diagnose, "fit_noise", "noise fit (Allan)")
    _wrap(diagnose._Diagnoser, "_check_model", "in-sample model check")
    _wrap(report, "write_report", "report figures")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("db", type=Path)
    parser.add_argument("--frame", action="store_true", help="read every sample into one frame (the old way)")
    parser.add_argument("--report", action="store_true", help="also draw the report")
    parser.add_argument("--hog", action="store_true", help="beside a second process spinning on one core")
    args = parser.parse_args()
    tracemalloc.start()
    instrument()
    from labrunner import api
    from labrunner.discrepancy import report as report_module
    from labrunner.discrepancy.diagnose import DiagnoseOptions, diagnose
    from labrunner.discrepancy.measurements import Measurements
    from labrunner.discrepancy.summary import read_store_summary
    from labrunner.errors import UserError

    print(f"before: {load_line()}{', CPU hog' if args.hog else ''}")
    with cpu_hog(args.hog):
        c0, t0 = time.process_time(), time.perf_counter()
        if args.frame:
            held, _ = tracemalloc.get_traced_memory()
            tracemalloc.reset_peak()
            c1 = time.process_time()
            try:
                frame = api.load_data(args.db, include_monitor=True).frame
            except UserError as exc:
                print(f"bench_diagnose_stages: {exc}", file=sys.stderr)
                return 1
            STATS["read store (one frame)"] = [1, time.process_time() - c1,
                                               tracemalloc.get_traced_memory()[1] - held]
            meas = Measurements.from_frame(frame)
            del frame
        else:
            try:
                stored = read_store_summary(args.db)
            except UserError as exc:  # not a store, no such file, no samples yet: one line, no traceback
                print(f"bench_diagnose_stages: {exc}", file=sys.stderr)
                return 1
            meas = Measurements.from_frame(stored.frame, stored.summary)
            del stored
        result = diagnose(meas, DiagnoseOptions())
        if args.report:
            with tempfile.TemporaryDirectory(prefix="bench-stages-") as tmp:
                report_module.write_report(result, Path(tmp) / "report")
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    print(f"{args.db}: {len(meas)} rows, verdict {result.verdict}, {cpu:.1f} s CPU, {wall:.1f} s wall")
    print(f"{'stage':44s} {'calls':>6s} {'CPU s':>8s} {'peak extra MB':>14s}")
    for name, (calls, cpu_s, extra) in STATS.items():
        print(f"{name:44s} {int(calls):6d} {cpu_s:8.2f} {extra / 1e6:14.0f}")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(f"peak RSS {rss / 1e6:.0f} MB (tracemalloc's own bookkeeping included)")
    print(f"after:  {load_line()}{', CPU hog' if args.hog else ''}")
    report("diagnose CPU (tracemalloc on)", cpu, TARGET_CPU_S, "s")
    report("diagnose peak RSS (tracemalloc on)", rss / 1e9, TARGET_RSS_GB, "GB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
