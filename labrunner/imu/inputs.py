"""What the IMU error model needs per sample."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ImuInputs:
    """What the error model needs per sample (all arrays of length N, time-ordered)."""

    t_s: np.ndarray  # time, s (any origin, increasing)
    run: np.ndarray  # power-on counter
    t_on_s: np.ndarray  # time since this run's power-on, s
    temp_c: np.ndarray  # IMU temperature sensor, deg C
    force_g: np.ndarray  # (N, 3) true specific force in the body frame, g
    rate_dps: np.ndarray  # (N, 3) true angular rate in the body frame, deg/s

    def __len__(self) -> int:
        return int(np.asarray(self.t_s).size)
