"""Candidate causes: the IMU effects of `labrunner.imu.effects`, as the diagnosis fits them.

Each registered effect that is a candidate becomes a `Term`: the effect class's
regressors (linear in its per-channel coefficients once its nonlinear parameters -- a time
constant, a temperature travel, a step's centre and width -- are fixed), its grids for
this campaign, its signature check and its summary into JSON parameters and the
simulator effect that reproduces them. Nothing here names an effect: adding a cause is
one file in `labrunner/imu/effects/`.

An effect that moves the baseline's temperature (the thermal lag) has no columns of its
own: the baseline is refitted at its lagged element temperature, as
`ImuModel.deterministic_error` evaluates it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from labrunner.domain import ROOM_C
from labrunner.imu.effect import Effect, Fit, Nonlinear
from labrunner.imu.effects import REGISTRY, candidate_causes

from .blocks import Blocks
from .measurements import Measurements
from .summary import weighted_percentile
from .temperature import element_temperature, temperature_rate

TermFit = Fit  # the name the diagnosis used before the effects owned it

__all__ = ["CAUSE_ORDER", "Nonlinear", "Term", "TermContext", "TermFit", "candidate_terms", "cause_order"]


class TermContext:
    """Row data, blocks and caches of the derived signals terms are built from (a `FitContext`)."""

    def __init__(self, meas: Measurements, blocks: Blocks) -> None:
        self.meas = meas
        self.rows = meas
        self.blocks = blocks
        self.remounts = meas.remounts
        # The branch state follows the whole path, also where it was not logged: a campaign starts
        # at room temperature and every remount opens the chamber.
        self.path_via_c: float | None = ROOM_C
        self.rng: np.random.Generator | None = None
        self._element: dict[float, np.ndarray] = {}
        self.run_ids = np.unique(meas.run)
        self.temp_min = float(np.min(meas.temp_c))
        self.temp_max = float(np.max(meas.temp_c))
        # A temperature logged in steps of q cannot resolve history effects finer than about
        # 2 q of travel, nor lags shorter than the time a ramp takes to cross 2 q: below those,
        # the rounding (even de-quantised) looks just like them.
        q = meas.temperature_quantum_c or 0.0
        rate = np.abs(temperature_rate(meas.t_s, meas.temp_c, meas.run))
        # Rows that summarise raw samples count as their samples (as if the samples were the rows).
        n = meas.summary.samples if meas.summary is not None else None
        moving = rate > 0.1 / 60.0
        ramping = rate[moving]
        ramp_rate = (weighted_percentile(ramping, None if n is None else n[moving], 90)
                     if ramping.size > 10 else 0.0)
        self.min_travel_c = max(0.2, 2.0 * q)
        fast = rate > 0.2 / 60.0
        self.ramps_logged = bool((np.mean(fast) if n is None else n[fast].sum() / n.sum()) > 0.02)
        self.min_lag_s = max(10.0, min(2.0 * q / ramp_rate, 300.0)) if q and ramp_rate else 10.0
        limits = [lim for cls in REGISTRY.values() if cls.candidate and (lim := cls.resolution_limit(self))]
        self.resolution_notes = [] if not q or not limits else [
            f"{' and '.join(limits)}: imu_temp_c is logged in {q:g} degC steps"]

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


class Term:
    """One candidate cause: an effect class at this campaign's grids."""

    def __init__(self, effect: type[Effect], ctx: TermContext) -> None:
        self.effect = effect
        self.name = effect.name
        self.what = effect.what
        self.driver = effect.driver
        self.channels = tuple(effect.acts_on)
        self.nonlinear: tuple[Nonlinear, ...] = tuple(effect.nonlinear(ctx))
        self.moves_baseline_temperature = effect.moves_baseline_temperature
        self.lag_parameter = effect.lag_parameter
        self.uses_element_temperature = effect.uses_element_temperature
        self.per_channel_columns = effect.per_channel_columns
        self.separates = dict(effect.separates)
        # A check of a fitted channel's coefficients (coef, Schur complement) that the cause's own
        # signature is there, beyond fitting well: False rejects the channel.
        self.consistent_fn = effect.consistent if effect.has_signature() else None

    def consistent(self, coef: np.ndarray, schur: np.ndarray) -> bool:
        return True if self.consistent_fn is None else bool(self.consistent_fn(coef, schur))

    @property
    def free_nonlinear(self) -> int:
        """Nonlinear parameters actually searched (each costs one parameter)."""
        return sum(1 for p in self.nonlinear if len(p.grid) > 1)

    def rows(self, ctx: TermContext, theta: dict[str, float], element_tau: float | None) -> dict[str, np.ndarray]:
        """channel -> (N, q) row-level regressors."""
        return self.effect.regressors(ctx, theta, element_tau)

    def predict(self, ctx: TermContext, theta: dict[str, float], element_tau: float | None, channel: str,
                coef: np.ndarray) -> np.ndarray:
        """(N,) this term's contribution to a channel's error for given coefficients."""
        return self.effect.predict(ctx, theta, element_tau, channel, coef)

    def columns(self, ctx: TermContext, theta: dict[str, float], element_tau: float | None) -> dict[str, np.ndarray]:
        """channel -> (M, q) block means of the regressors (shared arrays stay shared)."""
        blocks = self.effect.block_regressors(ctx, theta, element_tau)
        if blocks is not None:
            return blocks
        rows = self.rows(ctx, theta, element_tau)
        means: dict[int, np.ndarray] = {}
        out = {}
        for c, r in rows.items():
            if id(r) not in means:
                means[id(r)] = ctx.blocks.mean(r)
            out[c] = means[id(r)]
        return out

    def summarize(self, fit: Fit, ctx: TermContext) -> tuple[dict[str, Any], dict[str, Any]]:
        """(parameters for the JSON, keyword arguments of the sims effect)."""
        return self.effect.summarize(fit, ctx)

    def notes(self, ctx: TermContext) -> list[str]:
        return self.effect.notes(ctx)

    def grid(self) -> list[dict[str, float]]:
        if not self.nonlinear:
            return [{}]
        mesh = np.meshgrid(*[np.asarray(p.grid) for p in self.nonlinear], indexing="ij")
        return [{p.name: float(m.flat[i]) for p, m in zip(self.nonlinear, mesh)} for i in range(mesh[0].size)]


def candidate_terms(ctx: TermContext) -> dict[str, Term]:
    """Every candidate cause in registry order, with grids suited to this campaign."""
    return {name: Term(cls, ctx) for name, cls in candidate_causes().items()}


def cause_order() -> tuple[str, ...]:
    """The candidate causes' names, in the order the diagnosis tries and reports them."""
    return tuple(candidate_causes())


CAUSE_ORDER: tuple[str, ...] = cause_order()  # as registered at import (the CLI's help text)
