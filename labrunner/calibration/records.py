"""Records and temperature steps: the units the calibration fits work on.

A campaign CSV has no setpoint or step column, so structure is inferred from the rows:

* a *segment* is a stretch of consecutive rows with the same run and orientation, a
  steady table rate and no time gap (a gap is a row interval much longer than its
  neighbours', so both 50 Hz samples and averaged rows work);
* a *record* is a stable piece of a segment: segments that drift (chamber ramps, slow
  table acceleration) are cut into pieces whose temperature and rate spans stay within
  tolerances; pieces whose temperature still drifts (ramps, not soaks) and short ones
  (table acceleration rows) are dropped.
* *temperature steps* are clusters of record mean temperatures separated by gaps
  (single linkage on sorted temperatures), which is robust to the orientations being
  recorded at slightly different IMU temperatures. Continuous data (slow heating and
  cooling ramps, no soaks) has no gaps: a cluster wider than `max_step_width_c` without a
  gap of `continuous_gap_c` is cut into temperature bins of at most `ramp_bin_c`. The
  records of a ramp are the pieces whose temperature spans at most `temp_span_c` and
  changes by at most `max_drift_c_per_min` (a bounded |dT/dt|).

Fits use record means (the paper averages each orientation's measurements), weighted by
the record's duration, i.e. by the number of raw samples it stands for.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from labrunner.campaign_csv import OUTPUT_COLUMNS
from labrunner.domain import ORIENTATIONS, UP_VECTORS


@dataclass(frozen=True)
class RecordOptions:
    """Tolerances of record segmentation and temperature-step clustering."""

    gap_factor: float = 3.0  # a row interval > gap_factor x its neighbours' starts a new segment
    rate_tol_dps: float = 0.05  # rate change that starts a new segment (plus rate_tol_rel x |rate|)
    rate_tol_rel: float = 1e-3
    temp_span_c: float = 0.5  # a record's temperature may span at most this much
    # Steadier than this is a record: a soak, or a slow ramp (a real log heats and cools continuously at
    # a few C per hour); a chamber moving between soaks (a few C per minute) is not.
    max_drift_c_per_min: float = 0.1
    drift_allowance_c: float = 0.05  # ... give or take this (sensor quantisation and jitter)
    min_duration_s: float = 5.0  # shorter records (acceleration rows, fragments) are dropped
    step_gap_c: float = 2.0  # record temperatures further apart than this start a new step
    max_step_width_c: float = 3.0  # a wider cluster (chained by slow soak drift) is split at its widest gap
    continuous_gap_c: float = 0.5  # ... while that gap is wider than this; else the cluster is a ramp, binned:
    ramp_bin_c: float = 1.0  # temperature bins of continuous data are at most this wide


@dataclass
class Records:
    """Per-record summaries (struct of arrays, one entry per record) and the row labels.

    `row_record[i]` is the record index of frame row i, or -1 for rows in no record.
    `mean` holds mean outputs [ax ay az gx gy gz]; `reference` the true values in the
    same layout (accelerometer: +1 g along up; gyro: table rate about up).
    """

    row_record: np.ndarray  # (n_rows,) int
    run: np.ndarray  # (R,) int
    orientation: np.ndarray  # (R,) int index into ORIENTATIONS
    rate_dps: np.ndarray  # (R,) mean table rate
    temp_c: np.ndarray  # (R,) mean IMU temperature
    temp_span_c: np.ndarray  # (R,)
    t_start_s: np.ndarray  # (R,)
    t_end_s: np.ndarray  # (R,)
    n_rows: np.ndarray  # (R,) rows contributing
    row_interval_s: np.ndarray  # (R,) typical row interval
    mean: np.ndarray  # (R, 6)
    sem: np.ndarray  # (R, 6) standard error of the mean from the within-record scatter (nan if 1 row)
    reference: np.ndarray  # (R, 6)
    step: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (R,) step index, -1 none
    # (R,) each record's first row and one past its last, as positions in the campaign: what a chunked
    # fit keeps of the rows (no per-row label of the whole campaign; `row_record` is then empty).
    row_start: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    row_stop: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __len__(self) -> int:
        return int(self.run.size)

    @property
    def duration_s(self) -> np.ndarray:
        """Time each record stands for (rows x row interval): its weight in the fits."""
        return self.n_rows * self.row_interval_s

    @property
    def up(self) -> np.ndarray:
        return UP_VECTORS[self.orientation]

    def subset(self, keep: np.ndarray, with_labels: bool = True) -> Records:
        """The records selected by a boolean mask or index array (row labels renumbered; none with
        `with_labels=False`: a training part's summaries, whose rows nobody looks up)."""
        idx = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep, dtype=np.int64)
        remap = np.full(len(self) + 1, -1, dtype=np.int64)
        remap[idx] = np.arange(idx.size)
        # -1 maps via remap[-1] == -1
        rows = remap[self.row_record] if with_labels else np.zeros(0, dtype=np.int64)
        return Records(
            row_record=rows, run=self.run[idx], orientation=self.orientation[idx], rate_dps=self.rate_dps[idx],
            temp_c=self.temp_c[idx], temp_span_c=self.temp_span_c[idx], t_start_s=self.t_start_s[idx],
            t_end_s=self.t_end_s[idx], n_rows=self.n_rows[idx], row_interval_s=self.row_interval_s[idx],
            mean=self.mean[idx], sem=self.sem[idx], reference=self.reference[idx],
            step=self.step[idx] if self.step.size else self.step,
            row_start=self.row_start[idx] if self.row_start.size else self.row_start,
            row_stop=self.row_stop[idx] if self.row_stop.size else self.row_stop,
        )

    def labels(self, n_rows: int) -> np.ndarray:
        """(n_rows,) the record index of every row, -1 outside records, from the records' row ranges
        (records are disjoint row ranges; a masked training part's ranges are its records' extents)."""
        out = np.full(n_rows, -1, dtype=np.int64)
        for label, (s, e) in enumerate(zip(self.row_start.tolist(), self.row_stop.tolist())):
            out[s:e] = label
        return out


