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

The level starts diffuse (unknown): it takes over the role of the regression's constant,
whose whitened column is then zero, and no block is a point of high leverage. (Started
known, the level would make the first block -- whose innovation is the whole bias -- the
only evidence for the constant, and cross-validation holding it out falls apart.) The
constant itself is recovered afterwards from the unwhitened residual mean.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .blocks import Blocks

# rho in 1/s: drift variance per second relative to the per-row white-noise variance.
RHO_GRID = np.concatenate([[0.0], np.logspace(-12.0, 0.0, 25)])
_MAX_BLOCK_DECAY = 650.0  # scale factors up to exp(650) ~ 2e282, applied to unit-size columns
_MIN_LOG_A = -60.0  # a step that forgets (a ~ 0): exp(-60) is as good as 0
_DIFFUSE = 1e20  # initial level variance, in units of the per-row white-noise variance


def riccati(dt: np.ndarray, r: np.ndarray, rho: np.ndarray, observed: np.ndarray | None = None,
            reset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Kalman gains and innovation variances of the local-level filter, one column per filter.

    dt (M,) time steps, r (M,) observation variances, rho (L,) drift rates; observed (M, L)
    says which blocks each filter sees (a filter skips the others: no update, its level
    uncertainty keeps growing); reset (M,) marks blocks where the level starts afresh.
    Data-independent, so computed once and reused for every model. Variances are in units
    of the per-row white-noise variance.
    """
    m = dt.size
    rho = np.asarray(rho, dtype=float)
    gain = np.zeros((m, rho.size))
    fvar = np.ones((m, rho.size))
    p = np.full(rho.size, _DIFFUSE)  # the level starts unknown
    q = rho[None, :] * dt[:, None]
    obs = np.ones((m, rho.size), dtype=bool) if observed is None else observed
    for k in range(m):
        pp = p + q[k] if reset is None or not reset[k] else np.full(rho.size, _DIFFUSE)
        f = pp + r[k]
        o = obs[k]
        fvar[k] = f
        gain[k] = np.where(o, pp / f, 0.0)
        p = np.where(o, pp * (r[k] / f), pp)
    return gain, fvar


class FilterBank:
    """Several local-level filters over the same blocks, applied to columns all at once.

    Whitening is the filter's level recursion level[k] = (1 - K[k]) level[k-1] + K[k] x[k],
    solved in closed form (level[k] = P[k] sum_j K[j] x[j] / P[j], P the running product
    of 1 - K) over stretches short enough that 1/P cannot overflow, as labrunner.imu.recursions does
    for one series. The stretches and scale factors depend only on the gains, so they are
    computed once; each whitening is then a few vectorised in-place passes.
    """

    def __init__(self, gain: np.ndarray, fvar: np.ndarray, rows: list[np.ndarray | None],
                 diffuse: np.ndarray | None = None) -> None:
        self.rows = rows  # per filter: the blocks it observes (None: all)
        self.diffuse = diffuse  # blocks whose innovation carries nothing (a level reset), all filters
        m, nf = gain.shape
        with np.errstate(divide="ignore"):
            la = np.maximum(np.log(np.clip(1.0 - gain, 0.0, 1.0)), _MIN_LOG_A)
        decay = -np.cumsum(la, axis=0)  # (M, F), non-decreasing
        self.chunks: list[tuple[int, int]] = []
        scale = np.empty_like(gain)  # 1 / P within each stretch
        start = 0
        while start < m:
            base = decay[start - 1] if start else np.zeros(nf)
            stop = min(int(np.searchsorted(decay[:, f], base[f] + _MAX_BLOCK_DECAY, side="right")) for f in range(nf))
            stop = max(stop, start + 1)
            scale[start:stop] = np.exp(decay[start:stop] - base[None, :])
            self.chunks.append((start, stop))
            start = stop
        self.gain_scaled = gain * scale
        self.inv_scale = 1.0 / scale
        self.inv_sd = 1.0 / np.sqrt(fvar)
        observed = np.zeros((m, nf))
        for f, seen in enumerate(rows):
            observed[slice(None) if seen is None else seen, f] = 1.0
        self.inv_var_observed = observed / fvar  # to measure columns in whitened units

    @property
    def n_filters(self) -> int:
        return self.gain_scaled.shape[1]

    def whiten(self, x: np.ndarray, which: list[int] | None = None) -> list[np.ndarray]:
        """Innovations of x (M, q) scaled to unit variance, one (rows_f, q) array per filter.

        The first observed block's innovation (against a diffuse level) carries no
        information and is 0; a column the level absorbs entirely (a constant) leaves only
        rounding noise, which the solver would scale up into a regressor, so it is set to 0.
        """
        x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            x = x[:, None]
        which = list(range(self.n_filters)) if which is None else list(which)
        # Unit-size columns keep gain * x / P far from overflow.
        size = np.max(np.abs(x), axis=0)
        size[size == 0] = 1.0
        xs = x / size
        level = self.gain_scaled[:, which][:, :, None] * xs[:, None, :]  # (M, F, q), becomes the level
        inv_scale = self.inv_scale[:, which][:, :, None]
        carry = None
        for start, stop in self.chunks:
            part = level[start:stop]
            np.cumsum(part, axis=0, out=part)
            if carry is not None:
                part += carry
            part *= inv_scale[start:stop]
            carry = part[-1].copy()
        out = np.empty_like(level)
        out[0] = 0.0
        np.subtract(xs[1:, None, :], level[:-1], out=out[1:])
        out *= self.inv_sd[:, which][:, :, None]
        if self.diffuse is not None:
            out[self.diffuse] = 0.0
        norms = np.sqrt(self.inv_var_observed[:, which].T @ (xs * xs))  # (F, q) whitened-unit size
        result = []
        for j, f in enumerate(which):
            rows = self.rows[f]
            w = out[:, j] if rows is None else out[rows, j]
            w[0] = 0.0
            dead = np.sqrt(np.einsum("mq,mq->q", w, w)) <= 1e-9 * norms[j]
            w[:, dead] = 0.0
            result.append(w * size)
        return result


def _steps(blocks: Blocks) -> tuple[np.ndarray, np.ndarray]:
    dt = np.zeros(len(blocks))
    dt[1:] = np.abs(np.diff(blocks.t_s))
    return dt, 1.0 / blocks.weight


@dataclass
class DriftFilter:
    """The local-level filter for each rho of a grid, to estimate the drift strength.

    The level restarts (diffuse) at every power-on, so the estimate rests on how the
    residual wanders within runs only: per-run offsets -- turn-on bias, or anything that
    changes only at a remount -- cannot pass for drift, and a drift cannot hide in them.
    """

    rho: np.ndarray  # (L,)
    bank: FilterBank
    innovation_var: np.ndarray  # (M, L)
    informative: np.ndarray  # (M,) blocks whose innovation counts (not the first of a run)

    def whiten(self, index: int, x: np.ndarray) -> np.ndarray:
        return self.bank.whiten(x, [index])[0]

    @property
    def n_informative(self) -> int:
        return int(self.informative.sum())

    def log_det(self, index: int) -> float:
        """Sum of log innovation variances over the informative blocks."""
        return float(np.sum(np.log(self.innovation_var[self.informative, index])))

    def drift_per_sqrt_s(self, index: int, white_var: float) -> float:
        """The random walk's size in sensor units per sqrt(s)."""
        return float(np.sqrt(self.rho[index] * white_var))


def build_drift_filter(blocks: Blocks, rho: np.ndarray = RHO_GRID) -> DriftFilter:
    dt, r = _steps(blocks)
    rho = np.asarray(rho, dtype=float)
    gain, fvar = riccati(dt, r, rho, reset=blocks.new_run)
    return DriftFilter(rho=rho, bank=FilterBank(gain, fvar, [None] * rho.size, diffuse=blocks.new_run),
                       innovation_var=fvar, informative=~blocks.new_run)


@dataclass
class Whitened:
    """Columns whitened by the full filter and by each fold's filter (training rows only)."""

    full: np.ndarray
    folds: list[np.ndarray]


class FoldFilters:
    """For one drift rate: the filter over all blocks and, per fold, the filter that sees only
    the other folds (the held-out blocks missing). Held-out -2 log-likelihood of fold f is
    Q_all - Q_f: the chain rule p(all) = p(training) p(held-out | training) -- the drift
    level of a held-out stretch is predicted from training data on both sides of it, and no
    held-out sample leaks into the training fit through the filter's memory."""

    def __init__(self, blocks: Blocks, rho: float, folds: np.ndarray, n_folds: int) -> None:
        self.n_folds = n_folds
        self.train_rows = [np.flatnonzero(folds != f) for f in range(n_folds)]
        self.bank: FilterBank | None = None
        if rho > 0:
            dt, r = _steps(blocks)
            observed = np.column_stack([np.ones(len(blocks), dtype=bool)] + [folds != f for f in range(n_folds)])
            gain, fvar = riccati(dt, r, np.full(n_folds + 1, rho), observed)
            self.bank = FilterBank(gain, fvar, [None] + self.train_rows)
        else:
            # Without drift the filter is weighted least squares with the constant as a regressor
            # (equivalent to the diffuse level, without the memory of a running mean).
            self.weight = np.sqrt(blocks.weight.astype(float))

    def whiten(self, x: np.ndarray) -> Whitened:
        if self.bank is None:
            x = np.asarray(x, dtype=float)
            full = x * (self.weight if x.ndim == 1 else self.weight[:, None])
            return Whitened(full, [full[rows] for rows in self.train_rows])
        out = self.bank.whiten(x)
        return Whitened(out[0], out[1:])
