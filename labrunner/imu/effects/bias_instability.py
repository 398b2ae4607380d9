"""Bias instability: flicker-like bias wander, B in sensor units (the Allan deviation's floor is 0.664 B).

Part of the noise model, not a cause the diagnosis tests: `labrunner.discrepancy` fits it to the
Allan deviation of the residuals (with the white noise density and the rate random walk,
`bias_random_walk`). Flicker noise has no finite-state generator; the simulator approximates it
the usual way, by a sum of first-order Gauss-Markov processes with correlation times one decade
apart (1 s ... 1e6 s), equal in variance, whose Allan deviation is flat within a few per cent from a
few seconds to about 1e5 s. `allan_variance` gives the exact Allan variance of that sum (the
analysis fits against it, the tests check it by simulating).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import CHANNELS

from ..effect import Effect, Fit, FitContext, Stream, channel_map, channel_vector, per_channel, random_channels, scalars
from ..recursions import ltv_first_order

CORRELATION_S = np.logspace(0.0, 6.0, 7)  # 1 s ... 1e6 s
FLOOR = float(np.sqrt(2.0 * np.log(2.0) / np.pi))  # Allan deviation floor of flicker noise, per unit B (0.664)


def markov_allan_variance(tau_s: np.ndarray, corr_s: float) -> np.ndarray:
    """Allan variance of a unit-variance first-order Gauss-Markov process of correlation time corr_s."""
    x = np.asarray(tau_s, dtype=float) / corr_s
    return (2.0 * corr_s / np.asarray(tau_s, dtype=float)) * (
        1.0 - (3.0 - 4.0 * np.exp(-x) + np.exp(-2.0 * x)) / (2.0 * x))


def _unit_variance() -> float:
    """Each process's variance per B^2 that puts the sum's Allan floor at 0.664 B (mean over 10 s ... 1e5 s)."""
    taus = np.logspace(1.0, 5.0, 41)
    total = np.sum([markov_allan_variance(taus, tc) for tc in CORRELATION_S], axis=0)
    return float(FLOOR ** 2 / np.exp(np.mean(np.log(total))))


PROCESS_VARIANCE = _unit_variance()


def allan_variance(tau_s: np.ndarray, dt_s: float | None = None) -> np.ndarray:
    """Allan variance of the simulator's bias instability at B = 1 (sensor units squared): of the
    continuous process, or (dt_s given) of its samples every dt_s, taus multiples of dt_s -- what the
    simulator's rows show (at tau near the shortest correlation time the two differ by a third)."""
    taus = np.asarray(tau_s, dtype=float)
    if dt_s is None:
        return PROCESS_VARIANCE * np.sum([markov_allan_variance(taus, tc) for tc in CORRELATION_S], axis=0)
    out = np.zeros(taus.size)
    for i, tau in enumerate(taus):
        m = max(int(round(tau / dt_s)), 1)
        k = np.arange(1, 2 * m)
        for tc in CORRELATION_S:
            r = np.exp(-k * dt_s / tc)  # autocorrelation of the sampled process at lag k
            var_mean = (m + 2.0 * np.sum((m - k[: m - 1]) * r[: m - 1])) / m ** 2
            cov_means = np.sum(np.minimum(k, 2 * m - k) * r) / m ** 2
            out[i] += var_mean - cov_means
    return PROCESS_VARIANCE * out


def unit_wander(t_s: np.ndarray, t0: float | None, state: np.ndarray | None,
                rng: np.random.Generator, width: int = len(CHANNELS)) -> tuple[np.ndarray, np.ndarray]:
    """(N, width) bias wander at B = 1 and the processes' state (P, width) after the last row."""
    t = np.asarray(t_s, dtype=float)
    n = t.size
    p = CORRELATION_S.size
    sd = np.sqrt(PROCESS_VARIANCE)
    # The start is drawn from the stationary spread only at a stream's start: chunks of one stream
    # then draw exactly what one batch would.
    x = rng.standard_normal((p, width)) * sd if state is None else np.asarray(state, dtype=float)
    z = rng.standard_normal((n, p, width))
    dt = np.maximum(np.diff(t, prepend=t[0] if t0 is None else t0), 0.0)
    out = np.zeros((n, width))
    last = np.array(x, dtype=float)
    if n == 0:
        return out, last
    uniform = n > 2 and np.allclose(dt[1:], dt[1])
    for j, tc in enumerate(CORRELATION_S):
        a = np.exp(-dt / tc)
        drive = z[:, j] * sd * np.sqrt(1.0 - a * a)[:, None]
        first = a[0] * x[j] + drive[0]
        if uniform:  # the common case: one linear filter after the first row
            # Imported here: scipy.signal costs about a second of start-up, and the effect registry loads
            # this module for every dry run (whose IMU model mostly has no bias instability).
            from scipy.signal import lfilter

            rest = lfilter([1.0], [1.0, -a[1]], drive[1:], axis=0, zi=(a[1] * first)[None, :])[0]
            xs = np.vstack([first[None, :], rest])
        else:  # uneven rows: x[k] = a[k] x[k-1] + drive[k] in closed form
            xs = np.column_stack([ltv_first_order(a, drive[:, i], float(x[j, i])) for i in range(width)])
        out += xs
        last[j] = xs[-1]
    return out, last


@dataclass
class BiasInstability(Effect):
    """Flicker-like bias wander (bias instability B, sensor units): a noise-model term."""

    name = "bias_instability"
    order = 910
    what = "flicker-like bias wander (the noise model's bias instability, not a tested cause)"
    driver = "time (the Allan deviation's flat floor between the white noise and the random walk)"
    json_parameters = ("in the `noise` finding: `bias_instability` {channel: B, sensor units; Allan floor 0.664 B}; "
                       "in the extended model `b`: {channel: B}")
    candidate = False

    b: dict[str, float] = field(default_factory=dict)

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        return cls.from_dict({"b": random_channels(rng, CHANNELS, 1e-4, 5e-3, signed=False)})

    def validate(self) -> None:
        self.b = channel_map(self.b)
        for c, v in self.b.items():
            if v < 0:
                raise ValueError(f"bias_instability: b[{c}] must be >= 0, got {v}")

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        n = len(stream.inputs)
        if stream.rng is None:  # deterministic error only
            return np.zeros((n, len(CHANNELS))), stream.carried
        unit, state = unit_wander(stream.inputs.t_s, stream.t0, stream.carried, stream.rng)
        return unit * channel_vector(self.b)[None, :], state

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        if ctx.rng is None:
            raise ValueError("bias_instability: its regressors are the wander of the generator's draws; "
                             "the context needs an rng")
        unit, _ = unit_wander(ctx.rows.t_s, None, None, ctx.rng)
        return {c: unit[:, i: i + 1] for i, c in enumerate(CHANNELS)}

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        return per_channel(self.b)

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        b = scalars(fit)
        return {"b": b}, {"b": b}
