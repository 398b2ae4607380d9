"""Measured campaign rows as the arrays the error model needs.

The campaign CSV gives outputs and the conditions; the reference values follow from
each row: +1 g along the up axis, the table rate about the up axis, Earth
rate neglected. What the analysis fits is the *error*: measured output minus reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from labrunner.campaign_csv import OUTPUT_COLUMNS, read_campaign
from labrunner.domain import CHANNELS, UP_VECTORS, orientation_index
from labrunner.imu.model import ImuInputs

from .summary import RowSummary
from .temperature import (
    dequantize,
    is_jittery,
    smooth_temperature,
    smoothing_rows,
    temperature_jitter,
    temperature_rate,
)

# Below this quantum the rounding error is negligible against the model's temperature slopes.
_MIN_COARSE_QUANTUM_C = 0.05


@dataclass
class Measurements:
    """One campaign, rows in time order within each run."""

    t_s: np.ndarray  # (N,) s
    run: np.ndarray  # (N,) power-on counter (0, 1, ...: the rows since one power-on)
    orientation: np.ndarray  # (N,) index into labrunner.domain.ORIENTATIONS
    temp_c: np.ndarray  # (N,) IMU temperature (de-quantised when the log is coarse)
    chamber_c: np.ndarray  # (N,) chamber air, NaN when not logged
    table_rate_dps: np.ndarray  # (N,)
    force_g: np.ndarray  # (N, 3) reference specific force, body frame
    rate_dps: np.ndarray  # (N, 3) reference angular rate, body frame
    t_on_s: np.ndarray  # (N,) time since the power-on (the first row after it)
    output: np.ndarray  # (N, 6) measured, channel order labrunner.domain.CHANNELS
    row_dt_s: float  # typical spacing of consecutive rows within a run
    temperature_quantum_c: float | None  # the logger's temperature step, when it is coarse
    logged_temp_c: np.ndarray | None = None  # imu_temp_c as logged, when it was de-quantised
    # Rows need not be alike: a log may mix raw samples with averaged rows (a labrunner store
    # exported with its 1 s monitor rows). Each row's weight is its information relative to
    # the log's most common kind of row (a 1 s mean of 50 Hz samples weighs about 50), and
    # its spacing is that of its own kind of row.
    row_weight: np.ndarray | None = None  # (N,), ones when all rows are alike
    row_spacing_s: np.ndarray | None = None  # (N,)
    # Where the power-ons come from: "column" (the log's power_on column, or a store's power-on
    # events) or "assumed" (a change of `run` after a gap in time; none without a gap).
    power_on_source: str = "column"
    run_label: np.ndarray | None = None  # (N,) the log's `run` column
    continuous_run_changes: int = 0  # changes of `run` not taken as power-ons (no gap, or no power_on mark)
    temperature_jitter_c: float = 0.0  # row-to-row jitter of a jittering temperature sensor (0: not jittery)
    temperature_smoothing_s: float = 0.0  # the centred moving mean it was smoothed with (0: not smoothed)
    # Rows that are means of raw samples (a store read in 1 s summaries): their sample counts,
    # within-row spread and the raw samples' noise (None: every row is one sample or a logged mean).
    summary: RowSummary | None = None
    _error: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.row_weight is None:
            self.row_weight = np.ones(self.t_s.size)
        if self.row_spacing_s is None:
            self.row_spacing_s = np.full(self.t_s.size, self.row_dt_s)

    def __len__(self) -> int:
        return int(self.t_s.size)

    @property
    def samples(self) -> np.ndarray:
        """(N,) raw samples each row stands for (ones unless rows are summaries)."""
        return self.summary.samples if self.summary is not None else np.ones(self.t_s.size, dtype=np.int64)

    @property
    def sample_count(self) -> int:
        """Raw samples the rows stand for (the rows, unless they are summaries)."""
        return self.summary.total_samples if self.summary is not None else len(self)

    @property
    def reference(self) -> np.ndarray:
        """(N, 6) what an ideal IMU would output."""
        return np.concatenate([self.force_g, self.rate_dps], axis=1)

    @property
    def error(self) -> np.ndarray:
        """(N, 6) measured minus reference: what the error model has to explain (computed once)."""
        if self._error is None:
            self._error = self.output - self.reference
        return self._error

    @property
    def channels(self) -> tuple[str, ...]:
        return CHANNELS

    @property
    def remounts(self) -> np.ndarray:
        """Rows where the orientation changes (the IMU was remounted)."""
        return np.flatnonzero(self.orientation[1:] != self.orientation[:-1]) + 1

    def imu_inputs(self) -> ImuInputs:
        """The rows as inputs of `labrunner.imu.model.ImuModel` (to evaluate a model on this campaign)."""
        return ImuInputs(t_s=self.t_s, run=self.run, t_on_s=self.t_on_s, temp_c=self.temp_c,
                         force_g=self.force_g, rate_dps=self.rate_dps)

    @classmethod
    def from_frame(cls, frame: pd.DataFrame, summary: RowSummary | None = None) -> Measurements:
        """From a frame in campaign-CSV columns (validated by `read_campaign`); `summary`, aligned with
        the frame's rows, when rows are means of raw samples (`summary.read_store_summary`)."""
        frame = read_campaign(frame)
        if summary is not None and summary.samples.size != len(frame):
            raise ValueError(f"summary of {summary.samples.size} rows for a frame of {len(frame)}")
        run = frame["run"].to_numpy(dtype=np.int64)
        t = frame["t_s"].to_numpy(dtype=float)
        order = _time_order(t, run)
        frame = frame.iloc[order].reset_index(drop=True)
        if summary is not None:
            summary = summary.take(order)
        run = run[order]
        t = t[order]
        orient = orientation_index(frame["orientation"].astype(str).to_numpy())
        up = UP_VECTORS[orient]
        table = frame["table_rate_dps"].to_numpy(dtype=float)
        temp = frame["imu_temp_c"].to_numpy(dtype=float)
        label = run
        power, source = _power_ons(t, run, frame["power_on"].to_numpy() if "power_on" in frame.columns else None)
        segment = np.cumsum(power) - 1
        # A power-on's rows keep the run label of its first row (labels name runs in the report and
        # in the extended model's pinned offsets); numbered afresh only if labels repeat.
        labels = label[np.flatnonzero(power)]
        run = labels[segment] if np.unique(labels).size == labels.size else segment + 1
        first = t[np.flatnonzero(power)][segment]
        label_changes = int(np.sum(label[1:] != label[:-1]))
        continuous = int(np.sum((label[1:] != label[:-1]) & ~power[1:]))
        quantum = temperature_quantum(temp)
        logged = None
        jitter, reversals = temperature_jitter(t, temp, run)
        smoothing_s = 0.0
        if is_jittery(reversals):
            # A jittering sensor (quantised or not): the crossings de-quantisation relies on are
            # noise; a centred moving mean recovers the slow path instead.
            rows = smoothing_rows(jitter)
            logged, temp = temp, smooth_temperature(t, temp, run, rows)
            smoothing_s = rows * _row_spacing(t, run)
        elif quantum is not None:
            logged, temp = temp, dequantize(t, temp, run, quantum, _step_time(t, temp, run, quantum))
        output = frame.loc[:, list(OUTPUT_COLUMNS)].to_numpy(dtype=float)
        weight, spacing, typical = _row_weights(t, run, output, table, summary)
        return cls(
            t_s=t, run=run, orientation=orient, temp_c=temp,
            chamber_c=frame["chamber_c"].to_numpy(dtype=float), table_rate_dps=table,
            force_g=up.copy(), rate_dps=up * table[:, None], t_on_s=t - first,
            output=output, row_dt_s=typical, temperature_quantum_c=quantum, logged_temp_c=logged,
            row_weight=weight, row_spacing_s=spacing, power_on_source=source, run_label=label,
            continuous_run_changes=continuous if label_changes else 0,
            temperature_jitter_c=jitter if smoothing_s else 0.0, temperature_smoothing_s=smoothing_s,
            summary=summary if summary is not None and summary.averaged.any() else None,
        )


