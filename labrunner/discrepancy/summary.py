"""A store's campaign as 1 s summaries, read chunk by chunk: what `labrunner diagnose DB` analyses.

The diagnosis fits block means of rows weighted by their information, so a record step of raw
50 Hz samples carries the same information as its 1 s means weighted by their sample counts
(every candidate term changes little within a second). Reading the store one sample block at a
time and keeping only those means, the samples' count and, per channel, the within-second sum
of squares of the error (measured minus reference) bounds memory by the number of seconds
logged rather than the number of samples (12 M samples of the paper campaign are 0.55 M rows), and
at most `MAX_BINS_PER_BLOCK` summaries per sample block (longer means in longer records).

What the raw samples say beyond the means is kept too, so the figures that are statistics of the
samples stay so: the held-out and in-sample RMS over the samples (`sample_rms`: within-second
spread plus the means' residuals), the white-noise density (successive differences of the raw
samples) and the relative weight of the monitor rows (their noise against the samples').
Rows already at 1 s or slower (the store's monitor rows) pass through unchanged.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from labrunner.domain import CSV_COLUMNS, UP_VECTORS, orientation_index

logger = logging.getLogger(__name__)

BIN_S = 1.0  # the summaries' length
# ... or longer in a long sample block: at most this many summaries per block, so the rows (and the
# memory) follow the number of blocks and seconds of monitor rows, not the length of the records
# (a paper record step of 60 s keeps its 1 s means; one ten times as long gets 10 s means).
MAX_BINS_PER_BLOCK = 60
_RESERVOIR = 1_000_000  # successive differences of raw samples kept for the noise statistics
_CHANNELS = 6


@dataclass
class RowSummary:
    """What each row stands for, aligned with the frame's rows.

    Rows that are means of raw samples (`averaged`) carry their sample count and the within-row
    sum of squares of the error; other rows count 1 and 0. `raw_variance` (the white-noise
    variance of one raw sample from successive differences, per channel), `raw_density` (the
    white-noise density, sensor units per sqrt(Hz)) and `raw_spacing_s` describe the raw samples
    the averaged rows came from."""

    samples: np.ndarray  # (N,) raw samples per row
    within_ss: np.ndarray  # (N, 6) sum over the row's samples of (error - row mean error)^2
    averaged: np.ndarray  # (N,) bool: the row is a mean of raw samples
    raw_variance: np.ndarray | None  # (6,) per raw sample, None without averaged rows
    raw_density: np.ndarray | None  # (6,)
    raw_spacing_s: float | None

    def take(self, order: np.ndarray) -> RowSummary:
        """The rows reordered (or selected)."""
        return RowSummary(self.samples[order], self.within_ss[order], self.averaged[order], self.raw_variance,
                          self.raw_density, self.raw_spacing_s)

    @property
    def total_samples(self) -> int:
        return int(self.samples.sum())


class _Differences:
    """A bounded, evenly thinned collection of successive differences of raw samples."""

    def __init__(self, limit: int = _RESERVOIR) -> None:
        self.limit = limit
        self.stride = 1
        self.offset = 0  # samples seen, for a stride that runs across blocks
        self.parts: list[np.ndarray] = []
        self.size = 0

    def add(self, d: np.ndarray) -> None:
        first = (-self.offset) % self.stride
        self.offset += d.shape[0]
        kept = d[first::self.stride]
        if kept.size:
            self.parts.append(kept.astype(np.float32))
            self.size += kept.shape[0]
        if self.size > self.limit:  # thin what is kept by two, and from now on
            merged = np.concatenate(self.parts)[::2]
            self.parts, self.size, self.stride = [merged], merged.shape[0], self.stride * 2

    def values(self) -> np.ndarray:
        return np.concatenate(self.parts).astype(float) if self.parts else np.zeros((0, _CHANNELS))


def _mad_sigma(d: np.ndarray) -> np.ndarray:
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)


def _interp(t: np.ndarray, readings: np.ndarray, default: float) -> np.ndarray:
    """Instrument readings taken during a block at the sample times (as the store's frame has them)."""
    if readings.size == 0:
        return np.full(t.size, default)
    if readings.shape[0] == 1:
        return np.full(t.size, float(readings[0, 1]))
    return np.interp(t, readings[:, 0], readings[:, 1])


class _Builder:
    """Summary rows accumulated block by block."""

    def __init__(self, bin_s: float) -> None:
        self.bin_s = bin_s
        self.cols: dict[str, list[np.ndarray]] = {c: [] for c in CSV_COLUMNS}
        self.samples: list[np.ndarray] = []
        self.within: list[np.ndarray] = []
        self.averaged: list[np.ndarray] = []
        self.weight_diffs = _Differences()  # output differences at a steady table rate (row weights)
        self.error_diffs = _Differences()  # error differences times sqrt(dt) (noise density)
        self.raw_spacing: list[float] = []
        self.t_range = [np.inf, -np.inf]  # of the raw samples (the rows' times are means)

    def add(self, block: Any) -> None:
        n = len(block)
        if n == 0:
            return
        t = block.times()
        self.t_range = [min(self.t_range[0], float(t[0])), max(self.t_range[1], float(t[-1]))]
        chamber = _interp(t, block.chamber, float("nan"))
        table = _interp(t, block.table, 0.0)
        output = np.concatenate([np.asarray(block.accel_g, dtype=float), np.asarray(block.gyro_dps, dtype=float)],
                                axis=1)
        temp = np.asarray(block.temp_c, dtype=float)
        if block.rate_hz * self.bin_s <= 1.5:  # already 1 s rows (or slower): as they are
            self._append(t, block.run, block.orientation, chamber, temp, table, output, np.ones(n, dtype=np.int64),
                         np.zeros((n, _CHANNELS)), averaged=False)
            return
        up = UP_VECTORS[orientation_index(np.array([block.orientation]))[0]]
        error = output - np.concatenate([np.broadcast_to(up, (n, 3)), up[None, :] * table[:, None]], axis=1)
        if n > 1:
            dt = np.diff(t)
            good = dt > 0
            de = np.diff(error, axis=0)[good] * np.sqrt(dt[good])[:, None]
            self.error_diffs.add(de)
            steady = good & (table[1:] == table[:-1])
            self.weight_diffs.add(np.diff(output, axis=0)[steady])
            self.raw_spacing.append(float(np.median(dt[good])) if good.any() else 1.0 / block.rate_hz)
        counter = np.asarray(block.counter, dtype=np.int64)
        per_bin = max(int(round(block.rate_hz * self.bin_s)), -(-n // MAX_BINS_PER_BLOCK), 1)
        key = (counter - counter[0]) // per_bin
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        counts = np.diff(np.r_[starts, n])

        def mean(v: np.ndarray) -> np.ndarray:
            return np.add.reduceat(v, starts, axis=0) / (counts if v.ndim == 1 else counts[:, None])

        e_mean = mean(error)
        dev = error - np.repeat(e_mean, counts, axis=0)
        within = np.add.reduceat(dev * dev, starts, axis=0)
        self._append(mean(t), block.run, block.orientation, mean(chamber), mean(temp), mean(table), mean(output),
                     counts.astype(np.int64), within, averaged=True)

    def _append(self, t: np.ndarray, run: int, orientation: str, chamber: np.ndarray, temp: np.ndarray,
                table: np.ndarray, output: np.ndarray, samples: np.ndarray, within: np.ndarray, averaged: bool) -> None:
        m = t.size
        self.cols["t_s"].append(t)
        self.cols["run"].append(np.full(m, run, dtype=np.int64))
        self.cols["orientation"].append(np.full(m, orientation, dtype=object))
        self.cols["chamber_c"].append(chamber)
        self.cols["imu_temp_c"].append(temp)
        self.cols["table_rate_dps"].append(table)
        for j, c in enumerate(CSV_COLUMNS[6:]):
            self.cols[c].append(output[:, j])
        self.samples.append(samples)
        self.within.append(within)
        self.averaged.append(np.full(m, averaged))

    def result(self) -> tuple[pd.DataFrame, RowSummary]:
        if not self.samples:
            return pd.DataFrame({c: pd.Series(dtype=float) for c in CSV_COLUMNS}), RowSummary(
                np.zeros(0, dtype=np.int64), np.zeros((0, _CHANNELS)), np.zeros(0, dtype=bool), None, None, None)
        frame = pd.DataFrame({c: np.concatenate(v) for c, v in self.cols.items()})
        averaged = np.concatenate(self.averaged)
        raw_variance = raw_density = None
        spacing = None
        if averaged.any():
            wd = self.weight_diffs.values()
            if wd.shape[0] >= 20:
                raw_variance = np.maximum(_mad_sigma(wd) ** 2 / 2.0, 1e-30)
            ed = self.error_diffs.values()
            if ed.shape[0] >= 10:
                raw_density = _mad_sigma(ed)
            spacing = float(np.median(self.raw_spacing)) if self.raw_spacing else None
        summary = RowSummary(np.concatenate(self.samples), np.concatenate(self.within), averaged, raw_variance,
                             raw_density, spacing)
        order = np.argsort(frame["t_s"].to_numpy(), kind="stable")  # monitor rows between the records
        if np.any(order != np.arange(order.size)):
            frame = frame.iloc[order].reset_index(drop=True)
            summary = summary.take(order)
        return frame, summary


def summarize_blocks(blocks: Any, bin_s: float = BIN_S) -> tuple[pd.DataFrame, RowSummary]:
    """Sample blocks (`labrunner.store.SampleBlock`, in time order) as summary rows in campaign-CSV
    columns, time-ordered, and what each row stands for."""
    frame, summary, _ = _summarize(blocks, bin_s)
    return frame, summary


def _summarize(blocks: Any, bin_s: float) -> tuple[pd.DataFrame, RowSummary, list[float]]:
    builder = _Builder(bin_s)
    for block in blocks:
        builder.add(block)
    return (*builder.result(), builder.t_range)


@dataclass
class StoreSummary:
    """A store's campaign, summarised: the frame (campaign-CSV columns and `power_on`), what each
    row stands for, and the provenance `labrunner diagnose` reports."""

    frame: pd.DataFrame
    summary: RowSummary
    provenance: dict[str, Any]


def read_store_summary(address: Any, campaign: int | None = None, bin_s: float = BIN_S) -> StoreSummary:
    """Read a store's campaign (records and monitor rows) block by block into 1 s summaries."""
    from labrunner.campaign_csv import read_campaign
    from labrunner.data_source import mark_power_ons, step_progress
    from labrunner.errors import UserError
    from labrunner.store import Store
    from labrunner.store_address import store_address

    # The sample blocks' pages are checked by reading them all, as `load_campaign_data` does (see
    # Store.open_existing): a damaged one raises the whole check's StoreDamage.
    with Store.open_existing(store_address(address), check_samples=False) as store:
        cid = store.resolve(campaign)
        info = store.campaign(cid)
        frame, summary, t_range = _summarize(store.blocks(cid, ("record", "monitor")), bin_s)
        if frame.empty:
            raise UserError(f"{store.path}: campaign {cid} has no recorded samples yet")
        frame = read_campaign(frame, name=f"{store.path} campaign {cid}")
        frame = mark_power_ons(frame, store.events_frame(cid))
        provenance: dict[str, Any] = {
            "source": str(store.path.resolve()), "kind": "store", "campaign_id": cid, "campaign": info.name,
            "procedure_sha256": info.procedure_sha256, "status": info.status, "rows": summary.total_samples,
            "t_range_s": t_range,
            "recorded_with": info.software_version, "summary_rows": len(frame),
            "summary": f"raw samples faster than 1 per {bin_s:g} s averaged over {bin_s:g} s",
        }
        provenance.update(step_progress(store, cid))
    logger.info("%s: %d samples as %d summary rows", address, summary.total_samples, len(frame))
    return StoreSummary(frame, summary, provenance)


def sample_rms(summary: RowSummary | None, residual: np.ndarray) -> np.ndarray:
    """(6,) RMS over the raw samples of measured minus model, from the rows' residuals (N, 6) (the
    model changes little within a row, so a sample's residual is its row's plus its deviation
    from the row mean). Without a summary, the RMS over the rows."""
    r = np.asarray(residual, dtype=float)
    if summary is None:
        return np.sqrt(np.mean(r * r, axis=0))
    n = summary.samples.astype(float)
    return np.sqrt((summary.within_ss.sum(axis=0) + n @ (r * r)) / n.sum())


def channel_sample_rms(summary: RowSummary | None, residual: np.ndarray, channel: int) -> float:
    """RMS over the raw samples of one channel's residual (N,): its rows' plus its within-row spread."""
    r = np.asarray(residual, dtype=float)
    if summary is None:
        return float(np.sqrt(np.mean(r * r)))
    n = summary.samples.astype(float)
    return float(np.sqrt((float(summary.within_ss[:, channel].sum()) + float(n @ (r * r))) / n.sum()))


def weighted_percentile(values: np.ndarray, counts: np.ndarray | None, q: float) -> float:
    """`np.percentile(np.repeat(values, counts), q)` without the repeat (linear interpolation): a
    statistic over the raw samples when each row stands for `counts` of them."""
    v = np.asarray(values, dtype=float)
    if counts is None:
        return float(np.percentile(v, q))
    order = np.argsort(v, kind="stable")
    v, c = v[order], np.asarray(counts, dtype=np.int64)[order]
    ends = np.cumsum(c)  # sample k (0-based) is row searchsorted(ends, k, "right")
    pos = (ends[-1] - 1) * q / 100.0
    lo, frac = int(np.floor(pos)), pos - np.floor(pos)
    a = v[np.searchsorted(ends, lo, side="right")]
    b = v[np.searchsorted(ends, min(lo + 1, int(ends[-1]) - 1), side="right")]
    return float(a + (b - a) * frac)
