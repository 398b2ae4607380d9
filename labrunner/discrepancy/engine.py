"""Fitting a specification to one channel: drift-whitened GLS, blocked CV, held-out RMS.

Everything the selection compares goes through here: a `ChannelSystem` is one channel's
design and error whitened by the full drift filter and by each fold's filter, with their
Gram matrices, so candidates can be tried by adding columns (`try_columns`) without
refitting the rest. Whitened design parts are cached: the channels of a triad, the steps of
the search and the trial values of a candidate's parameters share most of them.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from labrunner.domain import CHANNELS

from .blocks import Blocks
from .crossval import CvResult, cross_validate, extend_gram, full_fit, solve
from .drift import DriftFilter, FoldFilters, Whitened
from .model import BASELINE, DesignBuilder, Spec
from .summary import channel_sample_rms

# Drift-strength grid points tried first when profiling the likelihood (then the best's neighbours).
_COARSE = (0, 1, 4, 7, 10, 13, 16, 19, 22, 25)
# Whitened design parts and candidate columns kept, in bytes: an entry is about 5 M p floats (M blocks,
# p columns), and the blocks follow the hours logged (a campaign of 10x longer records has 2.5x the
# blocks), so a count of entries let memory grow with the campaign (the paper store's search filled
# ~250 MB; at 10x ~600 MB). A part evicted is whitened again when asked for: the same numbers.
_DESIGN_CACHE_BYTES = 64_000_000
_COLUMN_CACHE_BYTES = 32_000_000

_V = TypeVar("_V")


class _ByteLru(Generic[_V]):
    """Values kept by recency of use up to a total of `max_bytes` (the least recent dropped first)."""

    def __init__(self, max_bytes: int, size: Callable[[_V], int]) -> None:
        self.max_bytes = max_bytes
        self._size = size
        self._items: OrderedDict[Hashable, tuple[_V, int]] = OrderedDict()
        self.bytes = 0

    def __len__(self) -> int:
        return len(self._items)

    def get(self, key: Hashable) -> _V | None:
        found = self._items.get(key)
        if found is None:
            return None
        self._items.move_to_end(key)
        return found[0]

    def put(self, key: Hashable, value: _V) -> _V:
        size = self._size(value)
        self._items[key] = (value, size)
        self.bytes += size
        while self.bytes > self.max_bytes and len(self._items) > 1:  # the newest stays (it is in use)
            _, (_, dropped) = self._items.popitem(last=False)
            self.bytes -= dropped
        return value


def _whitened_bytes(w: Whitened) -> int:
    return int(w.full.nbytes + sum(f.nbytes for f in w.folds))


def _part_bytes(entry: tuple[Whitened, np.ndarray, np.ndarray]) -> int:
    return _whitened_bytes(entry[0]) + int(entry[1].nbytes + entry[2].nbytes)


@dataclass
class ChannelFit:
    """One channel's fit of a specification, as its Grams of [X | y] whitened by the full filter and by
    each fold's filter: what the coefficients, the residual and the held-out RMS are read from."""

    channel: str
    rho_index: int
    g_full: np.ndarray  # (p+1, p+1)
    g_fold: np.ndarray  # (K, p+1, p+1)
    slices: dict[str, slice]
    cv: CvResult


