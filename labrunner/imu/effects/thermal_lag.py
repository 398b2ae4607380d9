"""Thermal lag: the sensing element lags the IMU's temperature sensor by a first-order lag.

The one effect that moves the baseline's temperature: the lagged channels' thermal terms
are evaluated at the element temperature, so it has no regressors of its own (the
diagnosis refits the baseline at the lagged temperature; its nonlinear parameter is the
time constant).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import CHANNELS

from ..effect import RAMP_C_PER_MIN, CampaignFacts, Effect, Fit, FitContext, Gap, Nonlinear, Stream, same_for
from ..inputs import ImuInputs
from ..recursions import first_order_lag


@dataclass
class ThermalLag(Effect):
    """The sensing element lags the IMU temperature sensor by a first-order lag."""

    name = "thermal_lag"
    order = 10
    what = "the sensing element lags the IMU temperature sensor (error follows dT/dt)"
    driver = "the rate of temperature change (log the ramps between soaks)"
    json_parameters = "`tau_s` (s); the lagged channels are the finding's `channels`"
    moves_baseline_temperature = True
    lag_parameter = "tau_s"
    separates = {
        "warmup":
            "the only temperature changes in the log are the self-heating after power-on, where a lag of the "
            "element and a power-on transient look alike: log the ramps between soaks (a lag follows dT/dt, a "
            "warm-up only the time since power-on)",
        "hysteresis":
            "only soaked data: a slow element still settling after a heating or a cooling approach looks like a "
            "branch offset: log the ramps, or soak longer before recording (a lag decays, hysteresis does not)",
    }

    tau_s: float = 300.0
    channels: list[str] = field(default_factory=lambda: list(CHANNELS))

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        n = int(rng.integers(1, len(CHANNELS) + 1))
        chans = sorted(rng.choice(CHANNELS, size=n, replace=False).tolist(), key=CHANNELS.index)
        return cls.from_dict({"tau_s": float(np.exp(rng.uniform(np.log(30.0), np.log(2000.0)))), "channels": chans})

    def validate(self) -> None:
        self.channels = [str(c) for c in self.channels]
        for c in self.channels:
            if c not in CHANNELS:
                raise ValueError(f"effect thermal_lag: unknown channel {c!r}")
        self.tau_s = float(self.tau_s)
        if self.tau_s <= 0:
            raise ValueError("effect thermal_lag: tau_s must be > 0")

    # -- the simulator -----------------------------------------------------------------------

    def baseline_temperature(self, inputs: ImuInputs, t0: float | None, temp0: float | None,
                             carried: Any) -> np.ndarray:
        temp = np.asarray(inputs.temp_c, dtype=float)
        if carried is not None and temp0 is not None and t0 is not None:
            return first_order_lag(inputs.t_s, temp, self.tau_s, y0=float(carried), x0=temp0, t0=t0)
        return first_order_lag(inputs.t_s, temp, self.tau_s)

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        # The baseline at the element temperature instead of the sensor's, on the lagged channels.
        lagged = np.array([c in self.channels for c in CHANNELS])
        temp = np.asarray(stream.inputs.temp_c, dtype=float)
        diff = stream.baseline_at(stream.element_c) - stream.baseline_at(temp)
        return np.where(lagged[None, :], diff, 0.0), float(stream.element_c[-1])

    # -- the diagnosis -------------------------------------------------------------------------

    @classmethod
    def nonlinear(cls, ctx: FitContext) -> tuple[Nonlinear, ...]:
        return (Nonlinear("tau_s", tuple(np.round(np.geomspace(ctx.min_lag_s, 4000.0, 11), 2))),)

    @classmethod
    def nonlinear_names(cls) -> tuple[str, ...]:
        return ("tau_s",)

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        # No columns: the baseline's own, at ctx.element_temp(theta["tau_s"]), carry the effect.
        return {c: np.zeros((len(ctx.rows.t_s), 0)) for c in cls.acts_on}

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        return {c: np.zeros(0) for c in self.channels}

    @classmethod
    def envelope(cls, ctx: FitContext) -> dict[str, np.ndarray]:
        temp = np.asarray(ctx.rows.temp_c, dtype=float)
        lags = np.stack([ctx.element_temp(tau) - temp for tau in (60.0, 300.0, 1200.0)], axis=1)
        return same_for(CHANNELS, lags)

    @classmethod
    def coverage_gaps(cls, facts: CampaignFacts) -> list[Gap]:
        if facts.max_temperature_rate_c_per_min < RAMP_C_PER_MIN:
            return [Gap(f"thermal_lag: the logged temperature never changes faster than {RAMP_C_PER_MIN} degC/min "
                        "(no ramps logged)", CHANNELS)]
        return []

    @classmethod
    def resolution_limit(cls, ctx: FitContext) -> str | None:
        return f"thermal lags below {ctx.min_lag_s:.0f} s"

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        channels = sorted(fit.coef, key=CHANNELS.index)
        return {"tau_s": fit.theta["tau_s"]}, {"tau_s": fit.theta["tau_s"], "channels": channels}
