"""PX4's thermal calibration as a reference row of the evaluation (the method most drones fly with).

What PX4's `Tools/process_sensor_caldata.py` does with a static log, per sensor axis: a 31-sample
median filter of the output; the offset from the log's median; the samples averaged in 2000
temperature bins over the log's range; a cubic of the offset in (T - T_ref), T_ref the middle of the
range. The firmware subtracts the cubic from the output with the temperature held within the
calibrated range. It corrects offsets only (no scale factor or misalignment), and one log holds one
orientation: here each orientation of the training data is one such log, and a row is compensated
with its orientation's fit (rows of an orientation without static training rows pass unchanged).
The accelerometer's offset is taken relative to the median, so in PX4 the level itself comes from a
separate calibration; the evaluation's `time_blocks` split removes every model's offset per power-on
alike (see `evaluation.py`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.ndimage import median_filter

MEDIAN_WINDOW = 31
N_BINS = 2000
ORDER = 3
STATIC_RATE_DPS = 0.05
# PX4's method assumes a continuous sweep of temperature: its cubic through the bins of a few soaks
# is not determined between them. An orientation's log counts as a sweep when its static rows occupy
# at least this fraction of the 1 C bins over their range.
MIN_SWEEP_OCCUPANCY = 0.5


@dataclass
class Px4Fit:
    """One orientation's fit: a cubic per channel of the offset in (T - t_ref), range [t_min, t_max]."""

    t_ref_c: float
    t_min_c: float
    t_max_c: float
    coef: np.ndarray  # (6, ORDER + 1), numpy.polyfit order (highest power first)


@dataclass
class Px4Reference:
    """PX4's method, one fit per orientation (index into ORIENTATIONS)."""

    fits: dict[int, Px4Fit] = field(default_factory=dict)
    # orientation -> fraction of its range's 1 C bins its static rows occupy (0: too few rows), when it has no fit
    skipped: dict[int, float] = field(default_factory=dict)

    def skipped_sentence(self, names: tuple[str, ...]) -> str:
        """Why orientations have no fit, in one sentence (`names`: orientation labels by index)."""
        if not self.skipped:
            return ""
        occ = [100 * v for v in self.skipped.values()]
        return (f"no fit for {', '.join(names[o] for o in sorted(self.skipped))}: PX4's method needs a continuous "
                f"temperature sweep and their static training rows occupy {min(occ):.0f}-{max(occ):.0f} % of the "
                "1 C bins over their range (soaks, or too few rows)")

    def compensate_rows(self, y: np.ndarray, temp_c: np.ndarray, orientation: np.ndarray) -> np.ndarray:
        out = np.array(y, dtype=float, copy=True)
        for o, f in self.fits.items():
            sel = orientation == o
            if not sel.any():
                continue
            tau = np.clip(temp_c[sel], f.t_min_c, f.t_max_c) - f.t_ref_c
            for k in range(6):
                out[sel, k] -= np.polyval(f.coef[k], tau)
        return out