def _power_ons(t: np.ndarray, run: np.ndarray, column: np.ndarray | None) -> tuple[np.ndarray, str]:
    """(N,) True on the first row after each power-on, and where that came from.

    The log's `power_on` column says it; without one, a change of `run` is taken for a power-on
    only where the recording stops (a gap in time, or the clock restarting): a log without gaps
    is one continuous recording, whatever its run labels (time since power-on runs on)."""
    power = np.zeros(t.size, dtype=bool)
    power[:1] = True
    if column is not None:
        power |= np.asarray(column, dtype=np.int64) == 1
        return power, "column"
    dt = np.diff(t)
    spacing = _row_spacing(t, run)
    gap = (dt > max(3.0 * spacing, spacing + 0.5)) | (dt < 0)
    power[1:] = (run[1:] != run[:-1]) & gap
    return power, "assumed"


def _time_order(t: np.ndarray, run: np.ndarray) -> np.ndarray:
    """Row order for the recursions: as given when time never goes back, else run by run.

    A campaign's clock normally runs on across power-ons; if it restarts per run the
    runs are kept in order of first appearance, each in time order.
    """
    if t.size < 2 or np.all(np.diff(t) >= 0):
        return np.arange(t.size)
    _, first_pos = np.unique(run, return_index=True)
    rank = np.empty(run.max() - run.min() + 1, dtype=np.int64)
    rank[run[np.sort(first_pos)] - run.min()] = np.arange(first_pos.size)
    return np.lexsort((t, rank[run - run.min()]))


