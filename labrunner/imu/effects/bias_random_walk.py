"""Bias random walk: slow random-walk bias drift, sigma in sensor units per sqrt(s).

Not a cause the diagnosis tests: it is the drift of its noise model, estimated for every
channel, and goes into the extended model as this effect (`represents_drift`). Its
regressors are the unit walk of the same normal draws the simulator makes
(cumsum(z sqrt(dt)) per channel), so forward error == regressors x sigma for a given
generator.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import CHANNELS

from ..effect import Effect, Fit, FitContext, Stream, channel_map, channel_vector, per_channel, random_channels, scalars


def _steps_dt(t_s: np.ndarray, t0: float | None) -> np.ndarray:
    t = np.asarray(t_s, dtype=float)
    t_prev = np.concatenate(([t[0] if t0 is None else t0], t[:-1]))
    return np.maximum(t - t_prev, 0.0)


@dataclass
class BiasRandomWalk(Effect):
    """Slow random-walk bias drift, sigma in sensor units per sqrt(s) (bias instability)."""

    name = "bias_random_walk"
    order = 900
    what = "a slow random-walk bias drift (the diagnosis's drift model, not a tested cause)"
    driver = "time (long records; estimated from the residual's drift on every channel)"
    json_parameters = ("in `noise`: `drift_per_sqrt_s` per channel; in the extended model `sigma_per_sqrt_s`: "
                       "{channel: sensor units per sqrt(s)}")
    candidate = False
    represents_drift = True

    sigma_per_sqrt_s: dict[str, float] = field(default_factory=dict)

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        return cls.from_dict({"sigma_per_sqrt_s": random_channels(rng, CHANNELS, 4e-7, 4e-5, signed=False)})

    def validate(self) -> None:
        self.sigma_per_sqrt_s = channel_map(self.sigma_per_sqrt_s)

    @classmethod
    def from_drift(cls, drift_per_sqrt_s: dict[str, float]) -> dict[str, Any]:
        """Keyword arguments reproducing a drift the diagnosis estimated per channel."""
        return {"sigma_per_sqrt_s": dict(drift_per_sqrt_s)}

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        n = len(stream.inputs)
        walk0 = np.zeros(len(CHANNELS)) if stream.carried is None else np.asarray(stream.carried, dtype=float)
        if stream.rng is None:  # deterministic error only: the walk stays where it was
            return np.zeros((n, len(CHANNELS))), stream.carried
        sig = channel_vector(self.sigma_per_sqrt_s)
        dt = _steps_dt(stream.inputs.t_s, stream.t0)
        steps = stream.rng.standard_normal((n, len(CHANNELS))) * np.sqrt(dt)[:, None] * sig[None, :]
        walk = walk0[None, :] + np.cumsum(steps, axis=0)
        return walk, walk[-1].copy()

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        if ctx.rng is None:
            raise ValueError("bias_random_walk: its regressors are the walk of the generator's draws; "
                             "the context needs an rng")
        n = len(ctx.rows.t_s)
        unit = np.cumsum(ctx.rng.standard_normal((n, len(CHANNELS))) * np.sqrt(_steps_dt(ctx.rows.t_s, None))[:, None],
                         axis=0)
        return {c: unit[:, i: i + 1] for i, c in enumerate(CHANNELS)}

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        return per_channel(self.sigma_per_sqrt_s)

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        sigma = scalars(fit)
        return {"sigma_per_sqrt_s": sigma}, {"sigma_per_sqrt_s": sigma}
