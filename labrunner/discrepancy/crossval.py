"""Cross-validation held out by time blocks, computed from per-fold Gram matrices.

Folds are contiguous stretches of time (`segment_s` long) within each run, dealt to the
K folds in turn, so every run and every part of the temperature profile appears in
every fold, but a held-out stretch is never fitted by its own samples or by samples
interleaved with it (random sampling would let slowly varying errors leak across).

A linear model's held-out error needs no refits over the data: with per-fold Grams
G_f = A_f' A_f of A = [X | y], fold f's coefficients solve (G - G_f) and its held-out
sum of squares is y_f'y_f - 2 b' X_f'y_f + b' X_f'X_f b. Adding a candidate's columns Z
only needs the cross products with Z, so a search over a nonlinear parameter costs a
few passes over a column, not a refit of the whole model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .blocks import Blocks

_RIDGE = 1e-10  # relative, on the unit-diagonal Gram: pins aliased directions to zero
_RANK_TOL = 1e-9


def time_folds(blocks: Blocks, n_folds: int = 5, segment_s: float = 600.0) -> np.ndarray:
    """(M,) fold of each block: `segment_s` stretches within runs, dealt out in turn."""
    t = blocks.t_s
    run_start = np.maximum.accumulate(np.where(blocks.new_run, np.arange(len(blocks)), 0))
    seg = np.floor((t - t[run_start]) / segment_s).astype(np.int64)
    run_rank = np.cumsum(blocks.new_run) - 1
    return ((seg + run_rank) % n_folds).astype(np.int64)


@dataclass
class FoldLayout:
    """Rows grouped by fold, so per-fold products are slices."""

    order: np.ndarray  # block order that groups the folds
    bounds: np.ndarray  # (K + 1,) slice bounds in that order
    n_folds: int

    @classmethod
    def from_folds(cls, folds: np.ndarray, n_folds: int) -> FoldLayout:
        order = np.argsort(folds, kind="stable")
        bounds = np.searchsorted(folds[order], np.arange(n_folds + 1))
        return cls(order=order, bounds=bounds, n_folds=n_folds)

    def sort(self, a: np.ndarray) -> np.ndarray:
        return np.asarray(a)[self.order]

    def products(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(K, p, q): a_f' b_f for fold-sorted a (M, p) and b (M, q)."""
        out = np.empty((self.n_folds, a.shape[1], b.shape[1]))
        for f in range(self.n_folds):
            s = slice(self.bounds[f], self.bounds[f + 1])
            out[f] = a[s].T @ b[s]
        return out


def solve(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Least-squares coefficients from normal equations, batched over a leading axis.

    Columns are scaled to a unit diagonal and a tiny ridge pins directions the data
    cannot identify (aliased columns) to zero instead of failing.
    """
    d = np.sqrt(np.clip(np.diagonal(gram, axis1=-2, axis2=-1), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    gs = gram / (d[..., :, None] * d[..., None, :])
    p = gs.shape[-1]
    gs = gs + _RIDGE * np.eye(p)
    hs = rhs / d
    try:
        bs = np.linalg.solve(gs, hs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        bs = np.einsum("...ij,...j->...i", np.linalg.pinv(gs, hermitian=True), hs)
    return bs / d


def rank(gram: np.ndarray) -> int:
    """Numerical rank of a Gram matrix after scaling to a unit diagonal."""
    d = np.sqrt(np.clip(np.diag(gram), 0.0, None))
    keep = d > 0
    if not keep.any():
        return 0
    g = gram[np.ix_(keep, keep)] / np.outer(d[keep], d[keep])
    w = np.linalg.eigvalsh(g)
    return int(np.sum(w > _RANK_TOL * max(w.max(), 1.0)))


@dataclass
class CvResult:
    sse: float  # held-out sum of squares (whitened units)
    n: int  # held-out rows (all rows, each once)
    n_params: int  # identifiable coefficients
    betas: np.ndarray  # (K, p) coefficients of each fold's training fit

    def score(self, penalty: float) -> float:
        """-2 log-likelihood of the held-out data plus the parsimony penalty (smaller is better)."""
        return self.n * float(np.log(max(self.sse, 1e-300) / self.n)) + penalty * self.n_params


def cross_validate(fold_grams: np.ndarray, n_rows: int) -> CvResult:
    """Held-out SSE from per-fold Grams of [X | y] (y the last column)."""
    total = fold_grams.sum(axis=0)
    p = total.shape[0] - 1
    train = total[None] - fold_grams
    betas = solve(train[:, :p, :p], train[:, :p, p])
    xy = fold_grams[:, :p, p]
    xx = fold_grams[:, :p, :p]
    sse_f = fold_grams[:, p, p] - 2 * np.einsum("kp,kp->k", betas, xy) + np.einsum("kp,kpq,kq->k", betas, xx, betas)
    return CvResult(sse=float(np.sum(np.maximum(sse_f, 0.0))), n=n_rows, n_params=rank(total[:p, :p]), betas=betas)


def full_fit(fold_grams: np.ndarray) -> tuple[np.ndarray, float]:
    """Coefficients fitted on all rows and their in-sample SSE."""
    total = fold_grams.sum(axis=0)
    p = total.shape[0] - 1
    beta = solve(total[:p, :p], total[:p, p])
    sse = total[p, p] - 2 * beta @ total[:p, p] + beta @ total[:p, :p] @ beta
    return beta, float(max(sse, 0.0))


def extend_grams(base: np.ndarray, a_sorted: np.ndarray, z_sorted: np.ndarray, layout: FoldLayout) -> np.ndarray:
    """Per-fold Grams of [X | Z | y] from those of [X | y] (a_sorted = fold-sorted [X | y])."""
    p = base.shape[1] - 1
    q = z_sorted.shape[1]
    az = layout.products(a_sorted, z_sorted)  # (K, p+1, q)
    zz = layout.products(z_sorted, z_sorted)
    out = np.empty((base.shape[0], p + q + 1, p + q + 1))
    out[:, :p, :p] = base[:, :p, :p]
    out[:, :p, p + q] = base[:, :p, p]
    out[:, p + q, :p] = base[:, p, :p]
    out[:, p + q, p + q] = base[:, p, p]
    out[:, :p, p:p + q] = az[:, :p]
    out[:, p:p + q, :p] = np.swapaxes(az[:, :p], 1, 2)
    out[:, p:p + q, p:p + q] = zz
    out[:, p:p + q, p + q] = az[:, p]
    out[:, p + q, p:p + q] = az[:, p]
    return out
