"""Temperature-derived signals: de-dithered temperature, branch state, element temperature, rate.

All built from `sims.recursions`, the same recursions the simulated IMU uses, so a term
fitted here means exactly what the sims effect of the same name does.
"""

from __future__ import annotations

import numpy as np

from sims.recursions import first_order_lag, play_state


def backlash(x: np.ndarray, half_width: float) -> np.ndarray:
    """Play (backlash) operator: the output follows the input only once it is more than
    `half_width` away. With half_width = quantum / 2 it removes the back-and-forth dither
    of a coarse temperature logger, which would otherwise look like heating/cooling reversals.
    """
    x = np.asarray(x, dtype=float)
    out = np.empty_like(x)
    if x.size == 0:
        return out
    w = float(half_width) * (1.0 + 1e-9)
    change = np.flatnonzero(np.diff(x) != 0) + 1  # the output can only move where the input does
    y = float(x[0])
    values = np.empty(change.size)
    for k, i in enumerate(change):
        xi = x[i]
        if xi > y + w:
            y = xi - w
        elif xi < y - w:
            y = xi + w
        values[k] = y
    out[:] = x[0]
    if change.size:
        seg = np.searchsorted(change, np.arange(x.size), side="right") - 1
        has = seg >= 0
        out[has] = values[seg[has]]
    return out


def branch_state(temp_c: np.ndarray, travel_c: float, quantum_c: float | None) -> np.ndarray:
    """Hysteresis branch state in [-1, 1] (+1 after heating), as `sims` computes it."""
    temp = temp_c if quantum_c is None else backlash(temp_c, 0.5 * quantum_c)
    return play_state(temp, travel_c)


def element_temperature(t_s: np.ndarray, temp_c: np.ndarray, tau_s: float) -> np.ndarray:
    """Temperature of a sensing element that lags the IMU's sensor by a first-order lag."""
    return first_order_lag(t_s, temp_c, tau_s)


def temperature_rate(t_s: np.ndarray, temp_c: np.ndarray, window_s: float = 60.0) -> np.ndarray:
    """dT/dt in degC/s, smoothed over about `window_s` (the difference of two lagged copies)."""
    fast = first_order_lag(t_s, temp_c, 0.25 * window_s)
    slow = first_order_lag(t_s, temp_c, 1.25 * window_s)
    # On a ramp of slope r the two lags differ by exactly r * (1.25 - 0.25) * window_s.
    return (fast - slow) / window_s
