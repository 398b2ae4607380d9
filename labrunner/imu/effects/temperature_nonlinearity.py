"""Temperature non-linearity: a temperature dependence that is not cubic, a smooth step
amplitude * tanh((T - center) / width) of the element temperature."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import CHANNELS, T_REF_C

from ..effect import (
    CampaignFacts,
    Effect,
    Fit,
    FitContext,
    Gap,
    Nonlinear,
    Stream,
    channel_map,
    channel_vector,
    per_channel,
    random_channels,
    same_for,
    scalars,
)

MIN_TEMPERATURE_LEVELS = 6  # a cubic has four coefficients: two spare levels to see anything else


def _step(temp_c: np.ndarray, center_c: float, width_c: float) -> np.ndarray:
    return np.tanh((np.asarray(temp_c, dtype=float) - center_c) / width_c)


@dataclass
class TemperatureNonlinearity(Effect):
    """Temperature dependence that is not cubic: a smooth step amplitude * tanh((T - centre) / width)."""

    name = "temperature_nonlinearity"
    order = 70
    what = "the temperature dependence is not cubic (a smooth step)"
    driver = "temperature (many levels, or logged ramps)"
    json_parameters = "`amplitude`: {channel}, `center_c`, `width_c` (amplitude x tanh((T - center)/width))"
    uses_element_temperature = True
    separates = {
        "hysteresis":
            "the temperature levels were each visited in one direction only: reach every level from both "
            "sides, or add levels",
        "thermal_lag":
            "log the ramps and add temperature levels: a lag follows dT/dt, a non-cubic temperature law the "
            "temperature itself",
    }

    amplitude: dict[str, float] = field(default_factory=dict)
    center_c: float = 10.0
    width_c: float = 4.0

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        return cls.from_dict({"amplitude": random_channels(rng, CHANNELS, 4e-3, 0.2),
                              "center_c": float(rng.uniform(-10.0, 40.0)), "width_c": float(rng.uniform(2.0, 12.0))})

    def validate(self) -> None:
        self.amplitude = channel_map(self.amplitude)
        self.center_c, self.width_c = float(self.center_c), float(self.width_c)
        if self.width_c <= 0:
            raise ValueError("effect temperature_nonlinearity: width_c must be > 0")

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        step = _step(stream.element_c, self.center_c, self.width_c)
        return step[:, None] * channel_vector(self.amplitude)[None, :], None

    @classmethod
    def nonlinear(cls, ctx: FitContext) -> tuple[Nonlinear, ...]:
        lo, hi = ctx.temp_min, ctx.temp_max
        span = max(hi - lo, 1.0)
        centres = tuple(np.round(np.linspace(lo + 0.1 * span, hi - 0.1 * span, 9), 3))
        return (Nonlinear("center_c", centres, log=False), Nonlinear("width_c", (2.0, 5.0, 12.0)))

    @classmethod
    def nonlinear_names(cls) -> tuple[str, ...]:
        return ("center_c", "width_c")

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        return same_for(CHANNELS, _step(ctx.element_temp(element_tau), theta["center_c"], theta["width_c"]))

    @classmethod
    def envelope(cls, ctx: FitContext) -> dict[str, np.ndarray]:
        # Any smooth departure from the cubic: the next four powers of the temperature.
        scaled = (np.asarray(ctx.rows.temp_c, dtype=float) - T_REF_C) / 30.0
        return same_for(CHANNELS, np.stack([scaled ** k for k in range(4, 8)], axis=1))

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        return per_channel(self.amplitude)

    @classmethod
    def coverage_gaps(cls, facts: CampaignFacts) -> list[Gap]:
        if facts.temperature_levels < MIN_TEMPERATURE_LEVELS:
            return [Gap(f"temperature_nonlinearity: {facts.temperature_levels} temperature levels; a cubic fits "
                        f"up to four, at least {MIN_TEMPERATURE_LEVELS} are needed", CHANNELS)]
        return []

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        amp = scalars(fit)
        params = {"amplitude": amp, "center_c": fit.theta["center_c"], "width_c": fit.theta["width_c"]}
        return params, dict(params)
