"""Weighted linear least squares that knows what the data cannot determine.

Every calibration fit here is linear in its parameters. `weighted_lstsq` finds which
parameters the design leaves undetermined (a missing orientation, no table rotation, a
single temperature), fits the others, and returns their covariance from the residuals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class LinearFit:
    """Result of a weighted least-squares fit with k right-hand sides sharing one design."""

    coef: np.ndarray  # (p, k); nan where not identifiable
    cov: np.ndarray  # (k, p, p); nan rows/columns where not identifiable (or no estimate of the noise)
    identifiable: np.ndarray  # (p,) bool
    dof: int  # residual degrees of freedom (records - identifiable parameters)
    sigma2: np.ndarray  # (k,) residual variance per unit weight (nan if dof < 1)
    residual: np.ndarray  # (n, k) unweighted residuals

    @property
    def std(self) -> np.ndarray:
        """(p, k) standard uncertainties."""
        return np.sqrt(np.clip(np.diagonal(self.cov, axis1=1, axis2=2), 0.0, None)).T


def identifiable_columns(x: np.ndarray, w: np.ndarray, rel_tol: float = 1e-9) -> np.ndarray:
    """(p,) True for parameters the weighted design determines (not in its null space)."""
    xw = x * np.sqrt(w)[:, None]
    norms = np.linalg.norm(xw, axis=0)
    ok = norms > 0
    if not ok.any():
        return ok
    xs = xw[:, ok] / norms[ok]
    # U is not needed: full_matrices only when the null space has more rows than vt would keep (n < p).
    _, s, vt = np.linalg.svd(xs, full_matrices=xs.shape[0] < xs.shape[1])
    rank = int(np.sum(s > rel_tol * max(s[0], 1e-300))) if s.size else 0
    null = vt[rank:]
    free = np.zeros(int(ok.sum()), dtype=bool)
    if null.size:
        free = np.linalg.norm(null, axis=0) > 1e-6
    out = np.zeros(x.shape[1], dtype=bool)
    out[np.flatnonzero(ok)] = ~free
    return out


def weighted_lstsq(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None,
                   known_var: np.ndarray | None = None) -> LinearFit:
    """Fit y ~ x @ coef with weights w (relative: only their ratios matter).

    Covariance is sigma^2 (X'WX)^-1 with sigma^2 from the weighted residuals. When there
    are no residual degrees of freedom and `known_var` (n, k) is given (e.g. the
    within-record standard errors), the covariance is propagated from it instead.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    y2 = y[:, None] if y.ndim == 1 else y
    n, p = x.shape
    k = y2.shape[1]
    w = np.ones(n) if w is None else np.asarray(w, dtype=float)
    w = w / w.mean() if w.size and w.mean() > 0 else w
    ident = identifiable_columns(x, w) if n else np.zeros(p, dtype=bool)
    coef = np.full((p, k), np.nan)
    cov = np.full((k, p, p), np.nan)
    sigma2 = np.full(k, np.nan)
    resid = y2.copy()
    cols = np.flatnonzero(ident)
    dof = n - cols.size
    if cols.size:
        sw = np.sqrt(w)[:, None]
        xi = x[:, cols]
        # Column scaling keeps powers of temperature well conditioned.
        scale = np.linalg.norm(xi * sw, axis=0)
        a = xi * sw / scale
        sol, *_ = np.linalg.lstsq(a, y2 * sw, rcond=None)
        beta = sol / scale[:, None]
        coef[cols] = beta
        resid = y2 - xi @ beta
        inv = np.linalg.inv(a.T @ a) / np.outer(scale, scale)
        if dof > 0:
            sigma2 = (w[:, None] * resid ** 2).sum(axis=0) / dof
            for j in range(k):
                cov[j][np.ix_(cols, cols)] = sigma2[j] * inv
        elif known_var is not None:
            kv = np.asarray(known_var, dtype=float).reshape(n, k)
            pinv = inv @ (xi * w[:, None]).T  # (p_i, n): beta = pinv @ y
            for j in range(k):
                if np.all(np.isfinite(kv[:, j])):
                    cov[j][np.ix_(cols, cols)] = (pinv * kv[:, j]) @ pinv.T
    return LinearFit(coef=coef, cov=cov, identifiable=ident, dof=int(dof), sigma2=sigma2, residual=resid)


def gauge_lstsq(x: np.ndarray, y: np.ndarray, w: np.ndarray, preferred: np.ndarray) -> np.ndarray:
    """(p, k) a least-squares solution that fixes what the design leaves free: the identifiable
    parameters as `weighted_lstsq` fits them, the free directions resolved by the smallest norm of
    the columns not `preferred` (in units of their weighted column norms).

    The calibration uses it where orientations cannot separate bias from scale factor and
    misalignment: the fit then reproduces each seen orientation's output exactly and puts what is
    common to them in the bias (preferred), only their differences in S.
    """
    w = np.asarray(w, dtype=float)
    w = w / w.mean() if w.size and w.mean() > 0 else w
    sw = np.sqrt(w)[:, None]
    xw = x * sw
    norms = np.linalg.norm(xw, axis=0)
    live = norms > 1e-12 * max(float(norms.max(initial=0.0)), 1e-300)
    # A preferred column costs (1 / CHEAP)^2 of a free one: the minimum-norm solution puts the free
    # directions into it. 1e3 keeps the system's conditioning far from the rank cut below.
    cheap = 1e3
    d = np.where(live, np.where(preferred, cheap, 1.0) / np.where(live, norms, 1.0), 0.0)
    a = xw[:, live] * d[live]
    sol, *_ = np.linalg.lstsq(a, np.asarray(y, dtype=float).reshape(x.shape[0], -1) * sw, rcond=1e-10)
    coef = np.zeros((x.shape[1], sol.shape[1]))
    coef[live] = sol * d[live][:, None]
    return coef
