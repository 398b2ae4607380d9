"""The drift strength is estimated under an 'envelope' model that contains every candidate.

If the drift were estimated under the baseline alone, an unexplained effect (a warm-up
transient, a lag during ramps) would be taken for drift; whitening by that inflated
drift then biases the very parameters the search is looking for (a warm-up time
constant comes out 20 % long). So, as Mallows' Cp takes its noise variance from the
full model, the drift is estimated once from a fit that includes a rough version of
every candidate: lag columns linearised around the baseline fit, warm-up and branch
columns at a few time constants and travels, higher temperature powers, force and
squared-input columns (not per-run offsets: see envelope_columns). The search
re-estimates the drift once causes are selected.
"""

from __future__ import annotations

import numpy as np

from labrunner.domain import CHANNELS, T_REF_C

from .crossval import solve
from .model import DesignBuilder, design_derivative
from .temperature import branch_state, element_temperature

_LAG_TAUS = (60.0, 300.0, 1200.0)
_WARMUP_TAUS = (100.0, 400.0, 1600.0)
_TRAVELS = (0.5, 2.0, 8.0)


def envelope_columns(builder: DesignBuilder, error_blocks: np.ndarray) -> dict[str, np.ndarray]:
    """channel -> (M, q) extra columns beyond the baseline."""
    ctx = builder.ctx
    meas = ctx.meas
    blocks = ctx.blocks
    w = np.sqrt(blocks.weight.astype(float))
    shared = [blocks.mean(np.exp(-np.maximum(meas.t_on_s, 0.0)[:, None] / np.array(_WARMUP_TAUS)[None, :]))]
    shared.append(np.column_stack([blocks.mean(branch_state(meas.temp_c, tr, meas.remounts))
                                   for tr in _TRAVELS]))
    scaled = (meas.temp_c - T_REF_C) / 30.0
    shared.append(blocks.mean(np.stack([scaled ** k for k in range(4, 8)], axis=1)))
    # No per-run offsets: they would soak up the drift's slow part, and per-run offsets against
    # a drift that is not there are what the turn-on-bias test must be able to see.
    lags = np.stack([element_temperature(meas.t_s, meas.temp_c, tau) - meas.temp_c for tau in _LAG_TAUS], axis=1)
    u = np.concatenate([meas.force_g, meas.rate_dps], axis=1)
    out: dict[str, np.ndarray] = {}
    for i, c in enumerate(CHANNELS):
        ref = meas.force_g if i < 3 else meas.rate_dps
        base = builder.baseline(c, None)
        coef = solve(((base * w[:, None]).T @ (base * w[:, None])), (base * w[:, None]).T @ (error_blocks[:, i] * w))
        slope = design_derivative(meas.temp_c, ref) @ coef  # fitted d(error)/dT per row
        curve = design_derivative(meas.temp_c, ref, order=2) @ coef
        # A lag to second order: e(T + d) = e(T) + e' d + e'' d^2 / 2 (lags reach ~10 degC on ramps).
        cols = shared + [blocks.mean(slope[:, None] * lags), blocks.mean(0.5 * curve[:, None] * lags ** 2),
                         blocks.mean((u[:, i] ** 2)[:, None])]
        if i >= 3:
            cols.append(blocks.mean(meas.force_g))
        else:
            w_rad = np.deg2rad(meas.rate_dps)
            cols.append(blocks.mean((w_rad[:, i] ** 2 - np.sum(w_rad ** 2, axis=1))[:, None]))
        out[c] = np.column_stack(cols)
    return out
