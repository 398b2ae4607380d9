"""Cross-validation held out by time blocks, computed from per-fold Gram matrices.

Folds are contiguous stretches of time (`segment_s` long, at most 120 s) within each run,
dealt to the K folds in turn, so every run and every part of the temperature profile
appears in every fold, but a held-out stretch is never fitted by its own samples or by
samples interleaved with it (random sampling would let slowly varying errors leak across;
the drift model handles what is slower than a stretch). Long stretches were tried first:
holding out a whole soak of one orientation made a cubic extrapolate, and the resulting
noise in the held-out score was larger than the parameter charge -- spurious causes won.

Under the drift model (drift.py) fold f's training fit is the GLS fit to the other folds
(whitened by a filter that skips the held-out blocks), and its held-out score is
Q_all(b_f) - Q_f(b_f): the drift-whitened residual sum of squares of all blocks minus that
of the training blocks, i.e. -2 log p(held-out | training). Both are quadratic forms read
off Gram matrices of [X | y], so adding a candidate's columns Z only needs cross products
with Z: a search over a nonlinear parameter costs passes over a column, not refits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .blocks import Blocks

_RIDGE = 1e-10  # relative, on the unit-diagonal Gram: pins aliased directions to zero
_RANK_TOL = 1e-9


def segment_length(blocks: Blocks, n_folds: int = 5, longest_s: float = 120.0) -> float:
    """Hold-out stretch: at most `longest_s`, and short enough that a typical run spans every
    fold twice -- a per-run term can only be validated if each run is also in training."""
    starts = np.flatnonzero(blocks.new_run)
    ends = np.append(starts[1:], len(blocks)) - 1
    spans = blocks.t_s[ends] - blocks.t_s[starts]
    return float(np.clip(np.median(spans) / (2 * n_folds), 30.0, longest_s))


def long_segment_length(span_s: float, n_folds: int = 5, longest_s: float = 3600.0) -> float:
    """Long hold-out stretch: an hour, or shorter when the record (`span_s` of campaign time) does
    not span every fold twice. Held out for an hour, a stretch's drift level is poorly predicted
    from its sides, so effects slower than the short stretches (per-run offsets, slow trends) can
    earn their place there."""
    return float(min(longest_s, max(span_s / (2 * n_folds), 1.0)))


def elapsed_s(t_s: np.ndarray) -> np.ndarray:
    """(N,) campaign time since the first row (a clock restarted per run counts on)."""
    t = np.asarray(t_s, dtype=float)
    return np.cumsum(np.maximum(np.diff(t, prepend=t[:1]), 0.0))


def long_folds(blocks: Blocks, row_elapsed_s: np.ndarray, n_folds: int, segment_s: float) -> np.ndarray:
    """(M,) fold of each block: `segment_s` stretches of campaign time (across runs), dealt out in
    turn; a block belongs to the stretch of its first row (`make_blocks` cuts blocks there)."""
    seg = np.floor(row_elapsed_s[blocks.start] / segment_s).astype(np.int64)
    return (seg % n_folds).astype(np.int64)


def time_folds(blocks: Blocks, n_folds: int = 5, segment_s: float | None = None) -> np.ndarray:
    """(M,) fold of each block: `segment_s` stretches within runs, dealt out in turn."""
    if segment_s is None:
        segment_s = segment_length(blocks, n_folds)
    t = blocks.t_s
    run_start = np.maximum.accumulate(np.where(blocks.new_run, np.arange(len(blocks)), 0))
    seg = np.floor((t - t[run_start]) / segment_s).astype(np.int64)
    run_rank = np.cumsum(blocks.new_run) - 1
    return ((seg + run_rank) % n_folds).astype(np.int64)


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
    sse: float  # held-out -2 log-likelihood, up to a model-independent constant (whitened units)
    n: int  # held-out blocks (all blocks, each once)
    n_params: int  # identifiable coefficients
    betas: np.ndarray  # (K, p) coefficients of each fold's training fit

    def score(self, penalty: float) -> float:
        """-2 log-likelihood of the held-out data plus the parsimony penalty (smaller is better)."""
        return self.n * float(np.log(max(self.sse, 1e-300) / self.n)) + penalty * self.n_params


def _quadratic(gram: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Residual sum of squares y'y - 2 b'X'y + b'X'X b from Grams of [X | y] (batched)."""
    p = gram.shape[-1] - 1
    return (gram[..., p, p] - 2 * np.einsum("...p,...p->...", beta, gram[..., :p, p])
            + np.einsum("...p,...pq,...q->...", beta, gram[..., :p, :p], beta))


def cross_validate(full: np.ndarray, folds: np.ndarray, n_rows: int) -> CvResult:
    """Held-out score from the Gram of [X | y] whitened by the full filter (p+1, p+1) and the
    per-fold training Grams whitened by the fold filters (K, p+1, p+1), y the last column."""
    p = full.shape[0] - 1
    betas = solve(folds[:, :p, :p], folds[:, :p, p])
    held = _quadratic(full[None], betas) - _quadratic(folds, betas)
    return CvResult(sse=float(np.sum(np.maximum(held, 0.0))), n=n_rows, n_params=rank(full[:p, :p]), betas=betas)


def full_fit(full: np.ndarray) -> tuple[np.ndarray, float]:
    """Coefficients fitted on all rows and their in-sample SSE, from the full Gram of [X | y]."""
    p = full.shape[0] - 1
    beta = solve(full[:p, :p], full[:p, p])
    return beta, max(float(_quadratic(full, beta)), 0.0)


def extend_gram(base: np.ndarray, az: np.ndarray, zz: np.ndarray) -> np.ndarray:
    """Gram of [X | Z | y] from that of [X | y] (..., p+1, p+1), [X | y]'Z (..., p+1, q) and Z'Z."""
    p = base.shape[-1] - 1
    q = zz.shape[-1]
    out = np.empty(base.shape[:-2] + (p + q + 1, p + q + 1))
    out[..., :p, :p] = base[..., :p, :p]
    out[..., :p, p + q] = base[..., :p, p]
    out[..., p + q, :p] = base[..., p, :p]
    out[..., p + q, p + q] = base[..., p, p]
    out[..., :p, p:p + q] = az[..., :p, :]
    out[..., p:p + q, :p] = np.swapaxes(az[..., :p, :], -1, -2)
    out[..., p:p + q, p:p + q] = zz
    out[..., p:p + q, p + q] = az[..., p, :]
    out[..., p + q, p:p + q] = az[..., p, :]
    return out
