"""Short blocks of consecutive rows: the unit the analysis fits, whitens and holds out.

Every candidate term is linear in its coefficients once its nonlinear parameter is
fixed, so the block means of the regressors and of the error are an exact (if slightly
less efficient) basis for the fit: what is lost is the variation within a block, mostly
white noise. Blocks never straddle a power-on, a remount, a rate change or a logging
gap, and end after `block_s` seconds or `temp_step_c` of temperature travel, so the
regressors change little within one. This turns a few hundred thousand rows into some
thousands of blocks, which keeps the drift filter and the many refits of the cause
search fast. (The held-out RMS reported as gain is computed on the rows themselves.)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse

from .measurements import Measurements


@dataclass
class Blocks:
    """Contiguous row ranges; block k is rows start[k] : start[k] + count[k]."""

    start: np.ndarray  # (M,) first row
    count: np.ndarray  # (M,) rows
    weight: np.ndarray  # (M,) information: the sum of its rows' weights (= count when rows are alike)
    t_s: np.ndarray  # (M,) mean time
    run: np.ndarray  # (M,) run of the block
    new_run: np.ndarray  # (M,) bool: first block of a run
    block_s: float  # the duration limit used
    _averager: sparse.csr_matrix | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return int(self.start.size)

    row_weight: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def mean(self, values: np.ndarray) -> np.ndarray:
        """Block means of row values weighted by the rows' information, (N,) -> (M,) or (N, k) -> (M, k)."""
        if self._averager is None:
            # A sparse averaging matrix: one pass over the rows, much faster than
            # np.add.reduceat along axis 0 of a 2-D array.
            n = int(self.count.sum())
            rw = self.row_weight if self.row_weight.size == n else np.ones(n)
            self._averager = sparse.csr_matrix(
                (rw / np.repeat(self.weight, self.count), (self.row_block(), np.arange(n))), shape=(len(self), n))
        return np.asarray(self._averager @ np.asarray(values, dtype=float))

    def row_block(self) -> np.ndarray:
        """(N,) block index of every row."""
        return np.repeat(np.arange(len(self)), self.count)


def make_blocks(meas: Measurements, block_s: float | None = None, temp_step_c: float = 0.8,
                target_blocks: int = 3000, cut_every_s: float | None = None,
                elapsed_s: np.ndarray | None = None) -> Blocks:
    """Cut the rows into blocks (see module docstring)."""
    n = len(meas)
    # Measurements.__post_init__ fills the per-row weights and spacings when they are not given.
    assert meas.row_weight is not None and meas.row_spacing_s is not None
    t = meas.t_s
    dt = np.diff(t)
    spacing = np.maximum(meas.row_spacing_s[1:], meas.row_spacing_s[:-1])  # each kind of row its own gap
    gap_limit = np.maximum(3.0 * spacing, spacing + 0.5)
    rate = meas.table_rate_dps
    rate_tol = 0.05 + 1e-3 * np.abs(rate[1:])
    hard = np.zeros(n, dtype=bool)
    hard[0] = True
    hard[1:] = ((meas.run[1:] != meas.run[:-1]) | (meas.orientation[1:] != meas.orientation[:-1])
                | (np.abs(np.diff(rate)) > rate_tol) | (dt > gap_limit) | (dt < 0))
    seg = np.cumsum(hard) - 1
    seg_start = np.flatnonzero(hard)

    if block_s is None:
        logged = float(np.sum(np.where(hard[1:], 0.0, dt))) + meas.row_dt_s * seg_start.size
        block_s = float(np.clip(logged / max(target_blocks, 1), 5.0 * meas.row_dt_s, 120.0))
        block_s = max(block_s, meas.row_dt_s)
    t_bin = np.floor((t - t[seg_start][seg]) / block_s).astype(np.int64)

    temp = meas.temp_c  # travel since the segment start (a coarse log is de-quantised already)
    travel = np.zeros(n)
    travel[1:] = np.cumsum(np.abs(np.diff(temp)))
    travel_bin = np.floor((travel - travel[seg_start][seg]) / temp_step_c).astype(np.int64)

    new = hard.copy()
    new[1:] |= (t_bin[1:] != t_bin[:-1]) | (travel_bin[1:] != travel_bin[:-1])
    if cut_every_s and elapsed_s is not None:  # never across a long held-out stretch's edge
        stretch = np.floor(elapsed_s / cut_every_s).astype(np.int64)
        new[1:] |= stretch[1:] != stretch[:-1]
    start = np.flatnonzero(new)
    count = np.diff(np.append(start, n))
    weight = np.add.reduceat(meas.row_weight, start) if n else np.zeros(0)
    blocks = Blocks(start=start, count=count, weight=weight, t_s=np.empty(0), run=meas.run[start],
                    new_run=np.ones(start.size, dtype=bool), block_s=block_s, row_weight=meas.row_weight)
    blocks.t_s = blocks.mean(t)
    blocks.new_run[1:] = blocks.run[1:] != blocks.run[:-1]
    return blocks
