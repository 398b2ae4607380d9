"""Predictive soak: fit the IMU temperature's approach to its equilibrium and extrapolate it.

With `soak.criterion: predictive` a soak does not wait until the observed spread of the IMU
temperature falls under the tolerance (for a first-order lag that is ~e-1 times longer than
needed). Over the last `predict_window_s` of readings it fits

    single:  T(t) = c + a * exp(-(t - t_now) / tau)
    double:  T(t) = c + a1 * exp(-(t - t_now) / tau1) + a2 * exp(-(t - t_now) / tau2)

(the time constants by a bounded search, the amplitudes by linear least squares: variable
projection, so the fit has no starting guess to get wrong) and predicts how much the IMU
temperature still changes over the horizon (the record that follows). The soak is done when that
change plus `SIGMAS` standard errors of it (from the fit's covariance, so a noisy or jittery sensor
widens the bound instead of ending the soak early) is within the tolerance.

A fit whose time constant sits on a bound of the search (the data show no approach, or one the
window cannot resolve), that has too few readings, or whose covariance is singular is no
prediction: `fit_approach` returns the reason and the caller falls back to the spread criterion.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from labrunner.imu.recursions import first_order_lag

log = logging.getLogger(__name__)

SIGMAS = 3.0  # the predicted drift's upper bound: estimate + 3 standard errors
MIN_READINGS = 8  # fewer readings than this cannot pin down an exponential and its noise
_GRID = 48  # time constants tried (log-spaced) before the bounded refinement
_EDGE = 1.02  # a time constant within 2 % of a bound is on the bound: not a resolved approach

ApproachModel = Literal["single", "double"]


@dataclass(frozen=True)
class ApproachFit:
    """A fitted approach, expressed at the newest reading (t = 0 there)."""

    model: ApproachModel
    equilibrium_c: float  # c: where the IMU temperature is heading
    amplitudes_c: tuple[float, ...]  # a (or a1, a2): the excess still to go, per time constant
    taus_s: tuple[float, ...]
    rms_c: float  # residual RMS of the fit
    n: int  # readings fitted
    span_s: float  # newest minus oldest reading time
    drift_c: float  # predicted |change| over the horizon
    drift_sigma_c: float  # its standard error
    horizon_s: float
    chamber_drift_c: float = 0.0  # what the air still off its setpoint adds over the horizon (the caller's)
    # With a sensing element lagging the temperature sensor by lag_s: its mean offset from the reading
    # over the horizon (what a record tagged with the sensor's temperature is off by), and its error.
    lag_s: float = 0.0
    lag_c: float = 0.0
    lag_sigma_c: float = 0.0

    @property
    def drift_bound_c(self) -> float:
        return self.drift_c + SIGMAS * self.drift_sigma_c + self.chamber_drift_c

    @property
    def lag_bound_c(self) -> float:
        return self.lag_c + SIGMAS * self.lag_sigma_c

    @property
    def tau_s(self) -> float:
        """The dominant (slowest) time constant."""
        return max(self.taus_s)

    def describe(self) -> str:
        taus = " and ".join(f"{t:.0f}" for t in self.taus_s)
        chamber = f", chamber +{self.chamber_drift_c:.3f} C" if self.chamber_drift_c else ""
        lag = (f", element {self.lag_c:.3f} C off the reading (bound {self.lag_bound_c:.3f} C, lag "
               f"{self.lag_s:.0f} s)" if self.lag_s else "")
        return (f"predicted drift {self.drift_c:.3f} C (bound {self.drift_bound_c:.3f} C: +{SIGMAS:g} sigma{chamber}) "
                f"over the "
                f"next {self.horizon_s:.0f} s{lag}, tau {taus} s, fit over {self.span_s:.0f} s ({self.n} readings, "
                f"rms {self.rms_c:.3f} C)")

    def detail(self) -> dict[str, float | int | str]:
        return {"criterion": "predictive", "predicted_drift_c": round(self.drift_c, 5),
                "predicted_drift_bound_c": round(self.drift_bound_c, 5), "tau_s": round(self.tau_s, 1),
                "fit_window_s": round(self.span_s, 1), "fit_readings": self.n, "fit_rms_c": round(self.rms_c, 5),
                "horizon_s": self.horizon_s, "model": self.model, "equilibrium_c": round(self.equilibrium_c, 4),
                "chamber_drift_c": round(self.chamber_drift_c, 5), "lag_s": self.lag_s,
                "predicted_lag_c": round(self.lag_c, 5), "predicted_lag_bound_c": round(self.lag_bound_c, 5)}


@dataclass(frozen=True)
class NoFit:
    """Why the readings gave no usable prediction."""

    reason: str


def _design(t: np.ndarray, taus: Sequence[float]) -> np.ndarray:
    return np.column_stack([np.ones_like(t)] + [np.exp(-t / tau) for tau in taus])


def _project(t: np.ndarray, y: np.ndarray, taus: Sequence[float]) -> tuple[float, np.ndarray]:
    """SSE and linear coefficients (c, a...) for fixed time constants."""
    x = _design(t, taus)
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    r = y - x @ coef
    return float(r @ r), coef


def _model(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """p = (c, a1, tau1, a2, tau2, ...)."""
    out = np.full_like(t, p[0])
    for a, tau in zip(p[1::2], p[2::2], strict=True):
        out = out + a * np.exp(-t / tau)
    return out


def _gains(taus: Sequence[float], horizon_s: float) -> list[np.ndarray]:
    """Weights on the amplitudes (c first) of the two drift forms (`_drift`)."""
    return [np.array([0.0] + [1.0 - math.exp(-horizon_s / tau) for tau in taus]),
            np.array([0.0] + [min(horizon_s / tau, 1.0) for tau in taus])]


def _lag_factor(tau_s: float, lag_s: float) -> float:
    """The element's steady offset behind a reading on exp(-t / tau), in lag x rate: tau / (tau - lag) for
    an approach at least twice the lag's time constant; 2 below (there the readings' history, not the
    component, sets it, and the component may be one of a near-degenerate pair)."""
    return tau_s / (tau_s - lag_s) if tau_s >= 2.0 * lag_s else 2.0


def _lag_gain(tau_s: float, t0_s: float, horizon_s: float, lag_s: float) -> float:
    """The mean over the horizon of (reading - element) for a unit component exp(-t / tau) of the reading.

    The element follows the reading through a first-order lag of `lag_s`, started at the window's first
    reading (`t0_s` < 0) at its steady offset (`_lag_factor` x lag x rate): a start at lag x rate left the
    remount soaks' element 8 % further off than predicted; extrapolating the fit back before its readings
    instead is unsafe for a near-degenerate pair of time constants. Exact for the exponential between grid
    points (the filter's first-order hold): no 1 / (tau - lag) singularity where the time constants meet."""
    step = max(min(horizon_s / 30.0, lag_s / 10.0, tau_s / 10.0, 5.0), 1e-3)
    n_past = max(int(math.ceil(-t0_s / step)), 1) + 1
    grid = np.concatenate([np.linspace(t0_s, 0.0, n_past), np.linspace(0.0, horizon_s, 31)[1:]])
    x = np.exp(-grid / tau_s)
    start = float(x[0] * (1.0 + _lag_factor(tau_s, lag_s) * lag_s / tau_s))
    element = first_order_lag(grid, x, lag_s, y0=start, x0=float(x[0]), t0=float(grid[0]))
    future = grid >= 0.0
    return float(np.mean((x - element)[future]))


def _lag_gains(t0_s: float, horizon_s: float, lag_s: float) -> Callable[[Sequence[float]], list[np.ndarray]]:
    """Weights on the amplitudes (c first: a constant has no offset) of the element's mean offset, per set
    of time constants; one filter run per time constant (the profile's grid repeats them)."""
    cache: dict[float, float] = {}

    def gains(taus: Sequence[float]) -> list[np.ndarray]:
        out = [0.0]
        for tau in taus:
            if tau not in cache:
                cache[tau] = _lag_gain(tau, t0_s, horizon_s, lag_s)
            out.append(cache[tau])
        return [np.array(out)]
    return gains


def _drift(p: np.ndarray, horizon_s: float) -> float:
    """The change still to come over the horizon: |T(horizon) - T(0)| of the model, but at least the
    current rate times the horizon (each component's, up to its amplitude). An approach that slows down
    changes by no more than that, whatever its shape; the exponential's own extrapolation is short of it
    when the fitted time constant is too fast (the air's own settling early in the window bends the
    readings: on the simulated lab the fitted tau is ~15 % short of the case's)."""
    amps, taus = p[1::2], p[2::2]
    return max(abs(float(g[1:] @ amps)) for g in _gains([float(v) for v in taus], horizon_s))


def _search_single(t: np.ndarray, y: np.ndarray, lo: float, hi: float) -> float:
    grid = np.geomspace(lo, hi, _GRID)
    sse = [_project(t, y, (tau,))[0] for tau in grid]
    k = int(np.argmin(sse))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, _GRID - 1)]
    if a == b:
        return float(a)
    res = minimize_scalar(lambda lt: _project(t, y, (math.exp(lt),))[0], bounds=(math.log(a), math.log(b)),
                          method="bounded", options={"xatol": 1e-4})
    return float(math.exp(res.x))


