"""The gain of a compensation model: does a real change of the sensor's output come out of it?

A compensation must pass signal: an acceleration step of 0.05 g added to the input must come out as
0.05 g divided by the fitted scale, wherever the IMU is. A network whose inputs are the raw outputs
can learn a lookup of the calibration's reference levels instead (any output near 1 g comes out as
1 g), which looks perfect on calibration data and erases real motion. `measure_gain` measures the
Jacobian of the model's output with respect to its input by secant differences over the training
envelope and a margin beyond it, and compares it with the fitted scale, (I + S(T))^-1 of the
polynomial model; `LIMIT` is the departure above which a model is not exported.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .compensation import compensate
from .rbf_model import RbfModel
from .records import Records
from .thermal_poly import PolyModel
from .triads import CHANNELS

LIMIT = 0.005  # 0.5 %: a model departing more from the fitted scale is not exported
STEP = np.array([0.05, 0.05, 0.05, 5.0, 5.0, 5.0])  # the input step (g, deg/s): a real motion, not a dither
TEMP_MARGIN = 0.1  # the envelope is widened by this fraction of the training temperature span (at least 2 C)
MAX_POINTS = 48  # training record means used as base points


@dataclass(frozen=True)
class GainCheck:
    """Largest departure of a model's Jacobian from the fitted scale over the envelope."""

    model: str
    max_departure: float  # max over points and channels of |J (I + S) - I| (relative gain error)
    worst_channel: str
    worst_temp_c: float
    gain_min: float  # range of the diagonal gains relative to the fitted scale, J_kk (1 + S_kk) ...
    gain_max: float
    temp_range_c: tuple[float, float]  # the temperatures checked (training envelope and margin)
    n_points: int

    @property
    def passed(self) -> bool:
        return bool(self.max_departure <= LIMIT)

    def sentence(self) -> str:
        return (f"`{self.model}`: its gain departs from the fitted scale by up to {100 * self.max_departure:.3g} % "
                f"({self.worst_channel} at {self.worst_temp_c:.1f} C; diagonal gains {self.gain_min:.3f} .. "
                f"{self.gain_max:.3f} of the fitted scale) over {self.temp_range_c[0]:.1f} .. "
                f"{self.temp_range_c[1]:.1f} C, more than the {100 * LIMIT:g} % allowed")

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "max_departure": self.max_departure, "worst_channel": self.worst_channel,
                "worst_temp_c": self.worst_temp_c, "gain_range": [self.gain_min, self.gain_max],
                "temp_range_c": list(self.temp_range_c), "n_points": self.n_points, "passed": self.passed,
                "limit": LIMIT}


def envelope_points(records: Records, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Base points (outputs (P, 6), temperatures (P,)): training record means at their own temperature
    and at the ends of the envelope, a margin beyond the training temperatures."""
    rng = np.random.default_rng(seed)
    idx = np.arange(len(records))
    if idx.size > MAX_POINTS:
        idx = np.sort(rng.choice(idx, MAX_POINTS, replace=False))
    y = records.mean[idx]
    t = records.temp_c[idx]
    lo, hi = float(records.temp_c.min()), float(records.temp_c.max())
    m = max(TEMP_MARGIN * (hi - lo), 2.0)
    temps = np.concatenate([t, np.full(idx.size, lo - m), np.full(idx.size, hi + m)])
    return np.vstack([y, y, y]), temps


def measure_gain(name: str, model: PolyModel | RbfModel, fitted: PolyModel, y: np.ndarray,
                 temp_c: np.ndarray) -> GainCheck:
    """Jacobian of `model` at the base points by central secant differences of `STEP`, compared with
    the fitted scale of `fitted` at each point's temperature."""
    p = y.shape[0]
    jac = np.empty((p, 6, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = STEP[k]
        up = compensate(model, y + d, temp_c).values
        down = compensate(model, y - d, temp_c).values
        jac[:, :, k] = (up - down) / (2 * STEP[k])
    scale = np.zeros((p, 6, 6))
    scale[:, :3, :3] = np.eye(3) + fitted.accel.scale_at(temp_c)
    scale[:, 3:, 3:] = np.eye(3) + fitted.gyro.scale_at(temp_c)
    dep = np.einsum("pij,pjk->pik", jac, scale) - np.eye(6)
    worst = np.abs(dep).max(axis=2)  # (p, 6) per output channel
    i, c = np.unravel_index(int(np.argmax(worst)), worst.shape)
    diag = np.einsum("pii->pi", np.einsum("pij,pjk->pik", jac, scale))
    return GainCheck(model=name, max_departure=float(worst[i, c]), worst_channel=CHANNELS[c],
                     worst_temp_c=float(temp_c[i]), gain_min=float(diag.min()), gain_max=float(diag.max()),
                     temp_range_c=(float(temp_c.min()), float(temp_c.max())), n_points=int(p))


def check_models(models: dict[str, PolyModel | RbfModel], fitted: PolyModel, records: Records,
                 seed: int = 0) -> dict[str, GainCheck]:
    """The gain of every model, by its evaluation name."""
    y, t = envelope_points(records, seed)
    return {name: measure_gain(name, m, fitted, y, t) for name, m in models.items()}