@dataclass
class ChannelSystem(ChannelFit):
    """A `ChannelFit` with its whitened design X and error y (X's whitening is shared by channels with
    the same design): what candidate columns are tried against (`Engine.try_columns`). Five floats per
    block and column: a fit kept for later (`Engine.prediction_system`) holds the Grams only."""

    x: Whitened  # (M, p) and per fold (training blocks, p)
    y: Whitened  # (M, 1) and per fold

    def cross(self, z_full: np.ndarray, z_folds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """[X | y]' z for the full and the fold-whitened data."""
        full = np.concatenate([self.x.full.T @ z_full, self.y.full.T @ z_full])
        folds = np.stack([np.concatenate([xf.T @ zf, yf.T @ zf])
                          for xf, yf, zf in zip(self.x.folds, self.y.folds, z_folds)])
        return full, folds


class Engine:
    def __init__(self, builder: DesignBuilder, blocks: Blocks, error_blocks: np.ndarray, drift: DriftFilter,
                 folds: np.ndarray, n_folds: int) -> None:
        self.builder = builder
        self.blocks = blocks
        self.y = error_blocks  # (M, 6) block means of measured minus reference
        self.drift = drift
        self.folds = folds
        self.n_folds = n_folds
        self.m = len(blocks)
        self.penalty = float(np.log(self.m))
        self._filters: dict[int, FoldFilters] = {}
        self._xcache: _ByteLru[tuple[Whitened, np.ndarray, np.ndarray]] = _ByteLru(_DESIGN_CACHE_BYTES, _part_bytes)
        self._ycache: dict[tuple[str, int], Whitened] = {}
        self._zcache: _ByteLru[Whitened] = _ByteLru(_COLUMN_CACHE_BYTES, _whitened_bytes)
        self._row_block = blocks.row_block()
        self._rms_cache: dict[tuple, float] = {}

    def filters(self, rho_index: int) -> FoldFilters:
        if rho_index not in self._filters:
            self._filters[rho_index] = FoldFilters(self.blocks, float(self.drift.rho[rho_index]), self.folds,
                                                   self.n_folds)
        return self._filters[rho_index]

    # -- drift strength -----------------------------------------------------------------

    def loglik(self, spec: Spec, channel: str, index: int, extra: np.ndarray | None = None) -> float:
        """Concentrated log-likelihood of the local-level GLS fit at rho[index] (extra: more columns)."""
        x = self.builder.design(spec, channel).x
        if extra is not None:
            x = np.column_stack([x, extra])
        a = self.drift.whiten(index, np.column_stack([x, self.y[:, CHANNELS.index(channel)]]))
        g = a.T @ a
        p = x.shape[1]
        beta = solve(g[:p, :p], g[:p, p])
        sse = max(float(g[p, p] - 2 * beta @ g[:p, p] + beta @ g[:p, :p] @ beta), 1e-300)
        n = self.drift.n_informative  # the first block of each run carries nothing
        return -0.5 * (n * np.log(sse / n) + self.drift.log_det(index))

    def estimate_rho(self, spec: Spec, channel: str, extra: np.ndarray | None = None) -> int:
        """Index of the most likely drift strength (coarse grid, then neighbours)."""
        n = self.drift.rho.size
        cache: dict[int, float] = {}

        def ll(i: int) -> float:
            if i not in cache:
                cache[i] = self.loglik(spec, channel, i, extra)
            return cache[i]

        best = max((i for i in _COARSE if i < n), key=ll)
        for i in (best - 2, best - 1, best + 1, best + 2):
            if 0 <= i < n:
                ll(i)
        return max(cache, key=cache.__getitem__)

    def drift_evidence(self, spec: Spec, channel: str, index: int) -> float:
        """2 * log-likelihood ratio of drift at rho[index] against no drift."""
        return 2.0 * (self.loglik(spec, channel, index) - self.loglik(spec, channel, 0))

    # -- systems --------------------------------------------------------------------------

    def system(self, spec: Spec, channel: str, rho_index: int) -> ChannelSystem:
        """The channel's whitened design and Grams. Whitening is the expensive part, so each part
        of the design (the baseline, each term) is whitened once per drift rate and reused across
        channels, candidates and steps; only the cross products are formed anew."""
        fit, parts, wy = self._fit(spec, channel, rho_index)
        wx = Whitened(np.concatenate([w.full for w, _, _ in parts], axis=1),
                      [np.concatenate([w.folds[f] for w, _, _ in parts], axis=1) for f in range(self.n_folds)])
        return ChannelSystem(**vars(fit), x=wx, y=wy)

    def _fit(self, spec: Spec, channel: str, rho_index: int
             ) -> tuple[ChannelFit, list[tuple[Whitened, np.ndarray, np.ndarray]], Whitened]:
        """`system` without the whitened design put together: the fit, the whitened parts and y."""
        design = self.builder.design(spec, channel)
        parts = [self._part(key, cols, rho_index) for key, cols in design.parts]
        if (channel, rho_index) not in self._ycache:
            self._ycache[(channel, rho_index)] = self.whiten(rho_index, self.y[:, CHANNELS.index(channel)][:, None])
        wy = self._ycache[(channel, rho_index)]
        pieces = [w for w, _, _ in parts] + [wy]
        sizes = [w.full.shape[1] for w in pieces]
        edges = np.r_[0, np.cumsum(sizes)]
        n = int(edges[-1])
        g_full = np.empty((n, n))
        g_fold = np.empty((self.n_folds, n, n))
        for i, wi in enumerate(pieces):
            si = slice(edges[i], edges[i + 1])
            for j in range(i, len(pieces)):
                sj = slice(edges[j], edges[j + 1])
                if i == j and i < len(parts):
                    g_full[si, si], g_fold[:, si, si] = parts[i][1], parts[i][2]
                    continue
                wj = pieces[j]
                g_full[si, sj] = wi.full.T @ wj.full
                g_fold[:, si, sj] = np.stack([a.T @ b for a, b in zip(wi.folds, wj.folds)])
                g_full[sj, si] = g_full[si, sj].T
                g_fold[:, sj, si] = np.swapaxes(g_fold[:, si, sj], 1, 2)
        return (ChannelFit(channel, rho_index, g_full, g_fold, design.slices, cross_validate(g_full, g_fold, self.m)),
                parts, wy)

    def _part(self, key: tuple, cols: np.ndarray, rho_index: int) -> tuple[Whitened, np.ndarray, np.ndarray]:
        """A design part whitened, with its own Grams (cached)."""
        ck = (key, rho_index)
        entry = self._xcache.get(ck)
        if entry is not None:
            return entry
        w = self.whiten(rho_index, cols)
        return self._xcache.put(ck, (w, w.full.T @ w.full, np.stack([f.T @ f for f in w.folds])))

    def whiten(self, rho_index: int, z: np.ndarray) -> Whitened:
        return self.filters(rho_index).whiten(z)

    def whiten_cached(self, key: tuple, rho_index: int, z: np.ndarray) -> Whitened:
        """Whitened candidate columns, kept for the next step (key identifies z)."""
        ck = (key, rho_index)
        w = self._zcache.get(ck)
        if w is None:
            w = self._zcache.put(ck, self.whiten(rho_index, z))
        return w

    def try_columns(self, system: ChannelSystem, z: np.ndarray | Whitened) -> CvResult:
        """CV of the system with extra block-level columns z (M, q), or z already whitened at its rho."""
        w = z if isinstance(z, Whitened) else self.whiten(system.rho_index, z)
        az_full, az_fold = system.cross(w.full, w.folds)
        g_full = extend_gram(system.g_full, az_full, w.full.T @ w.full)
        zz = np.stack([zf.T @ zf for zf in w.folds])
        return cross_validate(g_full, extend_gram(system.g_fold, az_fold, zz), self.m)

    def block_contributions(self, system: ChannelSystem) -> np.ndarray:
        """(M,) each block's share of the held-out score `system.cv.sse` (before the clip at 0).

        Fold f's score is Q_all(b_f) - Q_f(b_f), sums of squared whitened residuals over all
        blocks and over its training blocks; split by block, the shares of any subset of blocks
        (a resample of time stretches) give that subset's held-out score without refitting."""
        y_full = system.y.full[:, 0]
        out = np.zeros(self.m)
        for f in range(self.n_folds):
            beta = system.cv.betas[f]
            r_full = y_full - system.x.full @ beta
            out += r_full * r_full
            r_fold = system.y.folds[f][:, 0] - system.x.folds[f] @ beta
            out[self.filters(system.rho_index).train_rows[f]] -= r_fold * r_fold
        return out

    # -- fitted quantities -------------------------------------------------------------------

    def coefficients(self, spec: Spec, system: ChannelFit) -> tuple[np.ndarray, float]:
        """Coefficients fitted on all blocks, and the per-row white-noise variance estimate.

        The drift's diffuse start leaves the constant (the bias c0, the baseline's first
        column) to the drift level; it is put back as the mean raw residual.
        """
        beta, sse = full_fit(system.g_full)
        x = self.builder.design(spec, system.channel).x
        n = self.blocks.weight.astype(float)
        resid = self.y[:, CHANNELS.index(system.channel)] - x @ beta
        beta = beta.copy()
        beta[system.slices[BASELINE].start] += float(np.sum(n * resid) / np.sum(n))
        dof = max(self.m - 1 - system.cv.n_params, 1)
        return beta, sse / dof

    def term_fit(self, spec: Spec, system: ChannelFit, term: str) -> TermFitPart:
        """A term's coefficients in the full fit, their covariance and the term's Schur complement."""
        beta, s2 = self.coefficients(spec, system)
        sl = system.slices[term]
        g = system.g_full[:-1, :-1]
        idx = np.arange(g.shape[0])
        rest = np.setdiff1d(idx, idx[sl])
        gzr = g[sl][:, rest]
        schur = g[sl, sl] - gzr @ solve_many(g[np.ix_(rest, rest)], gzr.T)
        schur = 0.5 * (schur + schur.T)
        cov = s2 * np.linalg.pinv(schur, hermitian=True, rcond=1e-10)
        return TermFitPart(beta[sl], cov, schur)

    def residual(self, spec: Spec, system: ChannelFit) -> np.ndarray:
        """(M,) block-mean residual (measured minus fitted model) of the full fit."""
        beta, _ = self.coefficients(spec, system)
        return self.y[:, CHANNELS.index(system.channel)] - self.builder.design(spec, system.channel).x @ beta

    def prediction_system(self, spec: Spec, channel: str) -> ChannelFit:
        """The fit the deterministic terms are fitted in for prediction: weighted least squares
        (no drift whitening). Whitened by a strong drift model, the slow part of what temperature
        explains is left to the drift level, and the fit predicts held-out rows worse than a plain
        least-squares fit; the drift model weighs the evidence, this fit makes the model. (Its Grams
        only: the diagnosis keeps one per channel to the end, and nothing is tried against it.)"""
        return self._fit(spec, channel, 0)[0]

    def cached_heldout_rms(self, spec: Spec, channel: str) -> float:
        """`heldout_rms` of a specification, kept: the selection asks for the same "before" often."""
        key = (spec, channel)
        if key not in self._rms_cache:
            self._rms_cache[key] = self._heldout_rms(spec, channel)
        return self._rms_cache[key]

    def heldout_rms(self, spec: Spec, system: ChannelFit) -> float:
        """Held-out raw RMS of the specification on the system's channel (see `_heldout_rms`)."""
        return self.cached_heldout_rms(spec, system.channel)

    def _heldout_rms(self, spec: Spec, channel: str) -> float:
        """Held-out RMS over the raw rows of measured minus model: each row predicted by the
        weighted least-squares fit of the block means on the other folds.

        A term whose columns the training folds never excite (the offset of a power-on held out
        whole) predicts nothing there: that fold is fitted without it, so an unseen power-on
        gets the other runs' mean offset, as a simulator drawing a new one would on average."""
        c = CHANNELS.index(channel)
        design = self.builder.design(spec, channel)
        x = design.x
        w = np.sqrt(self.blocks.weight.astype(float))
        xw = x * w[:, None]
        yw = self.y[:, c] * w
        full_norm = np.einsum("mp,mp->p", xw, xw)
        betas = np.zeros((self.n_folds, x.shape[1]))
        for k in range(self.n_folds):
            train = self.folds != k
            keep = np.ones(x.shape[1], dtype=bool)
            norm = np.einsum("mp,mp->p", xw[train], xw[train])
            for name, sl in design.slices.items():
                if name != BASELINE and np.any((norm[sl] <= 1e-12 * full_norm[sl]) & (full_norm[sl] > 0)):
                    keep[sl] = False
            a = xw[train][:, keep]
            betas[k, keep] = solve(a.T @ a, a.T @ yw[train])
        pred = self.builder.predict_rows(spec, channel, betas, design.slices)  # (N, K)
        fold = self.folds[self._row_block]
        meas = self.builder.ctx.meas
        r = meas.error[:, c] - pred[np.arange(pred.shape[0]), fold]
        return channel_sample_rms(meas.summary, r, c)  # over the raw samples when rows summarise them


@dataclass
class TermFitPart:
    coef: np.ndarray
    cov: np.ndarray
    schur: np.ndarray


def solve_many(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """gram^-1 rhs for a (p, q) right-hand side."""
    if rhs.size == 0:
        return np.zeros_like(rhs)
    q = rhs.shape[1]
    return solve(np.broadcast_to(gram, (q,) + gram.shape), rhs.T).T