def _search_double(t: np.ndarray, y: np.ndarray, lo: float, hi: float) -> tuple[float, float]:
    grid = np.geomspace(lo, hi, _GRID // 2)
    best = (math.inf, lo, hi)
    for i, t1 in enumerate(grid):
        for t2 in grid[i + 1:]:
            if t2 < 1.5 * t1:  # two nearly equal time constants are one, badly conditioned
                continue
            sse = _project(t, y, (t1, t2))[0]
            if sse < best[0]:
                best = (sse, float(t1), float(t2))
    # Refine from the best grid pair, in log time constants, kept inside the search's bounds.
    res = minimize(lambda lt: _project(t, y, tuple(np.exp(np.clip(lt, math.log(lo), math.log(hi)))))[0],
                   np.log([best[1], best[2]]), method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-14})
    t1, t2 = sorted(float(v) for v in np.exp(np.clip(res.x, math.log(lo), math.log(hi))))
    return (t1, t2) if res.fun <= best[0] else (best[1], best[2])


def fit_approach(t_s: Sequence[float], temp_c: Sequence[float], horizon_s: float, tau_max_s: float,
                 model: ApproachModel = "single", lag_s: float = 0.0) -> ApproachFit | NoFit:
    """Fit the approach over the readings given (time order) and predict the drift over `horizon_s`;
    with `lag_s` > 0 also the mean offset over it of a sensing element lagging the readings by `lag_s`.

    With `double`, a window in which the faster component has died out (the two-constant fit is
    degenerate) is fitted with one time constant: that is the approach left to predict."""
    fit = _fit(t_s, temp_c, horizon_s, tau_max_s, model, lag_s)
    if isinstance(fit, NoFit) and model == "double":
        single = _fit(t_s, temp_c, horizon_s, tau_max_s, "single", lag_s)
        if isinstance(single, ApproachFit):
            return single
    return fit


