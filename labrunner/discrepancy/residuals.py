"""The residual (measured minus simulated) next to every quantity a cause would show up in.

One row per block: the block-mean residual of each channel under the baseline fit and
under the extended model, with temperature, its rate of change, heating or cooling,
time since power-on, run, table rate and specific force. The report plots it; it is
also written as CSV so the user can look further.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from labrunner.domain import CHANNELS, ORIENTATIONS

from .blocks import Blocks
from .measurements import Measurements
from .temperature import branch_state, temperature_rate


def residual_table(meas: Measurements, blocks: Blocks, baseline: np.ndarray, extended: np.ndarray) -> pd.DataFrame:
    """baseline/extended: (M, 6) block-mean residuals."""
    h = branch_state(meas.temp_c, 1.0, meas.remounts)
    dtdt = temperature_rate(meas.t_s, meas.temp_c, meas.run) * 60.0
    mean = blocks.mean
    start = blocks.start
    out = pd.DataFrame({
        "t_s": blocks.t_s,
        "run": blocks.run,
        "orientation": pd.Categorical([ORIENTATIONS[i] for i in meas.orientation[start]], categories=ORIENTATIONS),
        "rows": blocks.count,
        "imu_temp_c": mean(meas.temp_c),
        "temp_rate_c_per_min": mean(dtdt),
        "branch": np.sign(np.round(mean(h), 1)),  # +1 heating, -1 cooling, 0 undecided
        "t_on_s": mean(meas.t_on_s),
        "table_rate_dps": mean(meas.table_rate_dps),
        "force_x_g": mean(meas.force_g[:, 0]), "force_y_g": mean(meas.force_g[:, 1]),
        "force_z_g": mean(meas.force_g[:, 2]),
    })
    for i, c in enumerate(CHANNELS):
        out[f"residual_{c}"] = baseline[:, i]
        out[f"after_{c}"] = extended[:, i]
    return out