@dataclass
class TemperatureSteps:
    """Temperature steps inferred from record temperatures."""

    temp_c: np.ndarray  # (K,) duration-weighted mean IMU temperature of each step
    lo_c: np.ndarray  # (K,) lowest record temperature in the step
    hi_c: np.ndarray  # (K,) highest
    n_records: np.ndarray  # (K,)

    def __len__(self) -> int:
        return int(self.temp_c.size)


_UP_TWICE = np.concatenate([UP_VECTORS, UP_VECTORS], axis=1)  # per orientation: up, and up times the rate


def reference_values(orientation: np.ndarray, rate_dps: np.ndarray) -> np.ndarray:
    """(N, 6) true specific force (g) and angular rate (deg/s) in the body frame."""
    rate = np.asarray(rate_dps, dtype=float)
    out = _UP_TWICE[np.asarray(orientation, dtype=np.int64)]
    for j in range(3, 6):  # column by column: numpy loops per row over rows of three (2.5x the time)
        out[:, j] *= rate
    return out


class Outputs:
    """The six output columns of the rows, indexed like an (n, 6) array without being one: `y[rows]`
    stacks the selected rows only and `y[rows, k]` is column k's; a campaign's columns are not copied
    into a second (n, 6) array (half a gigabyte at paper scale)."""

    def __init__(self, columns: list[np.ndarray | ScaledColumn]) -> None:
        self.columns = columns

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.columns[0].size), len(self.columns))

    def __len__(self) -> int:
        return int(self.columns[0].size)

    def __getitem__(self, key: Any) -> np.ndarray:
        if isinstance(key, tuple):
            rows, k = key
            if isinstance(k, int | np.integer):
                return self.columns[int(k)][rows]
            return np.column_stack([c[rows] for c in self.columns])[:, k]
        return np.column_stack([c[key] for c in self.columns])

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return np.column_stack(self.columns).astype(dtype or float, copy=False)


class ScaledColumn:
    """A float64 column held as integer counts times a scale (a store's IMU channel): `c[rows]` converts
    the selected rows only, bit for bit what the float64 column holds (`counts * scale`)."""

    dtype = np.dtype(np.float64)

    def __init__(self, counts: np.ndarray, scale: float) -> None:
        self.counts = counts
        self.scale = float(scale)

    @property
    def size(self) -> int:
        return int(self.counts.size)

    @property
    def shape(self) -> tuple[int]:
        return (self.size,)

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, key: Any) -> np.ndarray:
        return np.multiply(self.counts[key], self.scale, dtype=np.float64)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        values = np.multiply(self.counts, self.scale, dtype=np.float64)
        return values if dtype is None else values.astype(dtype, copy=False)