def _fit(t_s: Sequence[float], temp_c: Sequence[float], horizon_s: float, tau_max_s: float,
         model: ApproachModel, lag_s: float = 0.0) -> ApproachFit | NoFit:
    t = np.asarray(t_s, float)
    y = np.asarray(temp_c, float)
    keep = np.isfinite(t) & np.isfinite(y)
    t, y = t[keep], y[keep]
    n_par = 3 if model == "single" else 5
    if len(t) < max(MIN_READINGS, n_par + 3):
        return NoFit(f"{len(t)} IMU readings in the fit window, {max(MIN_READINGS, n_par + 3)} needed")
    t = t - t[-1]  # t = 0 at the newest reading: the amplitudes are what is still to go from now
    span = float(-t[0])
    steps = np.diff(t)
    lo = max(2.0 * float(np.median(steps)), 1e-3)  # faster than two polls: the window cannot see it
    hi = tau_max_s
    if lo >= hi:
        return NoFit(f"soak.predict_tau_max_s ({tau_max_s:g} s) is shorter than two readings ({lo:g} s)")
    taus: tuple[float, ...]
    if model == "single":
        taus = (_search_single(t, y, lo, hi),)
    else:
        taus = _search_double(t, y, lo, hi)
    if min(taus) <= lo * _EDGE or max(taus) >= hi / _EDGE:
        words = " and ".join(f"{v:.0f}" for v in taus)
        return NoFit(f"time constant {words} s on the bound of the search ({lo:.0f} ... {hi:.0f} s): the readings "
                     "show no resolvable approach")
    sse, coef = _project(t, y, taus)
    p = np.empty(1 + 2 * len(taus))
    p[0] = coef[0]
    p[1::2] = coef[1:]
    p[2::2] = taus
    dof = len(t) - len(p)
    s2 = sse / dof
    # Jacobian of the model in all parameters (numerical in the time constants: relative steps).
    jac = np.empty((len(t), len(p)))
    jac[:, 0] = 1.0
    for k, tau in enumerate(taus):
        e = np.exp(-t / tau)
        jac[:, 1 + 2 * k] = e
        jac[:, 2 + 2 * k] = p[1 + 2 * k] * e * t / tau ** 2
    # Columns scaled to unit norm: the conditioning judged is the readings', not the units'.
    norm = np.linalg.norm(jac, axis=0)
    if not np.all(norm > 0):
        return NoFit("the fit's covariance is singular: the readings do not determine the approach")
    jtj = (jac / norm).T @ (jac / norm)
    if np.linalg.cond(jtj) > 1e12:
        return NoFit("the fit's covariance is singular: the readings do not determine the approach")
    cov = s2 * np.linalg.inv(jtj) / np.outer(norm, norm)
    drift = float(_drift(p, horizon_s))
    grad = np.empty(len(p))
    for k in range(len(p)):
        h = 1e-6 * max(abs(p[k]), 1e-3)
        q = p.copy()
        q[k] += h
        grad[k] = (_drift(q, horizon_s) - drift) / h
    sigma = float(math.sqrt(max(float(grad @ cov @ grad), 0.0)))
    if not (math.isfinite(drift) and math.isfinite(sigma)):
        return NoFit("the fit did not converge (non-finite prediction)")
    # The linearised sigma above trusts the fitted time constants; early in a soak (a short window
    # against tau) they are poorly pinned, and the drift is far from linear in them. The bound is also
    # the largest drift + SIGMAS linear sigmas over every set of time constants the readings do not
    # reject (profile likelihood: SSE within a factor exp(SIGMAS^2 / n) of the best), so a slower
    # approach the window cannot exclude keeps the soak going.
    profile = _profile_bound(t, y, taus, sse, lo, hi, lambda ts: _gains(ts, horizon_s))
    sigma = max(sigma, (profile - drift) / SIGMAS)
    lag = lag_sigma = 0.0
    if lag_s > 0:
        # The element's offset is linear in the amplitudes for given time constants: its bound is the
        # same profile over the time constants the readings do not reject.
        lag_gains = _lag_gains(float(t[0]), horizon_s, lag_s)
        lag = abs(float(lag_gains(taus)[0] @ coef))
        lag_sigma = max(_profile_bound(t, y, taus, sse, lo, hi, lag_gains) - lag, 0.0) / SIGMAS
    return ApproachFit(model=model, equilibrium_c=float(p[0]), amplitudes_c=tuple(float(a) for a in p[1::2]),
                       taus_s=tuple(float(v) for v in taus), rms_c=math.sqrt(sse / len(t)), n=len(t), span_s=span,
                       drift_c=drift, drift_sigma_c=sigma, horizon_s=horizon_s, lag_s=lag_s, lag_c=lag,
                       lag_sigma_c=lag_sigma)


