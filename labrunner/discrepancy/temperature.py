"""Temperature-derived signals: de-dithered temperature, branch state, element temperature, rate.

All built from `labrunner.imu.recursions`, the same recursions the simulated IMU uses, so a term
fitted here means exactly what the sims effect of the same name does.
"""

from __future__ import annotations

import numpy as np

from labrunner.domain import ROOM_C
from labrunner.imu.recursions import branch_state as path_branch_state
from labrunner.imu.recursions import first_order_lag


def dequantize(t_s: np.ndarray, temp_c: np.ndarray, run: np.ndarray, quantum_c: float,
               settle_s: float) -> np.ndarray:
    """Best estimate of the physical temperature behind a coarsely quantised log.

    A logger that rounds to `quantum_c` hides where in its step the temperature is, and
    the error model, steep in temperature (a few mg/degC), turns that into a sawtooth of
    structured residual that lags, drifts and branch offsets would gladly explain. But
    where the reading changes, the temperature is crossing the boundary between the two
    steps. Between two crossings of different boundaries it ramped through the step
    (linear in time); after entering a step it keeps moving into it for about `settle_s`
    (the time a ramp takes to cross one step) and, when it stays, sits on average at the
    step's centre -- holding the boundary instead would bias every soak by half a step
    towards where it came from, which looks exactly like hysteresis. Run by run.
    """
    t_s = np.asarray(t_s, dtype=float)
    temp = np.asarray(temp_c, dtype=float)
    out = temp.copy()
    bounds = np.flatnonzero(np.diff(run) != 0) + 1
    for s, e in zip(np.r_[0, bounds], np.r_[bounds, temp.size]):
        out[s:e] = _dequantize_run(t_s[s:e], temp[s:e], settle_s)
    return out


def _dequantize_run(t: np.ndarray, level: np.ndarray, settle_s: float) -> np.ndarray:
    change = np.flatnonzero(np.diff(level) != 0) + 1
    if change.size == 0:
        return level.copy()
    anchor_t = 0.5 * (t[change - 1] + t[change])
    anchor_v = 0.5 * (level[change - 1] + level[change])
    plateau = np.searchsorted(change, np.arange(t.size), side="right")  # 0 .. len(change)
    has_in = plateau > 0
    has_out = plateau < change.size
    t1 = np.where(has_in, anchor_t[np.maximum(plateau - 1, 0)], -np.inf)
    v1 = np.where(has_in, anchor_v[np.maximum(plateau - 1, 0)], level)
    t2 = np.where(has_out, anchor_t[np.minimum(plateau, change.size - 1)], np.inf)
    v2 = np.where(has_out, anchor_v[np.minimum(plateau, change.size - 1)], level)
    through = has_in & has_out & (v1 != v2)
    with np.errstate(invalid="ignore", over="ignore"):
        linear = v1 + (v2 - v1) * (t - t1) / np.where(through, t2 - t1, 1.0)
        w1 = np.where(has_in, np.exp(-np.maximum(t - t1, 0.0) / settle_s), 0.0)
        w2 = np.where(has_out, np.exp(-np.maximum(t2 - t, 0.0) / settle_s), 0.0)
    # Entered and left by the same boundary (or a soak at either end of the run): from the
    # boundary towards the step's centre and back.
    edge = np.where(w1 >= w2, v1, v2)
    settled = level + (edge - level) * np.maximum(w1, w2)
    return np.where(through, linear, settled)




def branch_state(temp_c: np.ndarray, travel_c: float, remounts: np.ndarray | None = None) -> np.ndarray:
    """Hysteresis branch state in [-1, 1] (+1 after heating), as the simulator computes it.

    The branch depends on the whole temperature path, also the part that was not
    logged. A campaign starts at room temperature, and remounting the IMU in another
    orientation means opening the chamber: at the start and before every row in
    `remounts` (indices) the path is taken through ROOM_C. Without this, the first soak
    of a log that starts in a soak, and every soak after a remount, would be put on the
    branch the previous orientation ended on.
    """
    return path_branch_state(temp_c, travel_c, remounts, ROOM_C)


def element_temperature(t_s: np.ndarray, temp_c: np.ndarray, tau_s: float) -> np.ndarray:
    """Temperature of a sensing element that lags the IMU's sensor by a first-order lag."""
    return first_order_lag(t_s, temp_c, tau_s)