def _row_spacing(t: np.ndarray, run: np.ndarray) -> float:
    d = np.diff(t)[run[1:] == run[:-1]]
    d = d[d > 0]
    return float(np.median(d)) if d.size else 1.0


def _row_weights(t: np.ndarray, run: np.ndarray, output: np.ndarray, table: np.ndarray,
                 summary: RowSummary | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Per row: weight (information relative to the most common kind of row) and spacing;
    and the most common kind's spacing.

    Rows are grouped by their spacing (half-octave classes); each class's white-noise level
    is measured on the data, from successive differences within the class (robustly: the
    slow thermal signal and the odd rate step do not count), so a 1 Hz log of averages and a
    1 Hz log of single samples get the weights they deserve.

    Rows that are summaries of raw samples (`summary.averaged`) are a kind of their own: a mean of
    n raw samples weighs n raw samples, whose noise the summary measured before averaging.
    """
    if summary is not None and summary.averaged.any() and summary.raw_variance is not None:
        return _summary_weights(t, run, output, table, summary)
    n = t.size
    same = (run[1:] == run[:-1]) & (np.diff(t) > 0)
    d = np.diff(t)
    nxt = np.full(n, np.inf)
    prv = np.full(n, np.inf)
    nxt[:-1] = np.where(same, d, np.inf)
    prv[1:] = np.where(same, d, np.inf)
    spacing = np.minimum(nxt, prv)
    typical = _row_spacing(t, run)
    spacing[~np.isfinite(spacing)] = typical
    cls = np.round(2.0 * np.log2(np.maximum(spacing, 1e-6))).astype(np.int64)
    classes, counts = np.unique(cls, return_counts=True)
    weight = np.ones(n)
    if classes.size == 1:
        return weight, spacing, typical
    variance: dict[int, np.ndarray] = {}
    for c in classes:
        v = _pair_variance(np.flatnonzero(cls == c), same, table, output)
        if v is not None:
            variance[int(c)] = v
    if not variance:
        return weight, spacing, typical
    ref = max(variance, key=lambda c: counts[classes == c][0])
    typical = float(np.median(spacing[cls == ref]))
    known = np.array(sorted(variance))
    for c in classes:
        nearest = int(known[np.argmin(np.abs(known - c))])
        weight[cls == c] = float(np.median(variance[ref] / variance[nearest]))
    return weight, spacing, typical


def _pair_variance(idx: np.ndarray, same: np.ndarray, table: np.ndarray, output: np.ndarray) -> np.ndarray | None:
    """Per-channel noise variance of one kind of row, from successive pairs of them in one run at one
    table rate (robust: MAD of the differences); None with fewer than 20 such pairs."""
    n = output.shape[0]
    pair = idx[:-1][(np.diff(idx) == 1) & same[idx[:-1].clip(max=n - 2)] & (table[idx[1:]] == table[idx[:-1]])]
    if pair.size < 20:
        return None
    dy = output[pair + 1] - output[pair]
    mad = np.median(np.abs(dy - np.median(dy, axis=0)), axis=0)
    return np.maximum((1.4826 * mad) ** 2 / 2.0, 1e-30)


def _summary_weights(t: np.ndarray, run: np.ndarray, output: np.ndarray, table: np.ndarray,
                     summary: RowSummary) -> tuple[np.ndarray, np.ndarray, float]:
    """`_row_weights` for a log of summaries: the averaged rows weigh their samples (in units of the
    most common kind of row, as when the samples themselves were rows), the other rows by their
    noise against it; the typical spacing is the rows' own."""
    assert summary.raw_variance is not None
    _, spacing, typical = _row_weights(t, run, output, table)  # spacings only: weights below
    averaged = summary.averaged
    same = (run[1:] == run[:-1]) & (np.diff(t) > 0)
    cls = np.round(2.0 * np.log2(np.maximum(spacing, 1e-6))).astype(np.int64)
    cls[averaged] = np.iinfo(np.int64).min  # never paired with the other rows
    raw_count = float(summary.samples[averaged].sum())
    variance: dict[int, np.ndarray] = {}
    counts: dict[int, float] = {}
    for c in np.unique(cls[~averaged]):
        idx = np.flatnonzero(cls == c)
        counts[int(c)] = float(idx.size)
        v = _pair_variance(idx, same, table, output)
        if v is not None:
            variance[int(c)] = v
    weight = summary.samples.astype(float)
    ref_var = summary.raw_variance
    top = max(counts, key=counts.__getitem__) if counts else None
    if top is not None and top in variance and counts[top] > raw_count:
        # another kind of row is the most common: the reference, as without summaries
        ref_var = variance[top]
        weight = weight * float(np.median(ref_var / summary.raw_variance))
    if variance:
        known = np.array(sorted(variance))
        for c in counts:
            nearest = int(known[np.argmin(np.abs(known - c))])
            weight[cls == c] = float(np.median(ref_var / variance[nearest]))
    return weight, spacing, typical


def _step_time(t: np.ndarray, temp: np.ndarray, run: np.ndarray, quantum: float) -> float:
    """How long a typical ramp takes to cross one logger step (s)."""
    rate = np.abs(temperature_rate(t, temp, run))
    ramping = rate[rate > 0.1 / 60.0]
    if ramping.size < 10:
        return 60.0
    return float(np.clip(quantum / np.percentile(ramping, 75), 5.0, 600.0))


def temperature_quantum(temp: np.ndarray) -> float | None:
    """The temperature step of a coarse logger (all values on a grid), or None."""
    values = np.unique(np.round(temp, 6))
    if values.size < 3:
        return None
    steps = np.diff(values)
    q = float(steps.min())
    if q < _MIN_COARSE_QUANTUM_C:
        return None
    k = values / q
    return q if np.all(np.abs(k - np.round(k)) < 1e-3) else None