def _profile_bound(t: np.ndarray, y: np.ndarray, best: Sequence[float], sse_min: float, lo: float, hi: float,
                   gains: Callable[[Sequence[float]], list[np.ndarray]]) -> float:
    """max over the time constants not rejected of |g . (c, a...)| + SIGMAS sigma (linear parameters), for
    each weight vector g that `gains` gives for them (the drift's forms, or the element's offset)."""
    n = len(t)
    limit = sse_min * math.exp(SIGMAS ** 2 / n)
    grid = np.geomspace(lo, hi, _GRID if len(best) == 1 else _GRID // 2)
    if len(best) == 1:
        cands: list[tuple[float, ...]] = [(float(v),) for v in grid]
    else:
        cands = [(float(a), float(b)) for i, a in enumerate(grid) for b in grid[i + 1:] if b >= 1.5 * a]
    bound = 0.0
    for taus in [tuple(best), *cands]:
        x = _design(t, taus)
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
        r = y - x @ coef
        sse = float(r @ r)
        if sse > limit and taus != tuple(best):
            continue
        try:
            inv = np.linalg.pinv(x.T @ x)
        except np.linalg.LinAlgError:
            continue
        s2 = sse_min / max(n - 1 - 2 * len(taus), 1)
        for g in gains(taus):
            var = float(g @ inv @ g) * s2
            bound = max(bound, abs(float(g @ coef)) + SIGMAS * math.sqrt(max(var, 0.0)))
    return bound


def model_at(fit: ApproachFit, t_from_newest_s: float) -> float:
    """The fitted temperature `t_from_newest_s` after the newest reading."""
    p = np.empty(1 + 2 * len(fit.taus_s))
    p[0] = fit.equilibrium_c
    p[1::2] = fit.amplitudes_c
    p[2::2] = fit.taus_s
    return float(_model(np.array([t_from_newest_s], float), p)[0])
