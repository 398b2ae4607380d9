"""Monitor rows: 1 s means of the IMU (and the chamber readings) while ramping and soaking.

They show what the IMU did between records (its thermal lag, its warm-up) at a fraction of
the raw data's size; they are stored as `kind="monitor"` sample blocks without a step.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from labrunner.drivers.protocols import Chamber, Imu, ImuRecord
from labrunner.store import SampleBlock

log = logging.getLogger(__name__)


def average_block(rec: ImuRecord, *, start: int, t0_s: float, rate_hz: float, average_s: float, run: int,
                  orientation: str, chamber: np.ndarray) -> SampleBlock | None:
    """Means of `rec` over bins of `average_s` (by frame counter after `start`); None if it is empty.

    `t0_s` is the campaign time of frame `start`; frames missing from a bin just make its mean
    of fewer frames, and a bin with no frame gives no row.
    """
    if len(rec) == 0:
        return None
    per_bin = max(1, int(round(average_s * rate_hz)))
    offs = rec.counter - (start + 1)
    t = (t0_s + (offs + 1) / rate_hz).astype(float)
    columns = (rec.accel_g, rec.gyro_dps, rec.temp_c, t)
    means = _full_bin_means(offs, per_bin, columns)
    if means is None:
        means = _bin_means(offs // per_bin, columns)
    accel, gyro, temp, t_rows = means
    return SampleBlock(kind="monitor", step_idx=None, run=run, orientation=orientation, t0_s=float(t_rows[0]),
                       rate_hz=1.0 / average_s,
                       counter=np.rint((t_rows - t_rows[0]) / average_s).astype(np.int64),
                       accel_g=accel, gyro_dps=gyro, temp_c=temp,
                       chamber=np.asarray(chamber, dtype=float), table=np.array([(t0_s, 0.0)]))


def _bin_means(bins: np.ndarray, columns: tuple[np.ndarray, ...]) -> list[np.ndarray]:
    """Means of each array of `columns` (rows per frame) over the frames of each bin, bins in ascending order."""
    if bins.size > 1 and np.all(bins[1:] >= bins[:-1]):  # a record's counters ascend: bins without a sort
        first = np.concatenate(([0], np.flatnonzero(bins[1:] != bins[:-1]) + 1))
        counts = np.diff(np.append(first, bins.size))
        inv = np.repeat(np.arange(first.size), counts)
    else:
        _, inv, counts = np.unique(bins, return_inverse=True, return_counts=True)
    n_bins = counts.size

    def means(a: np.ndarray) -> np.ndarray:
        # Sums per bin in the frames' order (bincount adds in input order, as np.add.at did).
        flat = a.reshape(a.shape[0], -1)
        out = np.empty((n_bins, flat.shape[1]))
        for j in range(flat.shape[1]):
            out[:, j] = np.bincount(inv, weights=flat[:, j], minlength=n_bins)
        return (out / counts[:, None]).reshape((n_bins,) + a.shape[1:])

    return [means(a) for a in columns]


def _full_bin_means(offs: np.ndarray, per_bin: int, columns: tuple[np.ndarray, ...]) -> list[np.ndarray] | None:
    """`_bin_means` when every bin is full (the frames are 0, 1, ... n - 1 after the start, n a whole number of
    bins: a monitor stretch without a lost frame), to the bit; None otherwise. The columns are laid out as
    (value, frame in its bin, bin) and summed over the frame axis from 0.0, one bin's frames after another in
    their order as bincount adds them (the bins are the contiguous inner axis, so numpy adds whole rows of bins,
    not pairwise), in one reduction instead of a bincount per column."""
    n = offs.size
    n_bins = n // per_bin
    # One bin: numpy would drop the bin axis and sum each column pairwise (another rounding): not here.
    if n_bins < 2 or n % per_bin or offs[0] != 0 or offs[-1] != n - 1 or not bool(np.all(np.diff(offs) == 1)):
        return None
    widths = [math.prod(a.shape[1:]) for a in columns]
    stacked = np.empty((sum(widths), per_bin, n_bins))
    row = 0
    for a, w in zip(columns, widths):
        stacked[row:row + w] = a.reshape(n_bins, per_bin, w).transpose(2, 1, 0)
        row += w
    sums = np.add.reduce(stacked, axis=1, initial=0.0)
    sums /= per_bin  # a count of per_bin in every bin (bincount's means divide by the int64 counts: the same)
    out, row = [], 0
    for a, w in zip(columns, widths):
        out.append(np.ascontiguousarray(sums[row:row + w].T).reshape((n_bins,) + a.shape[1:]))
        row += w
    return out


@dataclass
class MonitorWindow:
    """One stretch being monitored: where the IMU stream stood, when, and the chamber readings."""

    start: int
    t0_s: float
    chamber: list[tuple[float, float]] = field(default_factory=list)


class ImuMonitor:
    """Opens and closes monitor stretches on an IMU and a chamber; `now()` is campaign time."""

    def __init__(self, imu: Imu, chamber: Chamber, now: Callable[[], float], average_s: float,
                 read_chamber: Callable[[], float] | None = None) -> None:
        self.imu = imu
        self.chamber = chamber
        self.now = now
        self.average_s = average_s
        # How the chamber is read (the sequencer's, which does not ask again for a reading of this moment).
        self.read_chamber = read_chamber if read_chamber is not None else chamber.read_temperature

    def begin(self) -> MonitorWindow:
        start = self.imu.begin_record()
        t0 = self.now()
        return MonitorWindow(start=start, t0_s=t0, chamber=[(t0, self.read_chamber())])

    def end(self, window: MonitorWindow, seconds: float, *, timeout_s: float, run: int,
            orientation: str) -> SampleBlock | None:
        """Collect the stretch's frames (`seconds` long) and average them."""
        n = int(round(seconds * self.imu.rate_hz))
        rec = self.imu.end_record(window.start, n, timeout_s=timeout_s)
        window.chamber.append((self.now(), self.read_chamber()))
        block = average_block(rec, start=window.start, t0_s=window.t0_s, rate_hz=self.imu.rate_hz,
                              average_s=self.average_s, run=run, orientation=orientation,
                              chamber=np.array(window.chamber))
        if block is None:
            log.debug("monitor stretch of %.1f s from %.1f s: no frames", seconds, window.t0_s)
        return block
