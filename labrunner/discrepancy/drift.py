"""Slow bias drift as a nuisance: generalised least squares under a local-level noise model.

Measured campaigns drift: a bias random walk adds a slowly wandering level to every
channel. Fitted by ordinary least squares, anything that is constant over long
stretches (per-run offsets, branch offsets, per-orientation offsets) soaks that drift
up and looks like a cause. So each channel's block means are modelled as

    e_k = x_k' beta + mu_k + w_k,   mu_k = mu_{k-1} + eta_k,
    var(w_k) = s2 / n_k,  var(eta_k) = rho * s2 * dt_k,

white noise of per-row variance s2 plus a random walk of rho * s2 per second, the walk
running on across power-offs. A Kalman filter turns this into independent innovations;
applying the same filter to the regressors gives the whitened (GLS) regression, in
which a candidate has to explain more than a drift of the fitted size could. The
filter's gains depend only on the block times and sizes and on rho, so they are computed
once for a grid of rho and reused for every model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .blocks import Blocks

# rho in 1/s: drift variance per second relative to the per-row white-noise variance.
RHO_GRID = np.concatenate([[0.0], np.logspace(-12.0, 0.0, 25)])
_MAX_BLOCK_DECAY = 600.0  # exp(600) stays far from float overflow
_MIN_LOG_A = -700.0


def ltv_columns(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve y[k] = a[k] y[k-1] + b[k] (y[-1] = 0) for every column of b (M, p) at once.

    The closed form y[k] = P[k] * sum_{j<=k} b[j] / P[j], P the running product of a,
    is evaluated in stretches short enough that 1/P cannot overflow (as sims.recursions).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    out = np.empty_like(b)
    m = a.size
    if m == 0:
        return out
    with np.errstate(divide="ignore"):
        la = np.maximum(np.log(np.clip(a, 0.0, 1.0)), _MIN_LOG_A)
    decay = -np.cumsum(la)
    y = np.zeros(b.shape[1:])
    start = 0
    while start < m:
        base = decay[start - 1] if start else 0.0
        stop = max(int(np.searchsorted(decay, base + _MAX_BLOCK_DECAY, side="right")), start + 1)
        logp = -(decay[start:stop] - base)
        scale = np.exp(-logp) if b.ndim == 1 else np.exp(-logp)[:, None]
        acc = y + np.cumsum(b[start:stop] * scale, axis=0)
        out[start:stop] = acc / scale
        y = out[stop - 1]
        start = stop
    return out


@dataclass
class DriftFilter:
    """Kalman gains and innovation variances of the local-level model for each rho in a grid."""

    rho: np.ndarray  # (L,)
    gain: np.ndarray  # (M, L)
    innovation_var: np.ndarray  # (M, L), in units of the per-row white-noise variance

    def whiten(self, index: int, x: np.ndarray) -> np.ndarray:
        """Innovations of x (M,) or (M, p) scaled to unit variance, for rho[index]."""
        x = np.asarray(x, dtype=float)
        k = self.gain[:, index]
        if not np.any(k):
            v = x
        else:
            kk = k if x.ndim == 1 else k[:, None]
            level = ltv_columns(1.0 - k, kk * x)  # filtered drift level after each block
            v = x.copy()
            v[1:] -= level[:-1]
        s = np.sqrt(self.innovation_var[:, index])
        return v / (s if x.ndim == 1 else s[:, None])

    def log_det(self, index: int) -> float:
        return float(np.sum(np.log(self.innovation_var[:, index])))

    def drift_per_sqrt_s(self, index: int, white_var: float) -> float:
        """The random walk's size in sensor units per sqrt(s)."""
        return float(np.sqrt(self.rho[index] * white_var))


def build_drift_filter(blocks: Blocks, rho: np.ndarray = RHO_GRID) -> DriftFilter:
    """Run the (data-independent) Riccati recursion for every rho of the grid."""
    m = len(blocks)
    dt = np.zeros(m)
    dt[1:] = np.abs(np.diff(blocks.t_s))
    r = 1.0 / blocks.count
    rho = np.asarray(rho, dtype=float)
    gain = np.empty((m, rho.size))
    fvar = np.empty((m, rho.size))
    p = np.zeros(rho.size)  # the level starts known (the regression's constant absorbs it)
    q = rho[None, :] * dt[:, None]
    for k in range(m):
        pp = p + q[k]
        f = pp + r[k]
        fvar[k] = f
        gain[k] = pp / f
        p = pp * (r[k] / f)
    return DriftFilter(rho=rho, gain=gain, innovation_var=fvar)