def _output_column(series: pd.Series) -> np.ndarray | ScaledColumn:
    """An output column as the analysis reads it: a store's int16 counts stay counts (`ScaledColumn`,
    converted a chunk at a time), any other column is its float64 array (a view when it is one)."""
    from labrunner.data_source import ScaledFloatArray

    values = series.array
    if isinstance(values, ScaledFloatArray) and values.counts.dtype.kind in "iu":
        return ScaledColumn(values.counts, values.scale)
    return series.to_numpy(dtype=float)


def frame_arrays(frame: pd.DataFrame) -> dict[str, Any]:
    """The numeric columns the analysis needs, as arrays (orientation as an index into ORIENTATIONS,
    int8; `y` the outputs as `Outputs`). The frame's own float64 and int64 columns are views, not copies;
    the outputs of a store's campaign stay its int16 counts (`ScaledColumn`: `y[rows]` converts those
    rows), the temperature is converted once (the passes over it run on the whole column)."""
    orient = frame["orientation"]
    if isinstance(orient.dtype, pd.CategoricalDtype) and list(orient.cat.categories) == list(ORIENTATIONS):
        codes = orient.cat.codes.to_numpy()
    else:
        codes = pd.Categorical(orient.astype(str), categories=list(ORIENTATIONS)).codes
    return {
        "t": frame["t_s"].to_numpy(dtype=float),
        "run": frame["run"].to_numpy(dtype=np.int64),
        "orientation": np.asarray(codes),
        "temp": frame["imu_temp_c"].to_numpy(dtype=float),
        "rate": frame["table_rate_dps"].to_numpy(dtype=float),
        "y": Outputs([_output_column(frame[c]) for c in OUTPUT_COLUMNS]),
    }


CHUNK_ROWS = 1 << 20  # rows per chunk of the row-wise passes: bounded temporaries at any campaign size


def _segment_starts(a: dict[str, Any], opt: RecordOptions) -> np.ndarray:
    """Row indices where a new segment starts (always includes 0); in chunks of CHUNK_ROWS rows."""
    n = a["t"].size
    out = [np.zeros(1, dtype=np.int64)]
    for lo in range(1, n, CHUNK_ROWS):
        hi = min(lo + CHUNK_ROWS, n)
        # Rows lo..hi-1 need their two neighbours' intervals on either side.
        a0, b0 = max(lo - 2, 0), min(hi + 2, n)
        brk = _breaks(a["t"][a0:b0], a["run"][a0:b0], a["orientation"][a0:b0], a["rate"][a0:b0], opt)
        out.append(np.flatnonzero(brk[lo - a0 - 1:hi - a0 - 1]) + lo)
    return np.concatenate(out)


def _breaks(t: np.ndarray, run: np.ndarray, orient: np.ndarray, rate: np.ndarray, opt: RecordOptions) -> np.ndarray:
    """(n - 1,): whether row i + 1 starts a new segment after row i."""
    dt = np.diff(t)
    brk = (run[1:] != run[:-1]) | (orient[1:] != orient[:-1])
    tol = opt.rate_tol_dps + opt.rate_tol_rel * np.maximum(np.abs(rate[1:]), np.abs(rate[:-1]))
    brk |= np.abs(np.diff(rate)) > tol
    # A gap is an interval much longer than the shorter of its neighbours' intervals.
    pos = np.where(dt > 0, dt, np.inf)
    prev = np.concatenate(([np.inf], pos[:-1]))
    nxt = np.concatenate((pos[1:], [np.inf]))
    ref = np.minimum(prev, nxt)
    brk |= np.isfinite(ref) & (dt > opt.gap_factor * ref)
    return brk


def _stable_pieces(temp: np.ndarray, rate: np.ndarray, temp_tol: float, rate_tol: float) -> list[int]:
    """Start offsets of greedy pieces whose temperature and rate spans stay within tolerance."""
    starts = [0]
    s, n = 0, temp.size
    while True:
        w = 256
        while True:
            tt, rr = temp[s:s + w], rate[s:s + w]
            bad = np.flatnonzero((np.maximum.accumulate(tt) - np.minimum.accumulate(tt) > temp_tol)
                                 | (np.maximum.accumulate(rr) - np.minimum.accumulate(rr) > rate_tol))
            if bad.size or s + w >= n:
                break
            w *= 4
        if not bad.size:
            return starts
        s += int(bad[0])
        starts.append(s)


