"""Warm-up: a decaying transient after each power-on, amplitude * exp(-t_on / tau)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import CHANNELS

from ..effect import (
    Effect,
    Fit,
    FitContext,
    Nonlinear,
    Stream,
    channel_map,
    channel_vector,
    per_channel,
    random_channels,
    same_for,
    scalars,
)


def _decay(t_on_s: np.ndarray, tau_s: float) -> np.ndarray:
    return np.exp(-np.maximum(np.asarray(t_on_s, dtype=float), 0.0) / tau_s)


@dataclass
class Warmup(Effect):
    """A decaying transient after each power-on: amplitude * exp(-t_on / tau)."""

    name = "warmup"
    order = 30
    what = "a transient after each power-on that temperature does not explain"
    driver = "time since power-on (log from power-on, at several temperatures)"
    json_parameters = "`tau_s` (s), `amplitude`: {channel: offset at power-on}"

    tau_s: float = 600.0
    amplitude: dict[str, float] = field(default_factory=dict)  # offset at power-on

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        return cls.from_dict({"tau_s": float(rng.uniform(60.0, 2000.0)),
                              "amplitude": random_channels(rng, CHANNELS, 6e-3, 0.3)})

    def validate(self) -> None:
        self.amplitude = channel_map(self.amplitude)
        self.tau_s = float(self.tau_s)
        if self.tau_s <= 0:
            raise ValueError("effect warmup: tau_s must be > 0")

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        return _decay(stream.inputs.t_on_s, self.tau_s)[:, None] * channel_vector(self.amplitude)[None, :], None

    @classmethod
    def nonlinear(cls, ctx: FitContext) -> tuple[Nonlinear, ...]:
        return (Nonlinear("tau_s", tuple(np.round(np.geomspace(20.0, 6000.0, 11), 2))),)

    @classmethod
    def nonlinear_names(cls) -> tuple[str, ...]:
        return ("tau_s",)

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        return same_for(CHANNELS, _decay(ctx.rows.t_on_s, theta["tau_s"]))

    @classmethod
    def envelope(cls, ctx: FitContext) -> dict[str, np.ndarray]:
        taus = np.array([100.0, 400.0, 1600.0])
        return same_for(CHANNELS, np.exp(-np.maximum(np.asarray(ctx.rows.t_on_s, dtype=float), 0.0)[:, None]
                                         / taus[None, :]))

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        return per_channel(self.amplitude)

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        amp = scalars(fit)
        return {"tau_s": fit.theta["tau_s"], "amplitude": amp}, {"tau_s": fit.theta["tau_s"], "amplitude": amp}
