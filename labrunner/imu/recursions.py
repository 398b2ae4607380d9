"""Vectorised first-order recursions y[k] = a[k] * y[k-1] + b[k].

Thermal lag (a first-order filter over irregular sample times) and the hysteresis
branch state are both of this form; a Python loop over millions of samples is too
slow, so the recursion is solved in closed form block by block:
y[k] = P[k] * (y0 + sum_{j<=k} b[j] / P[j]), P[k] = prod_{j<=k} a[j],
with blocks cut before the cumulative decay makes 1/P overflow.
"""

from __future__ import annotations

import numpy as np

# exp(600) ~ 1e260: a block may decay this much before 1/P overflows float64.
_MAX_BLOCK_DECAY = 600.0
_MIN_LOG_A = -700.0


def ltv_first_order(a: np.ndarray, b: np.ndarray, y0: float = 0.0) -> np.ndarray:
    """Solve y[k] = a[k] y[k-1] + b[k] for k = 0..n-1 with y[-1] = y0; 0 <= a <= 1."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    n = a.size
    out = np.empty(n)
    if n == 0:
        return out
    with np.errstate(divide="ignore"):
        la = np.maximum(np.log(np.clip(a, 0.0, 1.0)), _MIN_LOG_A)
    decay = -np.cumsum(la)
    start = 0
    y = float(y0)
    while start < n:
        base = decay[start - 1] if start else 0.0
        # A single step may decay by up to 700: it then sits alone in its block.
        stop = int(np.searchsorted(decay, base + _MAX_BLOCK_DECAY, side="right"))
        stop = max(stop, start + 1)
        logp = -(decay[start:stop] - base)  # log P within the block, <= 0
        p = np.exp(logp)
        acc = y + np.cumsum(b[start:stop] * np.exp(-logp))
        out[start:stop] = p * acc
        y = float(out[stop - 1])
        start = stop
    return out


def lag_coefficients(dt: np.ndarray, tau: float) -> np.ndarray:
    """Per-step decay exp(-dt/tau) of a first-order lag."""
    return np.exp(-np.maximum(dt, 0.0) / tau)


def first_order_lag(
    t: np.ndarray, x: np.ndarray, tau: float, y0: float | None = None, x0: float | None = None,
    t0: float | None = None,
) -> np.ndarray:
    """Output of dy/dt = (x - y)/tau sampled at times t, x linear between samples.

    `y0`, `x0`, `t0` carry the state from a previous call (stream processing); by
    default the filter starts settled at x[0]. The first-order-hold form is exact
    for piecewise-linear input, so a ramp of slope r lags by exactly r*tau.
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    if t.size == 0:
        return np.empty(0)
    if tau <= 0:
        return x.copy()
    if y0 is None or x0 is None or t0 is None:
        t_prev = np.concatenate(([t[0]], t[:-1]))
        x_prev = np.concatenate(([x[0]], x[:-1]))
        y_init = float(x[0]) if y0 is None else float(y0)
    else:
        t_prev = np.concatenate(([t0], t[:-1]))
        x_prev = np.concatenate(([x0], x[:-1]))
        y_init = float(y0)
    dt = t - t_prev
    alpha = lag_coefficients(dt, tau)
    with np.errstate(divide="ignore", invalid="ignore"):
        ramp = np.where(dt > 0, (1.0 - alpha) * tau / np.where(dt > 0, dt, 1.0), 1.0)
    b = x - alpha * x_prev - ramp * (x - x_prev)
    return ltv_first_order(alpha, b, y_init)


def play_state(temp: np.ndarray, travel: float, h0: float = 0.0, temp0: float | None = None) -> np.ndarray:
    """Hysteresis branch state in [-1, 1]: +1 after heating, -1 after cooling.

    Each temperature step dT pulls the state towards sign(dT) by a fraction
    1 - exp(-|dT|/travel); a soak keeps the branch the last excursion left.
    """
    temp = np.asarray(temp, dtype=float)
    if temp.size == 0:
        return np.empty(0)
    prev = np.concatenate(([temp[0] if temp0 is None else temp0], temp[:-1]))
    d = temp - prev
    a = np.exp(-np.abs(d) / travel)
    return ltv_first_order(a, (1.0 - a) * np.sign(d), h0)


def branch_state(temp_c: np.ndarray, travel_c: float, remounts: np.ndarray | None = None,
                 via_c: float | None = None) -> np.ndarray:
    """`play_state` along a temperature path that, with `via_c`, passes through that temperature
    before the first row and before every row in `remounts` (the unlogged part of a campaign's
    path: it starts at room temperature, and a remount opens the chamber). Without `via_c` the
    path starts at the first row, as a fresh simulator stream does."""
    temp = np.asarray(temp_c, dtype=float)
    if via_c is None or temp.size == 0:
        return play_state(temp, travel_c)
    at = np.unique(np.r_[0, np.asarray(remounts if remounts is not None else [], dtype=np.int64)])
    h = play_state(np.insert(temp, at, via_c), travel_c)
    return np.delete(h, at + np.arange(at.size))
