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