def _binned(tau: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PX4's resampleWithDeltaX: means of tau and v in N_BINS equal temperature bins (empty bins dropped)."""
    lo, hi = float(tau.min()), float(tau.max())
    width = (hi - lo) / N_BINS
    idx = np.clip(((tau - lo) / width).astype(np.int64), 0, N_BINS - 1) if width > 0 else np.zeros(tau.size, int)
    cnt = np.bincount(idx, minlength=N_BINS)
    keep = cnt > 0
    return ((np.bincount(idx, weights=tau, minlength=N_BINS)[keep] / cnt[keep]),
            (np.bincount(idx, weights=v, minlength=N_BINS)[keep] / cnt[keep]))


def fit_px4(a: dict[str, np.ndarray], rows: np.ndarray) -> Px4Reference:
    """PX4's fit on the static rows among `rows` (a boolean mask over the campaign arrays `a`)."""
    ref = Px4Reference()
    static = rows & (np.abs(a["rate"]) < STATIC_RATE_DPS)
    for o in np.unique(a["orientation"][static]):
        sel = np.flatnonzero(static & (a["orientation"] == o))  # in time order: one log per orientation
        temp = a["temp"][sel]
        t_min, t_max = float(temp.min()), float(temp.max())
        if sel.size < MEDIAN_WINDOW or t_max - t_min <= 0:
            ref.skipped[int(o)] = 0.0
            continue
        n_bins = max(int(np.ceil(t_max - t_min)), 1)
        occupied = np.unique(np.minimum(((temp - t_min) // 1.0).astype(np.int64), n_bins - 1)).size / n_bins
        if occupied < MIN_SWEEP_OCCUPANCY:
            ref.skipped[int(o)] = float(occupied)
            continue
        t_ref = 0.5 * (t_min + t_max)
        tau = temp - t_ref
        coef = np.zeros((6, ORDER + 1))
        for k in range(6):
            v = median_filter(a["y"][sel, k], size=MEDIAN_WINDOW, mode="nearest")
            tb, vb = _binned(tau, v - np.median(v))
            if tb.size > ORDER:
                coef[k] = np.polyfit(tb, vb, ORDER)
        ref.fits[int(o)] = Px4Fit(t_ref_c=t_ref, t_min_c=t_min, t_max_c=t_max, coef=coef)
    return ref


class ValueCounts:
    """Distinct values and how often each occurred, merged chunk by chunk: `np.median` of all the values
    exactly, in memory that grows with the distinct values only (a store's outputs are int16 counts times
    an LSB, its times t0 + k / rate: few distinct values; a CSV's floats may all differ)."""

    def __init__(self) -> None:
        self.values = np.zeros(0)
        self.counts = np.zeros(0, dtype=np.int64)

    @property
    def n(self) -> int:
        return int(self.counts.sum())

    def add(self, x: np.ndarray) -> None:
        if x.size == 0:
            return
        v, c = np.unique(x, return_counts=True)
        if self.values.size:
            v, inv = np.unique(np.concatenate([self.values, v]), return_inverse=True)
            c = np.bincount(inv, weights=np.concatenate([self.counts, c]), minlength=v.size).astype(np.int64)
        self.values, self.counts = v, c

    def median(self) -> float:
        """`np.median` of the values counted: the middle one, or the mean of the middle two (NaN: none)."""
        n = self.n
        if n == 0:
            return float("nan")
        cum = np.cumsum(self.counts)
        middle = self.values[np.searchsorted(cum, [(n - 1) // 2, n // 2], side="right")]
        return float(np.median(middle[:1] if n % 2 else middle))


HALF_WINDOW = MEDIAN_WINDOW // 2


class _MedianStream:
    """`median_filter(x, MEDIAN_WINDOW, mode="nearest")` of a series met chunk by chunk: the last inputs are
    carried until their window is complete, so every output is the whole series' (the same element)."""

    def __init__(self) -> None:
        self.buf = np.zeros(0)
        self.start = 0  # series index of buf[0]
        self.done = 0  # outputs given so far

    def add(self, x: np.ndarray) -> np.ndarray:
        self.buf = np.concatenate([self.buf, x])
        last = self.start + self.buf.size - HALF_WINDOW  # outputs before it have their whole window
        if last <= self.done:
            return np.zeros(0)
        out = median_filter(self.buf, size=MEDIAN_WINDOW, mode="nearest")[self.done - self.start:last - self.start]
        self.done = last
        keep = max(self.start, last - HALF_WINDOW)  # the window of the next output; the series' start kept for its edge
        self.buf = self.buf[keep - self.start:].copy()
        self.start = keep
        return out

    def flush(self) -> np.ndarray:
        """The last outputs (the series' end padded as `mode="nearest"` pads it)."""
        if self.done == self.start + self.buf.size:
            return np.zeros(0)
        out = median_filter(self.buf, size=MEDIAN_WINDOW, mode="nearest")[self.done - self.start:]
        self.done = self.start + self.buf.size
        return out


CELLS_PER_C = 4  # cells of a quarter degree: a cell's temperatures fall in at most two of the 1 C occupancy bins


@dataclass
class _Log:
    """One orientation's static rows, met in time order, through the three passes `Px4Stream` makes."""

    n: int = 0
    t_min: float = np.inf
    t_max: float = -np.inf
    cells: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # floor(temp * CELLS_PER_C)
    cell_min: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cell_max: np.ndarray = field(default_factory=lambda: np.zeros(0))
    filters: list[_MedianStream] = field(default_factory=list)
    medians: list[ValueCounts] = field(default_factory=list)
    median: np.ndarray = field(default_factory=lambda: np.zeros(6))
    t_ref: float = 0.0
    lo: float = 0.0
    width: float = 0.0
    pending: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # bins of rows awaiting outputs
    count: np.ndarray = field(default_factory=lambda: np.zeros(N_BINS, dtype=np.int64))
    sum_tau: np.ndarray = field(default_factory=lambda: np.zeros(N_BINS))
    sum_v: np.ndarray = field(default_factory=lambda: np.zeros((6, N_BINS)))

    def add_range(self, temp: np.ndarray) -> None:
        self.n += temp.size
        self.t_min = min(self.t_min, float(temp.min()))
        self.t_max = max(self.t_max, float(temp.max()))
        keys, inv = np.unique(np.concatenate([self.cells, np.floor(temp * CELLS_PER_C).astype(np.int64)]),
                              return_inverse=True)
        lo, hi = np.full(keys.size, np.inf), np.full(keys.size, -np.inf)
        np.minimum.at(lo, inv, np.concatenate([self.cell_min, temp]))
        np.maximum.at(hi, inv, np.concatenate([self.cell_max, temp]))
        self.cells, self.cell_min, self.cell_max = keys, lo, hi

    def occupancy(self, n_bins: int) -> float:
        """fit_px4's occupied fraction of the 1 C bins from t_min: the bin of a temperature is monotone in it,
        so a cell's temperatures fall in the bins of its lowest and highest (at most two: a cell is narrower
        than a bin)."""
        def bins(x: np.ndarray) -> np.ndarray:
            return np.minimum(((x - self.t_min) // 1.0).astype(np.int64), n_bins - 1)

        b_lo, b_hi = bins(self.cell_min), bins(self.cell_max)
        assert np.all(b_hi - b_lo <= 1), "a quarter-degree cell spans more than two 1 C bins"
        return float(np.unique(np.concatenate([b_lo, b_hi])).size / n_bins)

    def add_median(self, y: list[np.ndarray]) -> None:
        for k in range(6):
            self.medians[k].add(self.filters[k].add(y[k]))

    def add_bins(self, temp: np.ndarray, y: list[np.ndarray]) -> None:
        tau = temp - self.t_ref
        idx = (np.clip(((tau - self.lo) / self.width).astype(np.int64), 0, N_BINS - 1) if self.width > 0
               else np.zeros(tau.size, dtype=np.int64))
        # np.add.at adds in row order onto the running sums: the sums np.bincount makes of all rows at once
        self.count += np.bincount(idx, minlength=N_BINS)
        np.add.at(self.sum_tau, idx, tau)
        self.pending = np.concatenate([self.pending, idx])
        self._add_outputs([f.add(v) for f, v in zip(self.filters, y)])

    def end_bins(self) -> None:
        self._add_outputs([f.flush() for f in self.filters])

    def _add_outputs(self, v: list[np.ndarray]) -> None:
        """The filtered outputs decided (they lag the inputs, alike in every channel) onto their rows' bins."""
        m = v[0].size
        for k in range(6):
            np.add.at(self.sum_v[k], self.pending[:m], v[k] - self.median[k])
        self.pending = self.pending[m:]


class Px4Stream:
    """`fit_px4` of rows met chunk by chunk in order (the concatenated rows' fit, bit for bit), in memory
    that does not grow with the rows: per orientation a quarter-degree cell table, the distinct filtered
    outputs and the 2000 bins' sums.

    PX4's fit needs each orientation's temperature range before it bins and the median of the filtered
    outputs before it sums their offsets per bin (sums in row order), so it takes up to three passes over
    the rows: the range and the occupancy check (every orientation), then, for the orientations that pass
    it (a sweep), the median of the filtered outputs, then the bins. `add` the rows of a pass, then
    `end_pass`; `needs_pass` says whether another pass is wanted."""

    def __init__(self) -> None:
        self.stage = "range"  # then "median", "bins", "done"
        self.logs: dict[int, _Log] = {}
        self.ref = Px4Reference()

    @property
    def needs_pass(self) -> bool:
        return self.stage != "done"

    def add(self, a: dict[str, Any], rows: np.ndarray) -> None:
        """The rows `rows` (a boolean mask over a chunk's campaign arrays `a`) of the current pass; like
        `fit_px4`, only the static ones count."""
        if self.stage == "done":
            return
        static = np.flatnonzero(rows & (np.abs(a["rate"]) < STATIC_RATE_DPS))
        if static.size == 0:
            return
        orient = a["orientation"][static]
        for o in np.unique(orient).tolist():
            sel = static[orient == o]
            if self.stage == "range":
                self.logs.setdefault(o, _Log()).add_range(a["temp"][sel])
                continue
            log = self.logs.get(o)
            if log is None:  # skipped after the range pass
                continue
            y = [a["y"][sel, k] for k in range(6)]
            if self.stage == "median":
                log.add_median(y)
            else:
                log.add_bins(a["temp"][sel], y)

    def end_pass(self) -> None:
        if self.stage == "range":
            self._end_range()
        elif self.stage == "median":
            for log in self.logs.values():
                for k in range(6):
                    log.medians[k].add(log.filters[k].flush())
                log.median = np.array([m.median() for m in log.medians])
                log.medians = []
                log.filters = [_MedianStream() for _ in range(6)]
                hi = log.t_max - log.t_ref  # the largest tau (t -> t - t_ref is monotone), and `lo` the smallest
                log.width = (hi - log.lo) / N_BINS
            self.stage = "bins"
        elif self.stage == "bins":
            for o, log in sorted(self.logs.items()):
                log.end_bins()
                keep = log.count > 0
                tb, cnt = log.sum_tau[keep] / log.count[keep], log.count[keep]
                coef = np.zeros((6, ORDER + 1))
                for k in range(6):
                    if tb.size > ORDER:
                        coef[k] = np.polyfit(tb, log.sum_v[k][keep] / cnt, ORDER)
                self.ref.fits[o] = Px4Fit(t_ref_c=log.t_ref, t_min_c=log.t_min, t_max_c=log.t_max, coef=coef)
            self.logs = {}
            self.stage = "done"

    def _end_range(self) -> None:
        for o, log in sorted(self.logs.items()):
            if log.n < MEDIAN_WINDOW or log.t_max - log.t_min <= 0:
                self.ref.skipped[o] = 0.0
                continue
            n_bins = max(int(np.ceil(log.t_max - log.t_min)), 1)
            occupied = log.occupancy(n_bins)
            if occupied < MIN_SWEEP_OCCUPANCY:
                self.ref.skipped[o] = occupied
                continue
            log.t_ref = 0.5 * (log.t_min + log.t_max)
            log.lo = log.t_min - log.t_ref
            log.filters = [_MedianStream() for _ in range(6)]
            log.medians = [ValueCounts() for _ in range(6)]
        self.logs = {o: log for o, log in self.logs.items() if o not in self.ref.skipped}
        self.stage = "median" if self.logs else "done"

    def result(self) -> Px4Reference:
        if self.stage != "done":
            raise RuntimeError(f"PX4's fit needs another pass over the rows (stage {self.stage})")
        return self.ref