def segment_records(frame: pd.DataFrame, options: RecordOptions | None = None) -> Records:
    """Split campaign rows into records (see the module docstring)."""
    opt = options or RecordOptions()
    a = frame_arrays(frame)
    n = a["t"].size
    starts, stops, interval = record_bounds(a, _segment_starts(a, opt), opt, lambda: _typical_interval(a["t"]))
    row_record = np.full(n, -1, dtype=np.int64)
    for label, (s, e) in enumerate(zip(starts.tolist(), stops.tolist())):  # records are disjoint row ranges
        row_record[s:e] = label
    return records_from_labels(a, row_record, interval)


def record_bounds(a: dict[str, Any], starts: np.ndarray, opt: RecordOptions,
                  typical: Callable[[], float] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows [start, stop) and row interval of the records among the segments starting at `starts` (the
    rows of `a` from starts[0] to its end): drifting segments cut into stable pieces, ramps and short
    pieces dropped. `typical()` is the campaign's typical row interval, the duration a one-row record
    stands for; with None, one-row records are kept with a NaN interval (decided by the caller once the
    whole campaign's interval is known)."""
    n = a["t"].size
    stops = np.append(starts[1:], n)
    temp, rate = a["temp"], a["rate"]

    # Split drifting segments (chamber ramps, slow table acceleration) into stable pieces;
    # only the few segments that drift need a look.
    span_t = np.maximum.reduceat(temp, starts) - np.minimum.reduceat(temp, starts)
    span_r = np.maximum.reduceat(rate, starts) - np.minimum.reduceat(rate, starts)
    rate_tol = opt.rate_tol_dps + opt.rate_tol_rel * np.maximum.reduceat(np.abs(rate), starts)
    extra: list[np.ndarray] = []
    for k in np.flatnonzero((span_t > opt.temp_span_c) | (span_r > rate_tol)):
        s, e = starts[k], stops[k]
        extra.append(s + np.asarray(_stable_pieces(temp[s:e], rate[s:e], opt.temp_span_c, float(rate_tol[k]))[1:],
                                    dtype=np.int64))
    if extra:
        starts = np.unique(np.concatenate([starts, *extra]))
        stops = np.append(starts[1:], n)

    counts = stops - starts
    span_time = a["t"][stops - 1] - a["t"][starts]
    # A one-row record stands for the typical row interval (averaged rows a few seconds apart).
    one = counts == 1
    typ = (typical() if typical is not None else np.nan) if one.any() else 1.0
    interval = np.where(counts > 1, span_time / np.maximum(counts - 1, 1), typ)
    # Soaks only: a record whose temperature drifts (a ramp) is not a calibration point.
    drift = np.abs(temp[stops - 1] - temp[starts])
    long_enough = counts * interval >= opt.min_duration_s
    if typical is None:
        long_enough |= one
    keep = (counts > 0) & long_enough \
        & (drift <= opt.max_drift_c_per_min * span_time / 60.0 + opt.drift_allowance_c)
    return starts[keep], stops[keep], interval[keep]


def _typical_interval(t: np.ndarray) -> float:
    """Median positive row interval (1 s without one)."""
    dt = np.diff(t)
    dt = dt[dt > 0]
    return float(np.median(dt)) if dt.size else 1.0


def records_from_labels(a: dict[str, Any], row_record: np.ndarray, row_interval_s: np.ndarray,
                        row_mask: np.ndarray | None = None, *, with_labels: bool = True) -> Records:
    """Record summaries from row labels, optionally using only rows where `row_mask` is true.

    With a mask (e.g. the training rows of a random split) records lose rows; records left
    with no rows are dropped and the labels renumbered. `with_labels=False` leaves
    `row_record` empty (a training part's summaries, whose rows nobody looks up).

    The rows are summed in chunks of about CHUNK_ROWS cut between records, so each record's sums
    run over its rows in order within one chunk (`np.bincount`, bin 0 for rows in no record), the
    same numbers as one pass over all rows, with temporaries of a chunk's size.
    """
    n_rec = int(row_interval_s.size)

    def labels_of(lo: int, hi: int) -> np.ndarray:
        lab = row_record[lo:hi]
        return lab if row_mask is None else np.where(row_mask[lo:hi], lab, -1)

    cnt = np.zeros(n_rec)
    sums = np.zeros((n_rec, 8))  # temp, rate, six outputs
    sq = np.zeros((n_rec, 6))
    first = np.zeros(n_rec, dtype=np.int64)
    last = np.zeros(n_rec, dtype=np.int64)
    tmax = np.full(n_rec, -np.inf)
    tmin = np.full(n_rec, np.inf)
    y = a["y"]
    cuts = _cuts(labels_of, row_record.size)
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        lab = labels_of(lo, hi)
        bins = lab + 1
        c = np.bincount(bins, minlength=n_rec + 1)[1:].astype(float)
        here = np.flatnonzero(c)
        if here.size == 0:
            continue
        cnt[here] = c[here]
        col = np.empty(hi - lo)  # one output column and its deviations at a time, in reused buffers
        dev = np.empty(hi - lo)
        for j in range(8):
            x = a["temp"][lo:hi] if j == 0 else a["rate"][lo:hi] if j == 1 else _output_into(y, j - 2, lo, hi, col)
            part = np.bincount(bins, weights=x, minlength=n_rec + 1)[1:]
            sums[here, j] = part[here]
            if j >= 2:  # scatter about the record's mean (complete: no record spans two chunks)
                mean = np.zeros(n_rec + 1)
                mean[here + 1] = part[here] / c[here]
                np.take(mean, bins, out=dev, mode="clip")  # (bins are in range; "raise" buffers the output)
                np.subtract(x, dev, out=dev)
                np.multiply(dev, dev, out=dev)
                sq[here, j - 2] = np.bincount(bins, weights=dev, minlength=n_rec + 1)[1:][here]
        rows = np.flatnonzero(lab >= 0)
        lab_in = lab[rows]
        # First and last row of each record from the runs of equal labels (a record's rows are one run, or a
        # few with masked rows between them): the same rows as np.unique's first occurrences, without
        # sorting the chunk's labels.
        edge = np.flatnonzero(lab_in[1:] != lab_in[:-1]) + 1
        run_start = np.concatenate(([0], edge))
        run_end = np.concatenate((edge, [lab_in.size]))
        run_lab = lab_in[run_start]
        uniq, first_run = np.unique(run_lab, return_index=True)
        _, last_rev = np.unique(run_lab[::-1], return_index=True)
        first[uniq] = lo + rows[run_start[first_run]]
        last[uniq] = lo + rows[run_end[run_lab.size - 1 - last_rev] - 1]
        temp_in = a["temp"][lo:hi][rows]
        np.maximum.at(tmax, lab_in, temp_in)
        np.minimum.at(tmin, lab_in, temp_in)

    present = cnt > 0
    labels = labels_of(0, row_record.size) if with_labels else np.zeros(0, dtype=np.int64)
    if not present.all():
        keep = np.flatnonzero(present)
        if with_labels:
            remap = np.full(n_rec + 1, -1, dtype=np.int64)
            remap[keep] = np.arange(keep.size)
            labels = remap[labels]
        cnt, sums, sq, first, last = cnt[keep], sums[keep], sq[keep], first[keep], last[keep]
        tmax, tmin, row_interval_s = tmax[keep], tmin[keep], row_interval_s[keep]
        n_rec = int(keep.size)
    temp = sums[:, 0] / np.maximum(cnt, 1)
    rate = sums[:, 1] / np.maximum(cnt, 1)
    mean = sums[:, 2:] / cnt[:, None]
    orient = np.asarray(a["orientation"][first]).astype(np.int64)
    run = np.asarray(a["run"][first]).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        sem = np.sqrt(sq / (cnt[:, None] - 1) / cnt[:, None])
    sem[cnt <= 1] = np.nan
    return Records(
        row_record=labels, run=run, orientation=orient, rate_dps=rate, temp_c=temp, temp_span_c=tmax - tmin,
        t_start_s=a["t"][first], t_end_s=a["t"][last], n_rows=cnt,
        row_interval_s=np.asarray(row_interval_s, dtype=float), mean=mean, sem=sem,
        reference=reference_values(orient, rate), step=np.full(n_rec, -1, dtype=np.int64),
        row_start=first.astype(np.int64), row_stop=last.astype(np.int64) + 1,
    )


def _output_into(y: Any, j: int, lo: int, hi: int, buf: np.ndarray) -> np.ndarray:
    """Output column j of rows lo..hi as float64: a store's counts converted into `buf` (the same numbers as
    `y[lo:hi, j]`), any other column as the view it is."""
    column = y.columns[j] if isinstance(y, Outputs) else None
    if isinstance(column, ScaledColumn):
        return np.multiply(column.counts[lo:hi], column.scale, dtype=np.float64, out=buf)
    return np.asarray(y[lo:hi, j], dtype=float)


def _cuts(labels_of: Callable[[int, int], np.ndarray], n: int) -> list[int]:
    """Chunk bounds 0 = c0 < c1 < ... = n, about CHUNK_ROWS apart, none inside a record; [0, n] when a
    record's rows are not one run of equal labels (then no cut is safe)."""
    if n <= CHUNK_ROWS:
        return [0, n]
    # Records are one run each when the runs of labels (rows in no record skipped) are as many as the labels.
    runs, prev, seen = 0, -1, 0
    counts = np.zeros(0, dtype=np.int64)
    for lo in range(0, n, CHUNK_ROWS):
        lab = labels_of(lo, min(lo + CHUNK_ROWS, n))
        lab = lab[lab >= 0]
        if lab.size == 0:
            continue
        runs += int(np.count_nonzero(lab[1:] != lab[:-1])) + int(lab[0] != prev)
        prev = int(lab[-1])
        c = np.bincount(lab)
        if c.size > counts.size:
            counts = np.concatenate([counts, np.zeros(c.size - counts.size, dtype=np.int64)])
        counts[:c.size] += c
    seen = int(np.count_nonzero(counts))
    if runs != seen:
        return [0, n]
    cuts = [0]
    while cuts[-1] + CHUNK_ROWS < n:
        hi = cuts[-1] + CHUNK_ROWS
        before = labels_of(cuts[-1], hi)
        inside = before[before >= 0]
        last_label = int(inside[-1]) if inside.size else -1
        # Cut at the first row of another record at or after hi.
        width = 4096
        while True:
            ahead = labels_of(hi, min(hi + width, n))
            other = np.flatnonzero((ahead >= 0) & (ahead != last_label))
            if other.size or hi + width >= n:
                break
            width *= 4
        if not other.size:
            break
        cuts.append(hi + int(other[0]))
    cuts.append(n)
    return cuts


def _split_wide(ts: np.ndarray, new: np.ndarray, max_width: float, continuous_gap: float = 0.5,
                bin_c: float = 1.0) -> np.ndarray:
    """Split clusters of sorted temperatures wider than max_width at their widest gaps; a wide cluster
    without a gap wider than `continuous_gap` (a ramp) is cut into equal bins of at most `bin_c`."""
    new = new.copy()
    binned: set[int] = set()
    while True:
        bounds = np.append(np.flatnonzero(new), ts.size)
        wide = [(a, b) for a, b in zip(bounds[:-1], bounds[1:])
                if b - a > 1 and ts[b - 1] - ts[a] > max_width and a not in binned]
        if not wide:
            return new
        for a, b in wide:
            gaps = np.diff(ts[a:b])
            if gaps.max() > continuous_gap:
                new[a + 1 + int(np.argmax(gaps))] = True
                continue
            n_bins = int(np.ceil((ts[b - 1] - ts[a]) / bin_c))
            edges = np.linspace(ts[a], ts[b - 1], n_bins + 1)[1:-1]
            cuts = a + np.searchsorted(ts[a:b], edges)
            new[cuts[(cuts > a) & (cuts < b)]] = True
            binned.update(int(c) for c in np.flatnonzero(new[a:b]) + a)


def temperature_steps(records: Records, gap_c: float = 2.0, max_width_c: float = 3.0,
                      continuous_gap_c: float = 0.5, ramp_bin_c: float = 1.0) -> TemperatureSteps:
    """Cluster record temperatures into steps (soaks) or bins (ramps) and set `records.step` (in place)."""
    if len(records) == 0:
        records.step = np.zeros(0, dtype=np.int64)
        return TemperatureSteps(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    order = np.argsort(records.temp_c, kind="stable")
    ts = records.temp_c[order]
    new = _split_wide(ts, np.concatenate(([True], np.diff(ts) > gap_c)), max_width_c, continuous_gap_c, ramp_bin_c)
    cluster_sorted = np.cumsum(new) - 1
    step = np.empty(len(records), dtype=np.int64)
    step[order] = cluster_sorted
    records.step = step
    k = int(cluster_sorted[-1]) + 1
    w = records.duration_s
    temp = np.bincount(step, weights=w * records.temp_c, minlength=k) / np.bincount(step, weights=w, minlength=k)
    lo = np.full(k, np.inf)
    hi = np.full(k, -np.inf)
    np.minimum.at(lo, step, records.temp_c)
    np.maximum.at(hi, step, records.temp_c)
    return TemperatureSteps(temp_c=temp, lo_c=lo, hi_c=hi, n_records=np.bincount(step, minlength=k))
