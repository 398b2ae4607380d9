"""Monitor rows: 1 s means of the IMU (and the chamber readings) while ramping and soaking.

They show what the IMU did between records (its thermal lag, its warm-up) at a fraction of
the raw data's size; they are stored as `kind="monitor"` sample blocks without a step.
"""

from __future__ import annotations

import logging
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
    bins = offs // per_bin
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

    t_rows = means((t0_s + (offs + 1) / rate_hz).astype(float))
    return SampleBlock(kind="monitor", step_idx=None, run=run, orientation=orientation, t0_s=float(t_rows[0]),
                       rate_hz=1.0 / average_s,
                       counter=np.rint((t_rows - t_rows[0]) / average_s).astype(np.int64),
                       accel_g=means(rec.accel_g), gyro_dps=means(rec.gyro_dps), temp_c=means(rec.temp_c),
                       chamber=np.asarray(chamber, dtype=float), table=np.array([(t0_s, 0.0)]))


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
