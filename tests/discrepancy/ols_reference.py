"""An independent least-squares reference: the baseline (Eq. 1, cubic thermal terms) fitted by plain
ordinary least squares to the rows, held out by time stretches of a given length dealt to five folds
in turn. The diagnosis's extended model must predict held-out rows no worse than this."""

from __future__ import annotations

import numpy as np
import pandas as pd

from labrunner.discrepancy import Measurements
from labrunner.imu.baseline import baseline_design


def ols_heldout_rms(frame: pd.DataFrame, segment_s: float, folds: int = 5) -> dict[str, float]:
    """channel -> held-out RMS of measured minus the OLS baseline fitted to the other folds."""
    meas = Measurements.from_frame(frame)
    step = np.maximum(np.diff(meas.t_s, prepend=meas.t_s[:1]), 0.0)
    fold = np.floor(np.cumsum(step) / segment_s).astype(np.int64) % folds
    out = {}
    for i, c in enumerate(meas.channels):
        x = baseline_design(meas.temp_c, meas.force_g if i < 3 else meas.rate_dps)
        y = meas.error[:, i]
        r = np.empty_like(y)
        for f in range(folds):
            train = fold != f
            coef = np.linalg.lstsq(x[train], y[train], rcond=None)[0]
            r[~train] = y[~train] - x[~train] @ coef
        out[c] = float(np.sqrt(np.mean(r * r)))
    return out


def assert_no_worse_than_ols(frame: pd.DataFrame, result, tolerance: float = 0.01) -> None:
    """The extended model's held-out RMS on short and on hour-long stretches against OLS's."""
    short = ols_heldout_rms(frame, result.method["holdout_segment_s"])
    long = ols_heldout_rms(frame, result.method["holdout_long_segment_s"])
    for c in short:
        got_short, got_long = result.gain.heldout_rms_after[c], result.gain_long.heldout_rms_after[c]
        assert got_short <= short[c] * (1 + tolerance), (c, "short", got_short, short[c])
        assert got_long <= long[c] * (1 + tolerance), (c, "long", got_long, long[c])
