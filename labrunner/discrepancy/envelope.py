"""The drift strength is estimated under an 'envelope' model that contains every candidate.

If the drift were estimated under the baseline alone, an unexplained effect (a warm-up
transient, a lag during ramps) would be taken for drift; whitening by that inflated
drift then biases the very parameters the search is looking for (a warm-up time
constant comes out 20 % long). So, as Mallows' Cp takes its noise variance from the
full model, the drift is estimated once from a fit that includes a rough version of
every candidate, each effect's own (`Effect.envelope`): warm-up and branch columns at a
few time constants and travels, higher temperature powers, force and squared-input
columns; a lag, which moves the baseline's temperature, as the element's temperature
offsets times the baseline's fitted derivatives. Not per-run offsets: they would soak up
the drift's slow part, and per-run offsets against a drift that is not there are what the
turn-on-bias test must be able to see. The search re-estimates the drift once causes are
selected.
"""

from __future__ import annotations

import numpy as np

from labrunner.domain import CHANNELS
from labrunner.imu.effects import candidate_causes

from .crossval import solve
from .model import DesignBuilder, derivative_dot


def envelope_columns(builder: DesignBuilder, error_blocks: np.ndarray) -> dict[str, np.ndarray]:
    """channel -> (M, q) extra columns beyond the baseline."""
    ctx = builder.ctx
    meas = ctx.meas
    blocks = ctx.blocks
    w = np.sqrt(blocks.weight.astype(float))
    rough = [(cls, cls.envelope(ctx)) for cls in candidate_causes().values()]
    means: dict[int, np.ndarray] = {}  # shared row arrays are averaged once

    def mean(rows: np.ndarray) -> np.ndarray:
        if id(rows) not in means:
            means[id(rows)] = blocks.mean(rows)
        return means[id(rows)]

    out: dict[str, np.ndarray] = {}
    for i, c in enumerate(CHANNELS):
        ref = meas.force_g if i < 3 else meas.rate_dps
        base = builder.baseline(c, None)
        coef = solve(((base * w[:, None]).T @ (base * w[:, None])), (base * w[:, None]).T @ (error_blocks[:, i] * w))
        slope = derivative_dot(meas.temp_c, ref, coef)  # fitted d(error)/dT per row
        curve = derivative_dot(meas.temp_c, ref, coef, order=2)
        cols = []
        for cls, env in rough:
            if c not in env:
                continue
            if cls.moves_baseline_temperature:
                # A lag to second order: e(T + d) = e(T) + e' d + e'' d^2 / 2 (lags reach ~10 degC on ramps).
                lags = env[c]
                cols += [blocks.mean(slope[:, None] * lags), blocks.mean(0.5 * curve[:, None] * lags ** 2)]
            else:
                cols.append(mean(env[c]))
        out[c] = np.column_stack(cols) if cols else np.zeros((len(blocks), 0))
    return out
