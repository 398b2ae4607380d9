"""Single-axis rate table physics: acceleration-limited rate changes and rate accuracy.

A commanded rate is reached at constant acceleration. The rate held differs from
the command by a static error drawn per command plus a once-per-revolution ripple,
together within the table's stated accuracy (+-0.01 %, the paper's table). The
rate profile is piecewise linear, so it is evaluated vectorised at any sample times.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class TableParams:
    max_rate_dps: float = 1000.0  # what the hardware can do; procedures set their own lower limit
    accel_dps2: float = 100.0
    rate_accuracy: float = 1e-4  # relative bound of |held - commanded| / |commanded|
    encoder_resolution_dps: float = 1e-4
    language: str = "labrunner"  # the command language the simulated table speaks (drivers/table_profiles.py)


class TablePlant:
    """Rate as a function of time; commands append piecewise-linear segments."""

    def __init__(self, params: TableParams | None = None, start_t: float = 0.0, seed: int = 0) -> None:
        self.p = params or TableParams()
        self._rng = np.random.default_rng([seed, 0x7AB1E])
        # Segments (t_start, rate_start, rate_end, t_end): linear from start to end, then constant.
        self._seg_t0 = np.array([start_t])
        self._seg_r0 = np.array([0.0])
        self._seg_r1 = np.array([0.0])
        self._seg_t1 = np.array([start_t])
        self.commanded_dps = 0.0
        self._angle0, self._angle_t0 = 0.0, start_t  # the angle at the last command, for `angle_at`
        self.overspeed = 1.0  # fault injection: the drive holds this multiple of the commanded rate

    def _held_rate(self, command: float) -> float:
        # Half of the accuracy budget as a static error, half as ripple.
        err = float(np.clip(self._rng.normal(0.0, 0.2 * self.p.rate_accuracy), -0.5 * self.p.rate_accuracy,
                            0.5 * self.p.rate_accuracy))
        return command * (1.0 + err) * self.overspeed

    def command(self, t: float, rate_dps: float) -> None:
        """Command a new rate at time t (0 stops the table)."""
        r_now = float(self.rate_at(np.array([t]), ripple=False)[0])
        self._angle0, self._angle_t0 = self.angle_at(t), t
        target = self._held_rate(rate_dps) if rate_dps != 0 else 0.0
        t_end = t + abs(target - r_now) / self.p.accel_dps2
        keep = self._seg_t0 < t
        self._seg_t0 = np.append(self._seg_t0[keep][-63:], t)
        self._seg_r0 = np.append(self._seg_r0[keep][-63:], r_now)
        self._seg_r1 = np.append(self._seg_r1[keep][-63:], target)
        self._seg_t1 = np.append(self._seg_t1[keep][-63:], t_end)
        self.commanded_dps = float(rate_dps)

    def rate_at(self, times: np.ndarray, ripple: bool = True) -> np.ndarray:
        """True table rate (deg/s) at times (must not precede the oldest kept segment)."""
        times = np.asarray(times, dtype=float)
        first = float(times.min()) if times.ndim == 1 and times.size else -math.inf
        if first >= self._seg_t0[-1]:
            rate = self._rate_in_last_segment(times, first)
        else:
            i = np.clip(np.searchsorted(self._seg_t0, times, side="right") - 1, 0, None)
            t0, r0, r1, t1 = self._seg_t0[i], self._seg_r0[i], self._seg_r1[i], self._seg_t1[i]
            span = np.maximum(t1 - t0, 1e-12)
            frac = np.clip((times - t0) / span, 0.0, 1.0)
            rate = r0 + (r1 - r0) * frac
        if ripple and (rate.ndim != 1 or rate.size == 0 or rate[0] != 0.0 or rate.any()):
            # Once-per-revolution wobble; the angle is only needed modulo a turn. (A table at rest has
            # none: 0 * (1 + k sin 0) is the 0 itself.) In place, in the expression's order.
            wobble = np.deg2rad(rate)
            wobble *= times
            np.sin(wobble, out=wobble)
            wobble *= 0.5 * self.p.rate_accuracy
            wobble += 1.0
            wobble *= rate
            rate = wobble
        return rate

    def _rate_in_last_segment(self, times: np.ndarray, first: float) -> np.ndarray:
        """The rate at times that all fall in the newest segment (`first` is the earliest; a stream's
        chunk, nearly always): the general formula's arithmetic on that one segment's scalars, so the
        same bits, and a constant once the ramp is over."""
        t0, r0, r1, t1 = (float(v[-1]) for v in (self._seg_t0, self._seg_r0, self._seg_r1, self._seg_t1))
        span = max(t1 - t0, 1e-12)
        if first - t0 >= span:  # (times - t0) / span >= 1 for every time (rounding is monotonic): clipped to 1
            return np.full(times.size, r0 + (r1 - r0) * 1.0)
        frac = (times - t0) / span
        np.clip(frac, 0.0, 1.0, out=frac)
        frac *= r1 - r0
        frac += r0
        return frac

    def angle_at(self, t: float) -> float:
        """The table's angle (degrees, 0..360) at t >= the last command: the integral of the rate
        since then (a ramp, then constant), ripple left out."""
        t0, r0, r1, t1 = self._angle_t0, self._seg_r0[-1], self._seg_r1[-1], self._seg_t1[-1]
        dt = max(t - t0, 0.0)
        ramp_s = max(t1 - t0, 0.0)
        ramp = min(dt, ramp_s)
        area = r0 * ramp + (0.5 * (r1 - r0) / ramp_s * ramp * ramp if ramp_s > 0 else 0.0)
        area += r1 * max(dt - ramp_s, 0.0)
        return float((self._angle0 + area) % 360.0)

    def measured_rate(self, t: float) -> float:
        """What the table's encoder reports (resolution-limited)."""
        r = float(self.rate_at(np.array([t]))[0])
        q = self.p.encoder_resolution_dps
        return round(r / q) * q

    def settled(self, t: float) -> bool:
        return bool(t >= self._seg_t1[-1])
