"""The paper's INS test (Sec. V.C, Fig. 14): strapdown navigation over short windows, before and after
compensation.

For each window (60 s by default) of contiguous rows of one record, two strapdown solutions start
from the same attitude at rest: one from the reference (the true specific force, +1 g along the up
axis, and the table's rate about it), one from the outputs (raw or compensated). Attitude is
integrated from the angular rate (Rodrigues' formula per step), velocity and position from the
specific force rotated into the navigation frame, minus the true one. At the window's end the
position error is the distance between the two solutions and the attitude error the angle of the
rotation between them; both are averaged over the windows. Earth's rate and the table's centripetal
acceleration are not modelled (neither is in the reference values), so a static window measures what
the IMU's errors alone do to a navigation solution in a minute.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .records import reference_values

G0 = 9.80665  # m/s^2 per g
DEFAULT_WINDOW_S = 60.0
MAX_WINDOWS = 400  # windows navigated per data set (spread over the data) to bound the time


@dataclass(frozen=True)
class InsErrors:
    """End-of-window navigation errors, averaged over the windows."""

    position_m: float  # mean distance between the solutions at the window's end
    attitude_deg: float  # mean angle between the attitudes at the window's end
    position_m_max: float
    n_windows: int
    window_s: float

    def to_dict(self) -> dict[str, Any]:
        return {"position_m": self.position_m, "attitude_deg": self.attitude_deg,
                "position_m_max": self.position_m_max, "n_windows": self.n_windows, "window_s": self.window_s}


def windows(t: np.ndarray, labels: np.ndarray, window_s: float = DEFAULT_WINDOW_S,
            max_windows: int = MAX_WINDOWS) -> np.ndarray:
    """(W, n) row indices of windows of `window_s` of consecutive rows with one label (>= 0) and no gap."""
    t = np.asarray(t, dtype=float)
    if t.size < 2:
        return np.zeros((0, 0), dtype=np.int64)
    dt = np.diff(t)
    step = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    n = int(round(window_s / step))  # rows of a window; each row stands for one step of `step` s
    brk = np.concatenate(([True], (labels[1:] != labels[:-1]) | (dt > 1.5 * step) | (dt <= 0)))
    starts = np.flatnonzero(brk)
    stops = np.append(starts[1:], t.size)
    out = [np.arange(s, s + n) for a, b in zip(starts, stops) if labels[a] >= 0
           for s in range(a, b - n + 1, n)]
    if not out:
        return np.zeros((0, n), dtype=np.int64)
    w = np.stack(out)
    if w.shape[0] > max_windows:
        w = w[np.linspace(0, w.shape[0] - 1, max_windows).round().astype(np.int64)]
    return w


def _rodrigues(phi: np.ndarray) -> np.ndarray:
    """(W, 3, 3) rotation matrices of rotation vectors (W, 3) (rad)."""
    angle = np.linalg.norm(phi, axis=1)
    k = np.where(angle[:, None] > 1e-12, phi / np.maximum(angle, 1e-300)[:, None], 0.0)
    kx = np.zeros((phi.shape[0], 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3)[None] + s * kx + (1 - c) * (kx @ kx)


def navigate(values: np.ndarray, reference: np.ndarray, idx: np.ndarray,
             window_s: float = DEFAULT_WINDOW_S) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and attitude (deg) errors (W,) at the windows' ends of navigating with `values`
    (N, 6: g, deg/s) against `reference`; each of a window's rows stands for window_s / rows."""
    n_w, n = idx.shape
    dt = window_s / n
    r_m = np.repeat(np.eye(3)[None], n_w, axis=0)
    r_t = r_m.copy()
    vel = np.zeros((n_w, 3))
    pos = np.zeros((n_w, 3))
    rad = np.pi / 180.0
    for k in range(n):
        i = idx[:, k]
        # specific force error in the navigation frame (m/s^2), from the step's start values
        f_err = (np.einsum("wij,wj->wi", r_m, values[i, :3]) - np.einsum("wij,wj->wi", r_t, reference[i, :3])) * G0
        pos += vel * dt + 0.5 * f_err * dt ** 2
        vel += f_err * dt
        r_m = r_m @ _rodrigues(values[i, 3:] * rad * dt)
        r_t = r_t @ _rodrigues(reference[i, 3:] * rad * dt)
    rel = np.einsum("wji,wjk->wik", r_t, r_m)
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return np.linalg.norm(pos, axis=1), np.degrees(np.arccos(cos))


def window_rows(a: dict[str, np.ndarray], rows: np.ndarray, labels: np.ndarray,
                window_s: float = DEFAULT_WINDOW_S, max_windows: int = MAX_WINDOWS) -> np.ndarray:
    """(W, n) indices into the campaign arrays of windows of contiguous rows of one record among `rows`."""
    sel = np.flatnonzero(rows) if rows.dtype == bool else np.asarray(rows)
    idx = windows(a["t"][sel], labels[sel], window_s, max_windows)
    return sel[idx] if idx.size else idx


def ins_errors(a: dict[str, np.ndarray], win: np.ndarray, outputs: dict[str, np.ndarray],
               window_s: float = DEFAULT_WINDOW_S) -> dict[str, InsErrors]:
    """Navigation errors of each output set over the windows `win` (W, n) of `window_rows`; an output set
    (name -> (W * n, 6)) holds the raw or compensated outputs of the rows `win.ravel()`."""
    if win.size == 0:
        return {name: InsErrors(float("nan"), float("nan"), float("nan"), 0, window_s) for name in outputs}
    rows = win.ravel()
    ref = reference_values(a["orientation"][rows], a["rate"][rows])
    names = list(outputs)
    w, n = win.shape
    local = np.arange(w * n).reshape(w, n)
    # All output sets in one pass: set m's windows index its copy of the rows.
    stacked = np.concatenate([outputs[m] for m in names])
    all_idx = np.concatenate([local + m * rows.size for m in range(len(names))])
    dist, ang = navigate(stacked, np.tile(ref, (len(names), 1)), all_idx, window_s)
    return {name: InsErrors(position_m=float(dist[m * w:(m + 1) * w].mean()),
                            attitude_deg=float(ang[m * w:(m + 1) * w].mean()),
                            position_m_max=float(dist[m * w:(m + 1) * w].max()), n_windows=w, window_s=window_s)
            for m, name in enumerate(names)}
