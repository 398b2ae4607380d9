"""Candidate causes: each a term of `sims.imu_model`, as regressors and as fitted parameters.

A term is linear in its per-channel coefficients once its nonlinear parameters (a time
constant, a temperature travel, a step's centre and width) are fixed; `columns` gives
the regressors (block means of row values, computed with the same functions the sims
use), `summarize` turns fitted coefficients into the parameters DESIGN.md names and
into the sims effect that reproduces them.

thermal_lag is the odd one: it has no columns of its own but moves the baseline's
temperature to the lagged element temperature (as `ImuModel.deterministic_error` does).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from labrunner.domain import ACCEL_CHANNELS, CHANNELS, GYRO_CHANNELS, STANDARD_GRAVITY

from .blocks import Blocks
from .measurements import Measurements
from .temperature import branch_state, element_temperature, temperature_rate

_SOAK_TRAVEL_C = 2.0  # the sims' default; any travel well below the soak steps gives the same offsets


@dataclass(frozen=True)
class Nonlinear:
    """A nonlinear parameter searched on a grid, then refined."""

    name: str
    grid: tuple[float, ...]
    log: bool = True  # refine on a log scale (time constants, travels)


@dataclass
class TermFit:
    """A term's fit on the channels it was selected for (whitened-GLS quantities)."""

    theta: dict[str, float]
    coef: dict[str, np.ndarray]  # channel -> this term's coefficients
    cov: dict[str, np.ndarray]  # channel -> their covariance
    schur: dict[str, np.ndarray]  # channel -> Gram of the term's columns with the rest projected out


class TermContext:
    """Row data, blocks and caches of the derived signals terms are built from."""

    def __init__(self, meas: Measurements, blocks: Blocks) -> None:
        self.meas = meas
        self.blocks = blocks
        self._element: dict[float, np.ndarray] = {}
        self.run_ids = np.unique(meas.run)
        self.temp_min = float(np.min(meas.temp_c))
        self.temp_max = float(np.max(meas.temp_c))
        # A temperature logged in steps of q cannot resolve history effects finer than about
        # 2 q of travel, nor lags shorter than the time a ramp takes to cross 2 q: below those,
        # the rounding (even de-quantised) looks just like them.
        q = meas.temperature_quantum_c or 0.0
        rate = np.abs(temperature_rate(meas.t_s, meas.temp_c, meas.run))
        ramping = rate[rate > 0.1 / 60.0]
        ramp_rate = float(np.percentile(ramping, 90)) if ramping.size > 10 else 0.0
        self.min_travel_c = max(0.2, 2.0 * q)
        # Soaked data alone shows the branch offset, not how fast the branch changes: the
        # travel needs temperature reversals during logged ramps.
        self.ramps_logged = bool(np.mean(rate > 0.2 / 60.0) > 0.02)
        self.min_lag_s = max(10.0, min(2.0 * q / ramp_rate, 300.0)) if q and ramp_rate else 10.0
        self.resolution_notes = [] if not q else [(
            f"hysteresis with a travel below {self.min_travel_c:.2g} degC and thermal lags below "
            f"{self.min_lag_s:.0f} s: imu_temp_c is logged in {q:g} degC steps")]
        if not self.ramps_logged:
            self.resolution_notes.append(
                f"hysteresis travel_c: no ramps logged, so it is fixed at {_SOAK_TRAVEL_C:g} degC; the width is the "
                "branch offset between soaks reached by heating and by cooling")

    def element_temp(self, tau_s: float | None) -> np.ndarray:
        """Row temperature that drives the errors (the sensor's, or lagged by tau_s)."""
        if tau_s is None:
            return self.meas.temp_c
        key = float(tau_s)
        if key not in self._element:
            if len(self._element) > 48:
                self._element.clear()
            self._element[key] = element_temperature(self.meas.t_s, self.meas.temp_c, key)
        return self._element[key]


ColumnFn = Callable[[TermContext, dict[str, float], float | None], dict[str, np.ndarray]]