def temperature_rate(t_s: np.ndarray, temp_c: np.ndarray, run: np.ndarray, window_s: float = 60.0) -> np.ndarray:
    """dT/dt in degC/s: the temperature change across a centred window of `window_s`.

    Only over logged stretches: the window is cut at power-ons and at logging gaps (a
    jump from one soak to the next across hours of unlogged ramp is not a rate), and a
    row whose stretch is shorter than a few seconds gets 0.
    """
    t = np.asarray(t_s, dtype=float)
    temp = np.asarray(temp_c, dtype=float)
    out = np.zeros(t.size)
    if t.size < 2:
        return out
    dt = np.diff(t)
    positive = dt[dt > 0]
    gap = max(10.0, 5.0 * float(np.median(positive))) if positive.size else 10.0
    cut = np.r_[True, (np.diff(run) != 0) | (dt > gap) | (dt <= 0)]
    seg = np.cumsum(cut) - 1
    starts = np.flatnonzero(cut)
    ends = np.r_[starts[1:], t.size] - 1
    lo = np.maximum(t - 0.5 * window_s, t[starts][seg])
    hi = np.minimum(t + 0.5 * window_s, t[ends][seg])
    span = hi - lo
    ok = span >= min(5.0, 0.5 * window_s)
    bounds = np.flatnonzero(np.diff(run) != 0) + 1
    for s, e in zip(np.r_[0, bounds], np.r_[bounds, t.size]):
        idx = np.arange(s, e)
        sel = idx[ok[s:e]]
        if sel.size == 0:
            continue
        tt, tv = t[s:e], temp[s:e]
        out[sel] = (np.interp(hi[sel], tt, tv) - np.interp(lo[sel], tt, tv)) / span[sel]
    return out


# A temperature sensor whose reading reverses direction this often between changes is jittering,
# not following the slow thermal path (a clean ramp, quantised or not, reverses only at its ends).
_JITTER_REVERSALS = 0.2
_SMOOTHED_SD_C = 0.004  # the smoothing window brings the sensor's jitter down to about this


def temperature_jitter(t_s: np.ndarray, temp_c: np.ndarray, run: np.ndarray) -> tuple[float, float]:
    """(row-to-row jitter of the temperature sensor in degC, fraction of direction reversals).

    The jitter is the spread of successive differences over sqrt(2), with the slow path's own
    change (a ramp's) taken out by differencing once more; reversals count consecutive nonzero
    changes of opposite sign."""
    temp = np.asarray(temp_c, dtype=float)
    same = np.diff(run) == 0
    d = np.diff(temp)[same]
    moves = d[d != 0]
    reversals = float(np.mean(np.sign(moves[1:]) != np.sign(moves[:-1]))) if moves.size > 10 else 0.0
    if d.size < 10:
        return 0.0, reversals
    dd = np.diff(d)  # second differences: a ramp's slope cancels; white jitter of sd s gives sd s sqrt(6)
    sd = float(np.sqrt(np.mean(np.clip(dd, -1.0, 1.0) ** 2) / 6.0))
    return sd, reversals


def is_jittery(reversals: float) -> bool:
    return reversals > _JITTER_REVERSALS


def smoothing_rows(jitter_c: float) -> int:
    """Rows of a centred moving mean that bring white jitter of this size down to ~0.004 degC."""
    return int(np.clip(np.ceil((jitter_c / _SMOOTHED_SD_C) ** 2), 5, 301)) | 1  # odd: centred


def smooth_temperature(t_s: np.ndarray, temp_c: np.ndarray, run: np.ndarray, rows: int) -> np.ndarray:
    """Centred moving mean over `rows` rows, within stretches without a power-on or a logging gap
    (shrinking at their ends). Centred, it follows a steady ramp without delay, so heating and
    cooling, the branch state and dT/dt see the thermal path instead of the sensor's jitter."""
    t = np.asarray(t_s, dtype=float)
    temp = np.asarray(temp_c, dtype=float)
    out = temp.copy()
    if temp.size < 3:
        return out
    dt = np.diff(t)
    positive = dt[dt > 0]
    gap = 5.0 * float(np.median(positive)) if positive.size else np.inf
    cut = np.r_[True, (np.diff(run) != 0) | (dt > gap) | (dt <= 0)]
    starts = np.flatnonzero(cut)
    ends = np.r_[starts[1:], temp.size]
    half = rows // 2
    for s, e in zip(starts, ends):
        seg = temp[s:e]
        c = np.r_[0.0, np.cumsum(seg)]
        i = np.arange(seg.size)
        lo = np.maximum(i - half, 0)
        hi = np.minimum(i + half + 1, seg.size)
        out[s:e] = (c[hi] - c[lo]) / (hi - lo)
    return out
