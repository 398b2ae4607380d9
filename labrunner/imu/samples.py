"""The diagnosis's view of raw samples: a `FitContext` where every sample is its own block.

With it an effect's regressors can be evaluated on exactly the samples the simulator ran
(tests/imu/test_effects.py, the per-effect agreement), without the analysis package: the
temperature path starts at the first sample, as a fresh simulator stream does.
"""

from __future__ import annotations

import numpy as np

from .inputs import ImuInputs
from .recursions import first_order_lag


class EachSample:
    """Blocks of one sample each: block means are the samples themselves."""

    def __init__(self, run: np.ndarray) -> None:
        self.run = np.asarray(run)

    def mean(self, values: np.ndarray) -> np.ndarray:
        return np.asarray(values, dtype=float)


class SampleContext:
    """A `FitContext` over samples given as `ImuInputs`."""

    def __init__(self, inputs: ImuInputs, rng: np.random.Generator | None = None) -> None:
        self.rows = inputs
        self.blocks = EachSample(inputs.run)
        self.run_ids = np.unique(np.asarray(inputs.run))
        self.remounts = np.zeros(0, dtype=np.int64)
        self.path_via_c: float | None = None
        self.rng = rng
        temp = np.asarray(inputs.temp_c, dtype=float)
        self.temp_min = float(temp.min()) if temp.size else 0.0
        self.temp_max = float(temp.max()) if temp.size else 0.0
        self.min_lag_s = 10.0
        self.min_travel_c = 0.2
        self.ramps_logged = True

    def element_temp(self, tau_s: float | None) -> np.ndarray:
        temp = np.asarray(self.rows.temp_c, dtype=float)
        return temp if tau_s is None else first_order_lag(self.rows.t_s, temp, float(tau_s))
