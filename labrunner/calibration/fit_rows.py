"""A campaign's rows as the fit reads them: passes of chunks in row order (a store read a bounded number
of rows at a time, or slices of a frame), the data summary taken on the way, and the bounded set of
rows the static figures draw, gathered at the end instead of keeping the campaign's frame.

The figures' rows (`FigureRows`): every k-th row of the static records, at most MAX_NORM_POINTS
(the norms before and after compensation), and the first MAX_ALLAN_SAMPLES rows of the
MAX_ALLAN_RECORDS longest static records (the Allan deviation), outputs as stored (a store's int16
counts): at most 6000 + 12 x 2^20 rows, in practice the few longest soaks (the paper campaign:
12 records of about a thousand rows).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from labrunner.domain import ORIENTATIONS

from .chunked_records import ChunkSegmenter, frame_chunks, join_arrays, take_rows, typical_interval_of
from .evaluation import STATIC_RATE_DPS
from .records import RecordOptions, Records, TemperatureSteps, frame_arrays

log = logging.getLogger(__name__)

CHUNK_ROWS = 1 << 19  # rows per pass chunk (a store read ~70 B a row at once; the paper fit: 510 -> 471 MB from 2^20)
MAX_NORM_POINTS = 6000  # per curve: enough to show the spread, cheap to compensate and draw
MAX_ALLAN_RECORDS = 12  # the longest static records, averaged (one short record gives a noisy curve)
MAX_ALLAN_SAMPLES = 1 << 20  # per record: octave-spaced taus need no more


@dataclass
class CampaignRows:
    """A campaign's rows: `chunks()` starts a pass (chunks in row order, validated like a whole read).
    `frame` is the whole frame when one is at hand (a CSV read whole, a lag-corrected frame)."""

    chunks: Callable[[], Iterable[pd.DataFrame]]
    frame: pd.DataFrame | None = None

    @classmethod
    def of_frame(cls, frame: pd.DataFrame, max_rows: int = CHUNK_ROWS) -> CampaignRows:
        return cls(chunks=lambda: frame_chunks(frame, max_rows), frame=frame)

    def whole(self) -> pd.DataFrame:
        """The whole frame (read and joined when the rows are a store's chunks)."""
        if self.frame is None:
            self.frame = pd.concat(list(self.chunks()))
        return self.frame


@dataclass
class _Summary:
    """What the fit reports of all rows (`FitResult.data_summary`), accumulated chunk by chunk."""

    rows: int = 0
    runs: set[int] = field(default_factory=set)
    orientations: set[str] = field(default_factory=set)
    t: list[float] = field(default_factory=lambda: [np.inf, -np.inf])
    temp: list[float] = field(default_factory=lambda: [np.inf, -np.inf])

    def add(self, chunk: pd.DataFrame) -> None:
        if len(chunk) == 0:
            return
        self.rows += len(chunk)
        self.runs.update(int(r) for r in pd.unique(chunk["run"].to_numpy()))
        self.orientations.update(str(o) for o in chunk["orientation"].unique())  # per value, not per row
        for acc, col in ((self.t, "t_s"), (self.temp, "imu_temp_c")):
            v = chunk[col].to_numpy(dtype=float)
            acc[0], acc[1] = min(acc[0], float(v.min())), max(acc[1], float(v.max()))


def read_records(rows: CampaignRows, options: RecordOptions,
                 progress: Callable[[str], None] | None = None) -> tuple[Records, _Summary]:
    """One pass: the campaign's records (row ranges, no per-row labels) and its data summary."""
    seg = ChunkSegmenter(options)
    summary = _Summary()
    for chunk in rows.chunks():
        summary.add(chunk)
        seg.add(chunk)
    records = seg.finish(lambda: typical_interval_of(rows.chunks()))
    if progress:
        progress(f"{summary.rows:,} rows read in chunks: {len(records)} records (largest carry {seg.max_carry:,} rows)")
    return records, summary


def summary_dict(summary: _Summary, records: Records, steps: TemperatureSteps) -> dict[str, Any]:
    """`FitResult.data_summary`: the rows' summary accumulated in chunks, with the records and steps."""
    per_step = []
    for k in np.argsort(steps.temp_c):
        sel = records.step == k
        per_step.append({
            "temp_c": round(float(steps.temp_c[k]), 3), "range_c": [float(steps.lo_c[k]), float(steps.hi_c[k])],
            "records": int(sel.sum()),
            "orientations": [ORIENTATIONS[i] for i in sorted(set(records.orientation[sel].tolist()))],
        })
    return {
        "rows": summary.rows, "rows_in_records": int((records.row_stop - records.row_start).sum()),
        "records": len(records), "runs": len(summary.runs),
        "time_range_s": list(summary.t), "imu_temp_range_c": list(summary.temp),
        "orientations": sorted(summary.orientations, key=lambda o: ORIENTATIONS.index(o)),
        "table_rates_dps": sorted({round(float(r), 1) for r in records.rate_dps}),
        "temperature_steps": per_step,
    }


@dataclass
class FigureRows:
    """The rows the static figures draw (see the module docstring), campaign arrays (`frame_arrays`)."""

    norm: dict[str, Any] | None  # every `every`-th row of the static records, in time order
    every: int
    n_static_records: int
    allan: dict[int, dict[str, Any]]  # record index -> the first MAX_ALLAN_SAMPLES rows of the record


def static_records(records: Records) -> np.ndarray:
    """Indices of the records with the table at rest."""
    return np.flatnonzero(np.abs(records.rate_dps) < STATIC_RATE_DPS)


def allan_records(records: Records) -> np.ndarray:
    """The longest static records (within 90 % of the longest), at most MAX_ALLAN_RECORDS."""
    recs = static_records(records)
    if recs.size == 0:
        return recs
    n = records.n_rows[recs]
    longest = recs[np.argsort(-n, kind="stable")]
    return longest[records.n_rows[longest] >= 0.9 * n.max()][:MAX_ALLAN_RECORDS]


def _range_positions(starts: np.ndarray, stops: np.ndarray, every: int) -> np.ndarray:
    """Every `every`-th row position of the joined ranges (what `rows[::every]` of their rows is)."""
    lengths = stops - starts
    ends = np.cumsum(lengths)
    ranks = np.arange(0, int(ends[-1]) if ends.size else 0, every)
    k = np.searchsorted(ends, ranks, side="right")
    return starts[k] + ranks - (ends[k] - lengths[k])


def gather_figure_rows(rows: CampaignRows, records: Records, max_points: int = MAX_NORM_POINTS) -> FigureRows:
    """The figures' rows, in one pass over the campaign."""
    recs = static_records(records)
    chosen = allan_records(records)
    if recs.size == 0:
        return FigureRows(norm=None, every=1, n_static_records=0, allan={})
    starts, stops = records.row_start[recs], records.row_stop[recs]
    total = int((stops - starts).sum())
    every = max(1, -(-total // max_points))  # figure_style.decimation
    want = _range_positions(starts, stops, every)
    a_lo = records.row_start[chosen]
    a_hi = np.minimum(records.row_stop[chosen], a_lo + MAX_ALLAN_SAMPLES)
    parts: list[dict[str, Any]] = []
    allan_parts: dict[int, list[dict[str, Any]]] = {int(r): [] for r in chosen}
    g0 = 0
    for chunk in rows.chunks():
        a = frame_arrays(chunk)
        m = int(a["t"].size)
        lo, hi = np.searchsorted(want, [g0, g0 + m])
        if hi > lo:
            parts.append(take_rows(a, want[lo:hi] - g0))
        for r, s, e in zip(chosen.tolist(), a_lo.tolist(), a_hi.tolist()):
            s2, e2 = max(s, g0), min(e, g0 + m)
            if e2 > s2:
                allan_parts[r].append(take_rows(a, np.arange(s2 - g0, e2 - g0)))
        g0 += m
    return FigureRows(norm=join_arrays(parts) if parts else None, every=every, n_static_records=int(recs.size),
                      allan={r: join_arrays(p) for r, p in allan_parts.items() if p})


def campaign_rows(source: Any, campaign: int | None = None,
                  max_rows: int = CHUNK_ROWS) -> tuple[dict[str, Any], CampaignRows]:
    """A campaign's provenance and rows: a store's (a path or `StoreAddress`) read `max_rows` at a time
    in every pass (`data_source.campaign_chunks`), a campaign CSV's read whole (fitted in slices)."""
    from labrunner.data_source import campaign_chunks

    provenance, chunks = campaign_chunks(source, campaign, max_rows=max_rows)
    if provenance.get("kind") != "store":
        return provenance, CampaignRows.of_frame(next(iter(chunks)), max_rows)
    close = getattr(chunks, "close", None)
    if close is not None:
        close()  # the provenance was all this read was for: the store is closed again
    cid, rows = int(provenance["campaign_id"]), int(provenance["rows"])
    # Every pass reads the rows counted now: a campaign still being recorded gains blocks between passes.
    return provenance, CampaignRows(chunks=lambda: campaign_chunks(source, cid, max_rows=max_rows, rows=rows)[1])
