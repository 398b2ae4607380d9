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


STEP_BLOCK = 256  # integration steps whose rotations are formed at once (windows x steps x 9 doubles)


def _solution(acc: np.ndarray, rate: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """End position (S, 3) in m and attitude (S, 3, 3) of strapdown solutions (S windows of n steps)
    from specific force `acc` (S, n, 3) in g and rate (S, n, 3) in deg/s, starting at rest.

    Each step's specific force, rotated by the attitude at the step's start, moves the end position by
    f dt (n - k - 1) dt + f dt^2 / 2 (the velocity it adds, carried to the end, and its own half step):
    the position is one weighted sum, and only the attitudes are integrated step by step."""
    n_s, n = acc.shape[:2]
    weight = (n - np.arange(n) - 0.5) * dt ** 2 * G0
    att = np.repeat(np.eye(3)[None], n_s, axis=0)
    pos = np.zeros((n_s, 3))
    rad = np.pi / 180.0
    for k0 in range(0, n, STEP_BLOCK):
        kb = slice(k0, min(k0 + STEP_BLOCK, n))
        b = kb.stop - kb.start
        rot = _rodrigues((rate[:, kb] * (rad * dt)).reshape(-1, 3)).reshape(n_s, b, 3, 3)
        starts = np.empty((n_s, b, 3, 3))
        for i in range(b):
            starts[:, i] = att
            att = att @ rot[:, i]
        pos += np.einsum("sbij,sbj,b->si", starts, acc[:, kb], weight[kb])
    return pos, att


def _errors(pos: np.ndarray, att: np.ndarray, pos_t: np.ndarray, att_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m) and rotation angle (deg) between two sets of end states."""
    rel = np.einsum("wji,wjk->wik", att_t, att)
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return np.linalg.norm(pos - pos_t, axis=1), np.degrees(np.arccos(cos))


def navigate(values: np.ndarray, reference: np.ndarray, idx: np.ndarray,
             window_s: float = DEFAULT_WINDOW_S) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and attitude (deg) errors (W,) at the windows' ends of navigating with `values`
    (N, 6: g, deg/s) against `reference`; each of a window's rows stands for window_s / rows."""
    dt = window_s / idx.shape[1]
    v, r = values[idx], reference[idx]
    pos, att = _solution(v[..., :3], v[..., 3:], dt)
    pos_t, att_t = _solution(r[..., :3], r[..., 3:], dt)
    return _errors(pos, att, pos_t, att_t)


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
    w, n = win.shape
    dt = window_s / n
    r = ref.reshape(w, n, 6)
    pos_t, att_t = _solution(r[..., :3], r[..., 3:], dt)  # the reference solution, once for every set
    out: dict[str, InsErrors] = {}
    for name, values in outputs.items():
        v = np.asarray(values, dtype=float).reshape(w, n, 6)
        pos, att = _solution(v[..., :3], v[..., 3:], dt)
        dist, ang = _errors(pos, att, pos_t, att_t)
        out[name] = InsErrors(position_m=float(dist.mean()), attitude_deg=float(ang.mean()),
                              position_m_max=float(dist.max()), n_windows=w, window_s=window_s)
    return out
