"""Field logs unlike the project's simulator: what a user brings from a bench without a rate table.

Written from the documented campaign CSV format only (docs/design.md, "The campaign CSV"); nothing
here uses `labrunner.sims` or `labrunner.imu`, so a fit that only works on the simulator's physics
fails on these. What they hold, as a real static thermal log does:

* one orientation per power-on, each power-on its own `run` with a fresh turn-on bias;
* three orientations, each with one axis pointing down (no axis is ever both up and down);
* 1 Hz rows, no table rotation, no soaks and no gaps: slow continuous heating and cooling ramps
  between 5 and 24 C (a triangle, < 0.07 C/min);
* the IMU's own temperature sensor, jittering by 0.01-0.03 C (per run) and reading in 0.01 C;
* per axis, a temperature dependence that is a cubic plus a smooth step (tanh) no polynomial of
  low order follows, in the bias; scale factor and misalignment change linearly with temperature;
* white noise plus a slow random-walk drift of the bias.

`field_log` returns the frame and the truth; tests give the analysis only the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

COLUMNS = ("t_s", "run", "orientation", "chamber_c", "imu_temp_c", "table_rate_dps",
           "ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps")
DOWN = {"x_down": np.array([-1.0, 0.0, 0.0]), "y_down": np.array([0.0, -1.0, 0.0]),
        "z_down": np.array([0.0, 0.0, -1.0])}
T_LOW_C, T_HIGH_C, T_MID_C = 5.0, 24.0, 15.0


@dataclass(frozen=True)
class FieldTruth:
    """The error model the log was made with (for checks only; never given to the fit)."""

    bias_cubic: np.ndarray  # (6, 4) coefficients of ((T - 15) / 10)^k, k = 0..3 (g, deg/s)
    step_amplitude: np.ndarray  # (6,) amplitude of the tanh step (g, deg/s)
    step_centre_c: np.ndarray  # (6,)
    step_width_c: float
    scale0: np.ndarray  # (2, 3, 3) S at 15 C per triad
    scale_slope: np.ndarray  # (2, 3, 3) dS/dT per C
    turn_on: dict[int, np.ndarray]  # run -> (6,) turn-on bias

    def bias_at(self, temp_c: np.ndarray) -> np.ndarray:
        """(N, 6) temperature-dependent bias (without turn-on bias and drift)."""
        tau = (np.asarray(temp_c, dtype=float)[:, None] - T_MID_C) / 10.0
        cubic = np.stack([np.polyval(c[::-1], tau[:, 0]) for c in self.bias_cubic], axis=1)
        step = self.step_amplitude * np.tanh((np.asarray(temp_c, dtype=float)[:, None] - self.step_centre_c)
                                             / self.step_width_c)
        return cubic + step

    def scale_at(self, temp_c: np.ndarray) -> np.ndarray:
        """(N, 2, 3, 3) S(T) per triad."""
        d = np.asarray(temp_c, dtype=float)[:, None, None, None] - T_MID_C
        return self.scale0[None] + self.scale_slope[None] * d


def _truth(rng: np.random.Generator, runs: list[int]) -> FieldTruth:
    acc = np.column_stack([rng.normal(0, 4e-3, 3), rng.normal(0, 3e-3, 3), rng.normal(0, 1.5e-3, 3),
                           rng.normal(0, 1e-3, 3)])
    gyr = np.column_stack([rng.normal(0, 0.1, 3), rng.normal(0, 0.06, 3), rng.normal(0, 0.03, 3),
                           rng.normal(0, 0.02, 3)])
    amp = np.concatenate([rng.choice([-1, 1], 3) * rng.uniform(1.5e-3, 2.5e-3, 3),
                          rng.choice([-1, 1], 3) * rng.uniform(0.012, 0.02, 3)])
    scale0 = np.stack([np.diag(rng.normal(0, 8e-4, 3)) + (1 - np.eye(3)) * rng.normal(0, 1e-3, (3, 3))
                       for _ in range(2)])
    slope = np.stack([np.diag(rng.normal(0, 4e-5, 3)) + (1 - np.eye(3)) * rng.normal(0, 5e-6, (3, 3))
                      for _ in range(2)])
    turn_on = {r: np.concatenate([rng.normal(0, 1e-3, 3), rng.normal(0, 0.02, 3)]) for r in runs}
    return FieldTruth(bias_cubic=np.vstack([acc, gyr]), step_amplitude=amp,
                      step_centre_c=rng.uniform(10.0, 19.0, 6), step_width_c=1.5, scale0=scale0,
                      scale_slope=slope, turn_on=turn_on)


def _ramp(n: int, start_high: bool) -> np.ndarray:
    """A triangle 5 -> 24 -> 5 C (or 24 -> 5 -> 24) over n rows: heating and cooling, no soak."""
    x = np.linspace(0.0, 2.0, n)
    tri = np.where(x <= 1.0, x, 2.0 - x)
    if start_high:
        tri = 1.0 - tri
    return T_LOW_C + (T_HIGH_C - T_LOW_C) * tri


def field_log(seed: int = 0, hours_per_run: float = 10.0,
              orientations: tuple[str, ...] = ("x_down", "y_down", "z_down")) -> tuple[pd.DataFrame, FieldTruth]:
    """A static 1 Hz log, one power-on (run) per orientation; returns (frame, truth)."""
    rng = np.random.default_rng(seed)
    runs = list(range(1, len(orientations) + 1))
    truth = _truth(rng, runs)
    noise = np.array([2e-4, 2e-4, 2.5e-4, 5e-3, 5e-3, 6e-3])  # white, per 1 Hz row
    walk = np.array([6e-7, 6e-7, 6e-7, 1.5e-5, 1.5e-5, 1.5e-5])  # random-walk step per row
    n = int(hours_per_run * 3600)
    frames = []
    t0 = 0.0
    for run, orient in zip(runs, orientations):
        temp = _ramp(n, start_high=run % 2 == 0)
        jitter = rng.uniform(0.01, 0.03)
        sensor = np.round(temp + rng.normal(0.0, jitter, n), 2)
        up = DOWN[orient]
        s = truth.scale_at(temp)  # (n, 2, 3, 3)
        acc = up + np.einsum("nij,j->ni", s[:, 0], up)
        gyr = np.zeros((n, 3))  # no rotation: the scale factor multiplies zero
        y = np.hstack([acc, gyr]) + truth.bias_at(temp) + truth.turn_on[run]
        y += np.cumsum(rng.normal(0.0, 1.0, (n, 6)) * walk, axis=0)
        y += rng.normal(0.0, 1.0, (n, 6)) * noise
        frames.append(pd.DataFrame({
            "t_s": t0 + np.arange(n, dtype=float), "run": run, "orientation": orient, "chamber_c": np.nan,
            "imu_temp_c": sensor, "table_rate_dps": 0.0,
            **{c: y[:, j] for j, c in enumerate(COLUMNS[6:])}}))
        t0 += n + 1800.0  # half an hour to remount and power on again
    return pd.concat(frames, ignore_index=True)[list(COLUMNS)], truth


def write_field_log(path: str, seed: int = 0, hours_per_run: float = 10.0) -> FieldTruth:
    """Write the log as a campaign CSV (chamber_c empty: the log has no chamber reading)."""
    frame, truth = field_log(seed, hours_per_run)
    frame.to_csv(path, index=False, float_format="%.9g", na_rep="")
    return truth
