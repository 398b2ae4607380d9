"""Gaussian RBF network (paper Eq. 8-10) trained by regularised forward selection.

h(x) = sum_j w_j exp(-sum_d (z_d - c_jd)^2 / (2 r_d^2)), z = (x - offset) / scale the normalised
input. The paper's network has one width r for all inputs; a per-input width floor
(`min_width`) lets the temperature input keep a width of at least the spacing of the
calibration temperatures (see `rbf_model.py`).

Training, after Chen, Cowan & Grant (1991) and Orr (1995, "Regularisation in the selection
of RBF centres"):

1. Candidate centres: at most `max_candidates` training inputs spread over the data by
   farthest-point sampling, so the candidate set does not grow with the sample count.
2. Forward selection with orthogonal least squares: each step adds the candidate whose
   orthogonalised column most reduces the regularised cost (y'f)^2 / (f'f + lambda); the
   regularisation lambda is re-estimated after each step by minimising generalised
   cross-validation (GCV) of the model in its orthogonal basis; selection stops when
   GCV has not improved for `patience` steps and the best-GCV subset is kept. GCV alone
   does not see that the best of many candidates fits noise by chance (on pure noise it
   happily keeps dozens of narrow centres), so selection also stops when the best
   candidate explains less than 2 ln M residual variances (the risk inflation criterion).
3. The weights of the selected centres minimise Eq. 10 (ridge), its lambda again chosen
   by GCV (closed form via the SVD of the design).
4. The Gaussian width r (in normalised units) is chosen from `widths` by final GCV
   (per input: max(r, min_width_d)).

Training points may carry weights (record means weigh by the samples they stand for):
this makes training on record means equivalent to training on the raw samples.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .malloc_tuning import tuned_malloc

log = logging.getLogger(__name__)

DEFAULT_WIDTHS: tuple[float, ...] = (0.08, 0.15, 0.3, 0.6)
CHUNK_ROWS = 1 << 11  # rows per kernel block: (rows x centres) temporaries stay in cache
_WORKERS = max(1, min(4, os.cpu_count() or 1))


@dataclass
class RbfNetwork:
    """A trained network: raw inputs in, the output (sensor units) out."""

    centres: np.ndarray  # (m, d) in normalised input units
    width: np.ndarray  # (d,) Gaussian r per input, normalised units
    weights: np.ndarray  # (m,)
    in_offset: np.ndarray  # (d,)
    in_scale: np.ndarray  # (d,)
    input_min: np.ndarray  # (d,) training input range (raw units), for extrapolation flags
    input_max: np.ndarray  # (d,)
    lam: float = 0.0  # ridge factor of Eq. 10 (weights of normalised-weight data)
    gcv: float = float("nan")
    n_train: int = 0
    n_candidates: int = 0
    width_gcv: dict[float, float] = field(default_factory=dict)

    @property
    def n_centres(self) -> int:
        return int(self.weights.size)

    @property
    def float32_error_bound(self) -> float:
        """Bound of the output error of single-precision evaluation (a microcontroller's float):
        each kernel value is good to ~1e-7 relative, so the output to ~1e-7 sum|w_j|."""
        return float(5e-7 * np.sum(np.abs(self.weights)))

    def normalise(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=float) - self.in_offset) / self.in_scale

    def predict(self, x: np.ndarray, precise: bool = False) -> np.ndarray:
        """(N,) outputs for raw inputs (N, d), in chunks on all cores.

        The fast path (default) evaluates the kernels in float32 (what a microcontroller
        does; relative error ~1e-6 of the correction); `precise` keeps float64.
        """
        x = np.asarray(x, dtype=float)
        out = np.empty(x.shape[0])
        if self.n_centres == 0 or x.shape[0] == 0:
            out[:] = 0.0
            return out
        dtype = np.float64 if precise else np.float32
        c = (self.centres / self.width).T.astype(dtype)  # (d, m), kernel exp(-|z' - c'|^2 / 2)
        w = self.weights.astype(dtype)
        inv = (1.0 / (self.in_scale * self.width))
        off = self.in_offset

        def run(s: int) -> None:
            z = ((x[s:s + CHUNK_ROWS] - off) * inv).astype(dtype)
            e = np.subtract(z[:, 0:1], c[0])
            e *= e
            for d in range(1, c.shape[0]):
                t = np.subtract(z[:, d:d + 1], c[d])
                t *= t
                e += t
            e *= dtype(-0.5)
            np.exp(e, out=e)
            out[s:s + CHUNK_ROWS] = e @ w

        starts = range(0, x.shape[0], CHUNK_ROWS)
        if len(starts) > 1 and _WORKERS > 1:
            tuned_malloc()
            with ThreadPoolExecutor(_WORKERS) as pool:  # numpy releases the GIL in these loops
                list(pool.map(run, starts))
        else:
            for s in starts:
                run(s)
        return out

    def outside(self, x: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) True where an input lies outside the training range (extrapolation)."""
        x = np.asarray(x, dtype=float)
        span = (self.input_max - self.input_min) * margin
        lo, hi = self.input_min - span, self.input_max + span
        # column by column: np.any(..., axis=1) over rows of 2-4 inputs loops per row (5x the time)
        out = (x[:, 0] < lo[0]) | (x[:, 0] > hi[0])
        for d in range(1, x.shape[1]):
            out |= (x[:, d] < lo[d]) | (x[:, d] > hi[d])
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "basis": "gaussian: exp(-sum_d (z_d - c_d)^2 / (2 width_d^2)), z = (x - input_offset) / input_scale",
            "centres": self.centres.tolist(), "width": self.width.tolist(), "weights": self.weights.tolist(),
            "input_offset": self.in_offset.tolist(), "input_scale": self.in_scale.tolist(),
            "input_min": self.input_min.tolist(), "input_max": self.input_max.tolist(),
            "lambda": self.lam, "gcv": self.gcv, "n_train": self.n_train, "n_candidates": self.n_candidates,
            "width_gcv": {repr(k): v for k, v in self.width_gcv.items()},
            "float32_error_bound": self.float32_error_bound,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RbfNetwork:
        dim = len(d["input_offset"])
        return cls(
            centres=np.array(d["centres"], dtype=float).reshape(-1, dim),
            width=np.broadcast_to(np.array(d["width"], dtype=float), (dim,)).copy(),
            weights=np.array(d["weights"], dtype=float), in_offset=np.array(d["input_offset"], dtype=float),
            in_scale=np.array(d["input_scale"], dtype=float), input_min=np.array(d["input_min"], dtype=float),
            input_max=np.array(d["input_max"], dtype=float), lam=float(d.get("lambda", 0.0)),
            gcv=float(d.get("gcv", np.nan)), n_train=int(d.get("n_train", 0)),
            n_candidates=int(d.get("n_candidates", 0)),
            width_gcv={float(k): float(v) for k, v in (d.get("width_gcv") or {}).items()},
        )


def gaussian_design(z: np.ndarray, centres: np.ndarray, width: np.ndarray | float) -> np.ndarray:
    """(n, m) basis values for normalised inputs."""
    width = np.asarray(width, dtype=float)
    z = z / width
    centres = centres / width
    # |z|^2 - 2 z.c + |c|^2 in place: one (n, m) array, not five (the same operations in the same order)
    d2 = z @ centres.T
    d2 *= -2.0
    d2 += np.einsum("ij,ij->i", z, z)[:, None]
    d2 += np.einsum("ij,ij->i", centres, centres)[None, :]
    np.maximum(d2, 0.0, out=d2)
    d2 *= -0.5
    return np.exp(d2, out=d2)


def farthest_points(z: np.ndarray, k: int, weights: np.ndarray | None = None) -> np.ndarray:
    """Indices of up to k points spread over z (greedy maximin, deterministic)."""
    n = z.shape[0]
    if n <= k:
        return np.arange(n)
    start = int(np.argmax(weights)) if weights is not None else 0
    chosen = [start]
    squared = _squared_distances(z)
    d = squared(start, np.empty(n))
    dj = np.empty_like(d)
    for _ in range(k - 1):
        j = int(np.argmax(d))
        if d[j] <= 0:
            break
        chosen.append(j)
        np.minimum(d, squared(j, dj), out=d)
    return np.array(chosen)


def _squared_distances(z: np.ndarray) -> Callable[[int, np.ndarray], np.ndarray]:
    """`squared(j, out)`: out = |z_i - z_j|^2 for every point i, in buffers reused over the calls.

    One or two inputs (the paper and hybrid networks): column by column, d0^2 + d1^2 as the row-wise
    einsum sums them (the same numbers), without numpy's per-row loop over a row of two. More inputs:
    the einsum itself (it sums longer rows in another order)."""
    n, dim = z.shape
    if dim > 2:
        diff = np.empty_like(z)

        def rows(j: int, out: np.ndarray) -> np.ndarray:
            np.subtract(z, z[j], out=diff)
            return np.einsum("ij,ij->i", diff, diff, out=out)

        return rows
    cols = [np.ascontiguousarray(z[:, i]) for i in range(dim)]
    tmp = np.empty(n)

    def columns(j: int, out: np.ndarray) -> np.ndarray:
        np.subtract(cols[0], cols[0][j], out=out)
        np.multiply(out, out, out=out)
        for c in cols[1:]:
            np.subtract(c, c[j], out=tmp)
            np.multiply(tmp, tmp, out=tmp)
            np.add(out, tmp, out=out)
        return out

    return columns


def _gcv_orthogonal(d: np.ndarray, g: np.ndarray, zz: float, n: float, lams: np.ndarray) -> np.ndarray:
    """GCV at each lambda of a model with orthogonal columns (norms d, projections g)."""
    lam = lams[:, None]
    dl = d + lam
    gamma = np.sum(d / dl, axis=1)
    rss = zz - np.sum(g ** 2 * (d + 2 * lam) / dl ** 2, axis=1)
    rss = np.maximum(rss, 0.0)
    left = n - gamma
    # GCV where the model leaves degrees of freedom, else inf (divided only there: no warning to silence)
    return np.divide(n * rss, left ** 2, out=np.full(lams.shape, np.inf), where=left > 1e-9)


def _lambda_grid(scale: float) -> np.ndarray:
    return np.concatenate(([0.0], scale * np.logspace(-12, 2, 57)))


def forward_select(phi: np.ndarray, y: np.ndarray, w: np.ndarray, max_centres: int,
                   patience: int = 6, n_total: float | None = None, within_ss: float = 0.0) -> tuple[list[int], float]:
    """Regularised OLS forward selection with GCV; returns selected columns and their GCV.

    The candidates are never orthogonalised in place: with Q the orthogonal basis built so
    far and C[i, j] = q_i'f_j / q_i'q_i, a candidate's squared norm and projection on the
    target after orthogonalisation are updated from one product q'F per step.
    """
    n_pts, m_all = phi.shape
    n = float(n_pts if n_total is None else n_total)
    sw = np.sqrt(w)
    f = phi * sw[:, None]
    z = y * sw
    zz = float(z @ z) + within_ss
    norms = np.einsum("ij,ij->j", f, f)
    orig = norms.copy()
    proj = f.T @ z
    avail = orig > 1e-12 * max(orig.max(), 1e-300)
    lams = _lambda_grid(float(orig.mean()) if m_all else 1.0)
    lam = 0.0
    steps = min(max_centres, m_all, n_pts - 1)
    q_basis = np.empty((n_pts, max(steps, 1)))
    c_mat = np.empty((max(steps, 1), m_all))
    sel: list[int] = []
    ds = np.empty(max(steps, 1))  # the selected columns' orthogonalised norms and projections, ds[:k], gs[:k]
    gs = np.empty(max(steps, 1))
    best_gcv, best_m = zz / n, 0
    for k in range(steps):
        score = np.where(avail, proj ** 2 / (norms + lam + 1e-300), -np.inf)
        j = int(np.argmax(score))
        if not np.isfinite(score[j]) or score[j] <= 0:
            break
        # Selection-bias guard (risk inflation criterion, Foster & George 1994): the best of M
        # candidates explains ~2 ln M noise variances by chance, so stop when it explains less.
        rss = zz - float(np.sum(gs[:k] ** 2 / ds[:k])) if k else zz
        if score[j] < 2.0 * np.log(max(int(avail.sum()), 2)) * rss / max(n - len(sel), 1):
            break
        q = f[:, j] - q_basis[:, :k] @ c_mat[:k, j]  # the chosen column, orthogonalised
        dq = float(q @ q)
        sel.append(j)
        ds[k] = dq
        gs[k] = g = float(proj[j])
        avail[j] = False
        c = (q @ f) / dq  # q is orthogonal to the basis, so q'f_j equals q'(orthogonalised f_j)
        q_basis[:, k] = q
        c_mat[k] = c
        proj -= c * g
        norms -= c * c * dq
        avail &= norms > 1e-9 * orig
        gcv = _gcv_orthogonal(ds[:k + 1], gs[:k + 1], zz, n, lams)
        i = int(np.argmin(gcv))
        lam = float(lams[i])
        if gcv[i] < best_gcv * (1 - 1e-9):
            best_gcv, best_m = float(gcv[i]), len(sel)
        elif len(sel) - best_m >= patience:
            break
    return sel[:best_m], best_gcv


def ridge_gcv(h: np.ndarray, y: np.ndarray, w: np.ndarray, n_total: float | None = None,
              within_ss: float = 0.0) -> tuple[np.ndarray, float, float]:
    """Weights minimising Eq. 10 with lambda chosen by GCV; returns (weights, lambda, gcv)."""
    n_pts, m = h.shape
    n = float(n_pts if n_total is None else n_total)
    if m == 0:
        z = y * np.sqrt(w)
        return np.zeros(0), 0.0, (float(z @ z) + within_ss) / n
    sw = np.sqrt(w)
    u, s, vt = np.linalg.svd(h * sw[:, None], full_matrices=False)
    z = y * sw
    uz = u.T @ z
    outside = float(z @ z - uz @ uz) + within_ss
    s2 = s ** 2
    lams = _lambda_grid(float(s2.mean()))
    shrink = lams[:, None] / (s2[None, :] + lams[:, None])  # 1 - filter factor
    rss = np.sum((shrink * uz[None, :]) ** 2, axis=1) + max(outside, 0.0)
    gamma = np.sum(1 - shrink, axis=1)
    gcv = np.where(n - gamma > 1e-9, n * rss / np.maximum(n - gamma, 1e-300) ** 2, np.inf)
    # Drop directions the data cannot see (lambda = 0 with a rank-deficient design).
    k = int(np.argmin(gcv))
    lam = float(lams[k])
    with np.errstate(divide="ignore", invalid="ignore"):
        filt = np.where(s2 + lam > 1e-14 * s2.max(), s / (s2 + lam), 0.0)
    return vt.T @ (filt * uz), lam, float(gcv[k])


def normalisation(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offset and scale mapping each input's range to [-1, 1] (scale 1 for constant inputs)."""
    lo, hi = x.min(axis=0), x.max(axis=0)
    scale = (hi - lo) / 2.0
    scale = np.where(scale > 1e-12 * np.maximum(np.abs(hi), 1.0), scale, 1.0)
    return (hi + lo) / 2.0, scale


def train_rbf(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None, *,
              widths: Sequence[float] = DEFAULT_WIDTHS, max_centres: int = 80, max_candidates: int = 400,
              candidates: np.ndarray | None = None, patience: int = 6, min_width: np.ndarray | None = None,
              in_offset: np.ndarray | None = None, in_scale: np.ndarray | None = None,
              counts: bool = False, within_ss: float = 0.0) -> RbfNetwork:
    """Train one network on inputs x (n, d), targets y (n,), point weights w (n,).

    With `counts`, w are sample counts of means (records) and `within_ss` the targets'
    sum of squares within them: least squares and GCV then equal those of training on
    the samples themselves (each at its mean's input). Otherwise w are relative weights.
    `candidates` (raw input units) overrides the farthest-point candidate set, e.g. to
    train two networks on different data from the same candidates.
    """
    x = np.asarray(x, dtype=float)
    x = x[:, None] if x.ndim == 1 else x
    y = np.asarray(y, dtype=float)
    n = y.size
    w = np.ones(n) if w is None else np.asarray(w, dtype=float)
    n_total: float | None = float(w.sum()) if counts else None
    if not counts:
        w = w / w.mean()
        within_ss = 0.0
    if in_offset is None or in_scale is None:
        in_offset, in_scale = normalisation(x)
    zx = (x - in_offset) / in_scale
    if candidates is None:
        cand = zx[farthest_points(zx, max_candidates, w)]
    else:
        cand = (np.asarray(candidates, dtype=float) - in_offset) / in_scale
    floor = np.zeros(zx.shape[1]) if min_width is None else np.asarray(min_width, dtype=float)
    fits: list[RbfNetwork] = []
    scores: dict[float, float] = {}
    for r0 in widths:
        r = np.maximum(float(r0), floor)
        phi = gaussian_design(zx, cand, r)
        sel, _ = forward_select(phi, y, w, max_centres, patience, n_total, within_ss)
        weights, lam, gcv = ridge_gcv(phi[:, sel], y, w, n_total, within_ss)
        scores[float(r0)] = gcv
        fits.append(RbfNetwork(centres=cand[sel], width=r, weights=weights, in_offset=in_offset, in_scale=in_scale,
                               input_min=x.min(axis=0), input_max=x.max(axis=0), lam=lam, gcv=gcv,
                               n_train=int(round(n_total)) if n_total else n,
                               n_candidates=int(cand.shape[0])))
    # Widths whose GCV is within 1 % of the best are equally good: keep the best-conditioned
    # (smallest sum |w|), which single precision evaluates best.
    top = min(f.gcv for f in fits)
    best = min((f for f in fits if f.gcv <= top * 1.01), key=lambda f: float(np.sum(np.abs(f.weights))))
    assert best is not None
    best.width_gcv = scores
    return best
