"""Gaussian RBF network (paper Eq. 8-10) trained by regularised forward selection.

h(x) = sum_j w_j exp(-|z - c_j|^2 / (2 r^2)), z = (x - offset) / scale the normalised input.

Training, after Chen, Cowan & Grant (1991) and Orr (1995, "Regularisation in the selection
of RBF centres"):

1. Candidate centres: at most `max_candidates` training inputs spread over the data by
   farthest-point sampling, so the candidate set does not grow with the sample count.
2. Forward selection with orthogonal least squares: each step adds the candidate whose
   orthogonalised column most reduces the regularised cost (y'f)^2 / (f'f + lambda); the
   regularisation lambda is re-estimated after each step by minimising generalised
   cross-validation (GCV) of the model in its orthogonal basis; selection stops when
   GCV has not improved for `patience` steps and the best-GCV subset is kept.
3. The weights of the selected centres minimise Eq. 10 (ridge), its lambda again chosen
   by GCV (closed form via the SVD of the design).
4. The Gaussian width r (in normalised units) is chosen from `widths` by final GCV.

Training points may carry weights (record means weigh by the samples they stand for):
this makes training on record means equivalent to training on the raw samples.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

DEFAULT_WIDTHS: tuple[float, ...] = (0.08, 0.15, 0.3, 0.6, 1.2)
CHUNK_ROWS = 1 << 15


@dataclass
class RbfNetwork:
    """A trained network: raw inputs in, the output (sensor units) out."""

    centres: np.ndarray  # (m, d) in normalised input units
    width: float  # Gaussian r, normalised units
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

    def normalise(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=float) - self.in_offset) / self.in_scale

    def predict(self, x: np.ndarray) -> np.ndarray:
        """(N,) outputs for raw inputs (N, d); evaluated in chunks to bound memory."""
        x = np.asarray(x, dtype=float)
        out = np.empty(x.shape[0])
        if self.n_centres == 0:
            out[:] = 0.0
            return out
        c = self.centres
        a = -0.5 / self.width ** 2
        cc = a * np.einsum("ij,ij->i", c, c)
        c2 = -2.0 * a * c.T  # (d, m)
        for s in range(0, x.shape[0], CHUNK_ROWS):
            z = self.normalise(x[s:s + CHUNK_ROWS])
            # exponent a|z - c|^2 = a|z|^2 + (-2a) z.c + a|c|^2, as one matrix product
            e = z @ c2
            e += cc
            e += (a * np.einsum("ij,ij->i", z, z))[:, None]
            np.minimum(e, 0.0, out=e)  # rounding can make it slightly positive
            np.exp(e, out=e)
            out[s:s + CHUNK_ROWS] = e @ self.weights
        return out

    def outside(self, x: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) True where an input lies outside the training range (extrapolation)."""
        x = np.asarray(x, dtype=float)
        span = (self.input_max - self.input_min) * margin
        return np.any((x < self.input_min - span) | (x > self.input_max + span), axis=1)

    def to_dict(self) -> dict[str, Any]:
        return {
            "basis": "gaussian: exp(-|z - c|^2 / (2 width^2)), z = (x - input_offset) / input_scale",
            "centres": self.centres.tolist(), "width": self.width, "weights": self.weights.tolist(),
            "input_offset": self.in_offset.tolist(), "input_scale": self.in_scale.tolist(),
            "input_min": self.input_min.tolist(), "input_max": self.input_max.tolist(),
            "lambda": self.lam, "gcv": self.gcv, "n_train": self.n_train, "n_candidates": self.n_candidates,
            "width_gcv": {repr(k): v for k, v in self.width_gcv.items()},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RbfNetwork:
        dim = len(d["input_offset"])
        return cls(
            centres=np.array(d["centres"], dtype=float).reshape(-1, dim), width=float(d["width"]),
            weights=np.array(d["weights"], dtype=float), in_offset=np.array(d["input_offset"], dtype=float),
            in_scale=np.array(d["input_scale"], dtype=float), input_min=np.array(d["input_min"], dtype=float),
            input_max=np.array(d["input_max"], dtype=float), lam=float(d.get("lambda", 0.0)),
            gcv=float(d.get("gcv", np.nan)), n_train=int(d.get("n_train", 0)),
            n_candidates=int(d.get("n_candidates", 0)),
            width_gcv={float(k): float(v) for k, v in (d.get("width_gcv") or {}).items()},
        )


def gaussian_design(z: np.ndarray, centres: np.ndarray, width: float) -> np.ndarray:
    """(n, m) basis values for normalised inputs."""
    d2 = np.einsum("ij,ij->i", z, z)[:, None] - 2.0 * z @ centres.T + np.einsum("ij,ij->i", centres, centres)[None, :]
    return np.exp(-np.maximum(d2, 0.0) / (2.0 * width ** 2))


def farthest_points(z: np.ndarray, k: int, weights: np.ndarray | None = None) -> np.ndarray:
    """Indices of up to k points spread over z (greedy maximin, deterministic)."""
    n = z.shape[0]
    if n <= k:
        return np.arange(n)
    start = int(np.argmax(weights)) if weights is not None else 0
    chosen = [start]
    d = np.einsum("ij,ij->i", z - z[start], z - z[start])
    for _ in range(k - 1):
        j = int(np.argmax(d))
        if d[j] <= 0:
            break
        chosen.append(j)
        d = np.minimum(d, np.einsum("ij,ij->i", z - z[j], z - z[j]))
    return np.array(chosen)


def _gcv_orthogonal(d: np.ndarray, g: np.ndarray, zz: float, n: int, lams: np.ndarray) -> np.ndarray:
    """GCV at each lambda of a model with orthogonal columns (norms d, projections g)."""
    dl = d[None, :] + lams[:, None]
    gamma = np.sum(d[None, :] / dl, axis=1)
    rss = zz - np.sum(g[None, :] ** 2 * (d[None, :] + 2 * lams[:, None]) / dl ** 2, axis=1)
    rss = np.maximum(rss, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(n - gamma > 1e-9, n * rss / (n - gamma) ** 2, np.inf)


def _lambda_grid(scale: float) -> np.ndarray:
    return np.concatenate(([0.0], scale * np.logspace(-12, 2, 57)))


def forward_select(phi: np.ndarray, y: np.ndarray, w: np.ndarray, max_centres: int,
                   patience: int = 6) -> tuple[list[int], float]:
    """Regularised OLS forward selection with GCV; returns selected columns and their GCV."""
    n, m_all = phi.shape
    sw = np.sqrt(w)
    f = phi * sw[:, None]
    z = y * sw
    zz = float(z @ z)
    norms = np.einsum("ij,ij->j", f, f)
    orig = norms.copy()
    avail = orig > 1e-12 * max(orig.max(), 1e-300)
    lams = _lambda_grid(float(orig.mean()) if m_all else 1.0)
    lam = 0.0
    sel: list[int] = []
    ds: list[float] = []
    gs: list[float] = []
    best_gcv, best_m = zz / n, 0
    for _ in range(min(max_centres, m_all, n - 1)):
        proj = f.T @ z
        score = np.where(avail, proj ** 2 / (norms + lam + 1e-300), -np.inf)
        j = int(np.argmax(score))
        if not np.isfinite(score[j]) or score[j] <= 0:
            break
        q = f[:, j].copy()
        dq = float(q @ q)
        sel.append(j)
        ds.append(dq)
        gs.append(float(proj[j]))
        avail[j] = False
        # Modified Gram-Schmidt: remove the new direction from every remaining candidate.
        coef = (q @ f) / dq
        f -= np.outer(q, coef)
        norms = np.einsum("ij,ij->j", f, f)
        avail &= norms > 1e-9 * orig
        gcv = _gcv_orthogonal(np.array(ds), np.array(gs), zz, n, lams)
        k = int(np.argmin(gcv))
        lam = float(lams[k])
        if gcv[k] < best_gcv * (1 - 1e-9):
            best_gcv, best_m = float(gcv[k]), len(sel)
        elif len(sel) - best_m >= patience:
            break
    return sel[:best_m], best_gcv


def ridge_gcv(h: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Weights minimising Eq. 10 with lambda chosen by GCV; returns (weights, lambda, gcv)."""
    n, m = h.shape
    if m == 0:
        z = y * np.sqrt(w)
        return np.zeros(0), 0.0, float(z @ z) / n
    sw = np.sqrt(w)
    u, s, vt = np.linalg.svd(h * sw[:, None], full_matrices=False)
    z = y * sw
    uz = u.T @ z
    outside = float(z @ z - uz @ uz)
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
              candidates: np.ndarray | None = None, patience: int = 6,
              in_offset: np.ndarray | None = None, in_scale: np.ndarray | None = None) -> RbfNetwork:
    """Train one network on inputs x (n, d), targets y (n,), point weights w (n,).

    `candidates` (raw input units) overrides the farthest-point candidate set, e.g. to
    train two networks on different data from the same candidates.
    """
    x = np.asarray(x, dtype=float)
    x = x[:, None] if x.ndim == 1 else x
    y = np.asarray(y, dtype=float)
    n = y.size
    w = np.ones(n) if w is None else np.asarray(w, dtype=float)
    w = w / w.mean()
    if in_offset is None or in_scale is None:
        in_offset, in_scale = normalisation(x)
    zx = (x - in_offset) / in_scale
    if candidates is None:
        cand = zx[farthest_points(zx, max_candidates, w)]
    else:
        cand = (np.asarray(candidates, dtype=float) - in_offset) / in_scale
    best: RbfNetwork | None = None
    scores: dict[float, float] = {}
    for r in widths:
        phi = gaussian_design(zx, cand, r)
        sel, _ = forward_select(phi, y, w, max_centres, patience)
        weights, lam, gcv = ridge_gcv(phi[:, sel], y, w)
        scores[float(r)] = gcv
        if best is None or gcv < best.gcv:
            best = RbfNetwork(centres=cand[sel], width=float(r), weights=weights, in_offset=in_offset,
                              in_scale=in_scale, input_min=x.min(axis=0), input_max=x.max(axis=0), lam=lam,
                              gcv=gcv, n_train=n, n_candidates=int(cand.shape[0]))
    assert best is not None
    best.width_gcv = scores
    return best