@dataclass
class Term:
    """One candidate cause."""

    name: str
    what: str  # one line: what the term is
    driver: str  # what the data must vary to show it (used to advise on confounding)
    channels: tuple[str, ...]
    nonlinear: tuple[Nonlinear, ...] = ()
    rows_fn: ColumnFn | None = None  # row-level regressors per channel
    summarize_fn: Callable[[TermFit, TermContext], tuple[dict[str, Any], dict[str, Any]]] | None = None
    blocks_fn: ColumnFn | None = None  # block-level regressors, when cheaper than averaging rows
    predict_fn: Callable[..., np.ndarray] | None = None  # row-level contribution, when not rows @ coef
    # A check of a fitted channel's coefficients (coef, Schur complement) that the cause's own
    # signature is there, beyond fitting well: False rejects the channel.
    consistent_fn: Callable[[np.ndarray, np.ndarray], bool] | None = None

    def consistent(self, coef: np.ndarray, schur: np.ndarray) -> bool:
        return True if self.consistent_fn is None else bool(self.consistent_fn(coef, schur))

    @property
    def free_nonlinear(self) -> int:
        """Nonlinear parameters actually searched (each costs one parameter)."""
        return sum(1 for p in self.nonlinear if len(p.grid) > 1)

    @property
    def moves_baseline_temperature(self) -> bool:
        return self.name == "thermal_lag"

    def rows(self, ctx: TermContext, theta: dict[str, float], element_tau: float | None) -> dict[str, np.ndarray]:
        """channel -> (N, q) row-level regressors."""
        if self.rows_fn is None:
            return {c: np.zeros((len(ctx.meas), 0)) for c in self.channels}
        return self.rows_fn(ctx, theta, element_tau)

    def predict(self, ctx: TermContext, theta: dict[str, float], element_tau: float | None, channel: str,
                coef: np.ndarray) -> np.ndarray:
        """(N,) this term's contribution to a channel's error for given coefficients."""
        if self.predict_fn is not None:
            return self.predict_fn(ctx, theta, element_tau, channel, coef)
        return self.rows(ctx, theta, element_tau)[channel] @ coef

    def columns(self, ctx: TermContext, theta: dict[str, float], element_tau: float | None) -> dict[str, np.ndarray]:
        """channel -> (M, q) block means of the regressors (shared arrays stay shared)."""
        if self.blocks_fn is not None:
            return self.blocks_fn(ctx, theta, element_tau)
        rows = self.rows(ctx, theta, element_tau)
        means: dict[int, np.ndarray] = {}
        out = {}
        for c, r in rows.items():
            if id(r) not in means:
                means[id(r)] = ctx.blocks.mean(r)
            out[c] = means[id(r)]
        return out

    def summarize(self, fit: TermFit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
        """(parameters for the JSON, keyword arguments of the sims effect)."""
        assert self.summarize_fn is not None
        return self.summarize_fn(fit, ctx)

    def grid(self) -> list[dict[str, float]]:
        if not self.nonlinear:
            return [{}]
        mesh = np.meshgrid(*[np.asarray(p.grid) for p in self.nonlinear], indexing="ij")
        return [{p.name: float(m.flat[i]) for p, m in zip(self.nonlinear, mesh)} for i in range(mesh[0].size)]


# --- regressors (row level; the engine fits their block means) ------------------------------


def _same_for(channels: tuple[str, ...], col: np.ndarray) -> dict[str, np.ndarray]:
    col = col.reshape(col.shape[0], -1)
    return {c: col for c in channels}


def _warmup_rows(ctx: TermContext, theta: dict[str, float], _: float | None) -> dict[str, np.ndarray]:
    return _same_for(CHANNELS, np.exp(-np.maximum(ctx.meas.t_on_s, 0.0) / theta["tau_s"]))


def _hysteresis_rows(ctx: TermContext, theta: dict[str, float], _: float | None) -> dict[str, np.ndarray]:
    h = branch_state(ctx.meas.temp_c, theta["travel_c"], ctx.meas.remounts)
    return _same_for(CHANNELS, 0.5 * h)  # coefficient = heating minus cooling


def _turn_on_blocks(ctx: TermContext, theta: dict[str, float], _: float | None) -> dict[str, np.ndarray]:
    # Indicators of every run but the first (the bias constant holds the first run's offset);
    # blocks never straddle a power-on, so block means are the indicators themselves.
    cols = (ctx.blocks.run[:, None] == ctx.run_ids[None, 1:]).astype(float)
    return _same_for(CHANNELS, cols)


def _turn_on_predict(ctx: TermContext, theta: dict[str, float], _: float | None, channel: str,
                     coef: np.ndarray) -> np.ndarray:
    offsets = np.concatenate([[0.0], coef])
    return offsets[np.searchsorted(ctx.run_ids, ctx.meas.run)]


def _g_sensitivity_rows(ctx: TermContext, theta: dict[str, float], _: float | None) -> dict[str, np.ndarray]:
    return _same_for(GYRO_CHANNELS, ctx.meas.force_g)


def _scale_nonlinearity_rows(ctx: TermContext, theta: dict[str, float], _: float | None) -> dict[str, np.ndarray]:
    u = np.concatenate([ctx.meas.force_g, ctx.meas.rate_dps], axis=1)
    sq = u * u
    return {c: sq[:, i: i + 1] for i, c in enumerate(CHANNELS)}


def _temperature_nonlinearity_rows(ctx: TermContext, theta: dict[str, float],
                                   element_tau: float | None) -> dict[str, np.ndarray]:
    temp = ctx.element_temp(element_tau)
    return _same_for(CHANNELS, np.tanh((temp - theta["center_c"]) / theta["width_c"]))


def _lever_arm_rows(ctx: TermContext, theta: dict[str, float], _: float | None) -> dict[str, np.ndarray]:
    # Accel channel i senses (w_i (w.r) - |w|^2 r_i) / g0; with the rotation about a body axis
    # only r_i enters channel i: coefficient r_i (metres).
    w = np.deg2rad(ctx.meas.rate_dps)
    cols = (w * w - np.sum(w * w, axis=1)[:, None]) / STANDARD_GRAVITY
    return {c: cols[:, i: i + 1] for i, c in enumerate(ACCEL_CHANNELS)}


# --- parameters --------------------------------------------------------------------------


def _scalar(fit: TermFit) -> dict[str, float]:
    return {c: float(v[0]) for c, v in fit.coef.items()}


def _thermal_lag_summary(fit: TermFit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
    channels = sorted(fit.coef, key=CHANNELS.index)
    return {"tau_s": fit.theta["tau_s"]}, {"tau_s": fit.theta["tau_s"], "channels": channels}


def _warmup_summary(fit: TermFit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
    amp = _scalar(fit)
    return {"tau_s": fit.theta["tau_s"], "amplitude": amp}, {"tau_s": fit.theta["tau_s"], "amplitude": amp}


def _hysteresis_summary(fit: TermFit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
    width = _scalar(fit)
    return ({"width": width, "travel_c": fit.theta["travel_c"]},
            {"width": width, "travel_c": fit.theta["travel_c"]})


# Directions of the per-run offsets the data determines within 10x the best standard error:
# nearly aliased ones (runs that coincide with temperatures, up to a little self-heating)
# would only add estimation noise.
_IDENTIFIED = 1e-2


def turn_on_sigma(offsets: np.ndarray, schur: np.ndarray, cov: np.ndarray) -> float:
    """Spread of per-run offsets from their estimates relative to the first run.

    Offsets d_r ~ N(0, s^2) estimated relative to run 1: b = d[1:] - d[0], cov s^2 (I + 11').
    Directions the rest of the model can also explain (runs that coincide with
    orientations or temperatures) are not estimable: only the part of b in the range of
    the term's Schur complement counts, with its expected size and estimation noise.
    """
    if offsets.size == 0:
        return 0.0
    w, v = np.linalg.eigh(schur)
    keep = w > _IDENTIFIED * max(float(w.max()), 1e-300)
    if not keep.any():
        return 0.0
    proj = v[:, keep] @ v[:, keep].T
    ones = np.ones(offsets.size)
    dof = float(np.trace(proj) + ones @ proj @ ones)
    noise = float(np.trace(proj @ cov))
    return float(np.sqrt(max(float(offsets @ proj @ offsets) - noise, 0.0) / dof))


def offsets_roughness(coef: np.ndarray, schur: np.ndarray) -> float:
    """Von Neumann ratio of the fitted per-run offsets in run order: mean squared step from one
    run to the next over their variance. Independent offsets (turn-on bias) give about 2; a
    slow drift sampled run by run gives steps much smaller than its spread (near 0). Only the
    identifiable part of the offsets counts (see turn_on_sigma)."""
    w, v = np.linalg.eigh(schur)
    keep = w > _IDENTIFIED * max(float(w.max()), 1e-300)
    b = (v[:, keep] @ v[:, keep].T) @ coef if keep.any() else coef * 0.0
    d = np.concatenate([[0.0], b])
    d = d - d.mean()
    denom = float(np.sum(d * d))
    return float(np.sum(np.diff(d) ** 2) / denom) if denom > 0 else 0.0


def _turn_on_consistent(coef: np.ndarray, schur: np.ndarray) -> bool:
    # Below half the roughness of independent offsets the offsets follow a drift, not power-ons.
    # Too few runs to tell: accept.
    return coef.size < 5 or offsets_roughness(coef, schur) >= 1.0


def _turn_on_summary(fit: TermFit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
    sigma: dict[str, float] = {}
    offsets: dict[str, dict[str, float]] = {str(int(r)): {} for r in ctx.run_ids}
    for c, b in fit.coef.items():
        sigma[c] = turn_on_sigma(b, fit.schur[c], fit.cov[c])
        offsets[str(int(ctx.run_ids[0]))][c] = 0.0
        for r, value in zip(ctx.run_ids[1:], b):
            offsets[str(int(r))][c] = float(value)
    return {"sigma": sigma, "runs": int(ctx.run_ids.size)}, {"sigma": sigma, "offsets": offsets}


def _g_sensitivity_summary(fit: TermFit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
    m = np.zeros((3, 3))
    for c, b in fit.coef.items():
        m[GYRO_CHANNELS.index(c)] = b
    return {"matrix_dps_per_g": m.tolist()}, {"matrix_dps_per_g": m.tolist()}


def _scale_nonlinearity_summary(fit: TermFit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
    k2 = _scalar(fit)
    return {"k2_per_dps": k2}, {"k2_per_dps": k2}


def _temperature_nonlinearity_summary(fit: TermFit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
    amp = _scalar(fit)
    params = {"amplitude": amp, "center_c": fit.theta["center_c"], "width_c": fit.theta["width_c"]}
    return params, dict(params)


def _lever_arm_summary(fit: TermFit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
    r = [float(fit.coef[c][0]) if c in fit.coef else 0.0 for c in ACCEL_CHANNELS]
    return {"r_m": r}, {"r_m": r}


# --- the candidates ----------------------------------------------------------------------


def candidate_terms(ctx: TermContext) -> dict[str, Term]:
    """Every candidate cause, with grids suited to this campaign's temperature range."""
    lo, hi = ctx.temp_min, ctx.temp_max
    span = max(hi - lo, 1.0)
    centres = tuple(np.round(np.linspace(lo + 0.1 * span, hi - 0.1 * span, 9), 3))
    return {
        "thermal_lag": Term(
            "thermal_lag", "the sensing element lags the IMU temperature sensor (error follows dT/dt)",
            "the rate of temperature change (log the ramps between soaks)", CHANNELS,
            (Nonlinear("tau_s", tuple(np.round(np.geomspace(ctx.min_lag_s, 4000.0, 11), 2))),),
            summarize_fn=_thermal_lag_summary),
        "hysteresis": Term(
            "hysteresis", "heating and cooling branches differ at the same temperature",
            "the direction of temperature change (reach temperatures from both sides)", CHANNELS,
            (Nonlinear("travel_c", tuple(np.round(np.geomspace(ctx.min_travel_c, 12.0, 10), 3))
                                   if ctx.ramps_logged else (_SOAK_TRAVEL_C,)),),
            _hysteresis_rows, _hysteresis_summary),
        "warmup": Term(
            "warmup", "a transient after each power-on that temperature does not explain",
            "time since power-on (log from power-on, at several temperatures)", CHANNELS,
            (Nonlinear("tau_s", tuple(np.round(np.geomspace(20.0, 6000.0, 11), 2))),),
            _warmup_rows, _warmup_summary),
        "turn_on_bias": Term(
            "turn_on_bias", "a different constant offset after each power-on",
            "power-ons (runs) that do not coincide with orientation or temperature changes", CHANNELS,
            (), None, _turn_on_summary, _turn_on_blocks, _turn_on_predict, _turn_on_consistent),
        "g_sensitivity": Term(
            "g_sensitivity", "gyro output depends on specific force",
            "orientation (specific force) independently of power-ons", GYRO_CHANNELS,
            (), _g_sensitivity_rows, _g_sensitivity_summary),
        "scale_nonlinearity": Term(
            "scale_nonlinearity", "output error grows with the square of the input",
            "the input magnitude (several table rates; for accelerometers, axes up and down)", CHANNELS,
            (), _scale_nonlinearity_rows, _scale_nonlinearity_summary),
        "temperature_nonlinearity": Term(
            "temperature_nonlinearity", "the temperature dependence is not cubic (a smooth step)",
            "temperature (many levels, or logged ramps)", CHANNELS,
            (Nonlinear("center_c", centres, log=False), Nonlinear("width_c", (2.0, 5.0, 12.0))),
            _temperature_nonlinearity_rows, _temperature_nonlinearity_summary),
        "lever_arm": Term(
            "lever_arm", "the accelerometer sits off the table axis and senses centripetal acceleration",
            "the table rate (rate squared on the horizontal axes)", ACCEL_CHANNELS,
            (), _lever_arm_rows, _lever_arm_summary),
    }


CAUSE_ORDER: tuple[str, ...] = ("thermal_lag", "hysteresis", "warmup", "turn_on_bias", "g_sensitivity",
                                "scale_nonlinearity", "temperature_nonlinearity", "lever_arm")
