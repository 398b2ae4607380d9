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

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .px4_reference import ValueCounts
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


# Consecutive intervals of a piece of `RowRuns` differ by at most this fraction (a store's times, t0 + k / rate
# in float64, differ by a few ulps: 1e-8 of 20 ms at a week's t).
PIECE_REL_TOL = 1e-6


class RowRuns:
    """The rows `windows` chooses from (times, labels, campaign positions, in order), met chunk by chunk
    and held as pieces: consecutive positions of one label whose intervals are positive and alike, each
    as (first index in the sequence, rows, first position, label, interval before it, smallest and largest
    interval within), with the intervals' distinct values and counts for their median. Memory grows
    with the pieces (records, dropped samples) and the distinct intervals, not with the rows.

    `window_positions` gives `pos[windows(t, labels)]` of the rows added, or None when the pieces cannot
    tell: a piece's intervals straddle the gap threshold (1.5 x the median interval), or a window is
    one row; the caller then runs `windows` on the rows themselves."""

    def __init__(self) -> None:
        self.closed: list[np.ndarray] = []  # (k, 7) float rows of closed pieces, columns as _FIELDS
        self.open: np.ndarray | None = None  # the last piece, still growing
        self.last = (0.0, 0, 0)  # time, position, label of the last row
        self.prev_dt = np.nan  # the last interval
        self.n = 0
        self.intervals = ValueCounts()

    _FIELDS = ("first", "rows", "pos", "label", "dt_before", "dt_min", "dt_max")

    def add(self, t: np.ndarray, labels: np.ndarray, pos: np.ndarray) -> None:
        m = int(t.size)
        if m == 0:
            return
        carried = self.open is not None
        if carried:
            t = np.concatenate([[self.last[0]], t])
            pos = np.concatenate([[self.last[1]], pos])
            labels = np.concatenate([[self.last[2]], labels])
        t = np.asarray(t, dtype=float)
        dt = np.diff(t)
        self.intervals.add(dt[dt > 0])
        before = np.concatenate([[self.prev_dt], dt[:-1]])
        with np.errstate(invalid="ignore"):
            cut = ((labels[1:] != labels[:-1]) | (pos[1:] != pos[:-1] + 1) | (dt <= 0)
                   | (np.abs(dt - before) > PIECE_REL_TOL * before))
        starts = np.concatenate([[0], np.flatnonzero(cut) + 1])
        stops = np.append(starts[1:], t.size)
        inner = np.append(np.where(cut, np.inf, dt), np.inf)  # a piece's inner intervals; cuts and the end: inf
        dt_min = np.minimum.reduceat(inner, starts)
        dt_max = np.maximum.reduceat(np.where(np.isinf(inner), -np.inf, inner), starts)
        first = self.n - 1 + starts if carried else self.n + starts
        dt_before = np.concatenate([[np.nan], dt[starts[1:] - 1]])
        pieces = np.column_stack([first, stops - starts, pos[starts], labels[starts], dt_before, dt_min, dt_max]
                                 ).astype(float)
        if carried:
            assert self.open is not None
            head = pieces[0]
            self.open[1] += head[1] - 1
            self.open[5] = min(self.open[5], head[5])
            self.open[6] = max(self.open[6], head[6])
            pieces = pieces[1:]
        if pieces.shape[0]:
            if self.open is not None:
                self.closed.append(self.open[None])
            self.closed.append(pieces[:-1])
            self.open = pieces[-1].copy()
        self.n += m
        self.last = (float(t[-1]), int(pos[-1]), int(labels[-1]))
        if dt.size:
            self.prev_dt = float(dt[-1])

    def pieces(self) -> np.ndarray:
        """(P, 7) the pieces so far (columns as _FIELDS)."""
        parts = self.closed + ([self.open[None]] if self.open is not None else [])
        return np.concatenate(parts) if parts else np.zeros((0, 7))

    def window_positions(self, window_s: float = DEFAULT_WINDOW_S,
                         max_windows: int = MAX_WINDOWS) -> np.ndarray | None:
        """(W, n) positions of the windows `windows` chooses from the rows added (None: cannot tell)."""
        if self.n < 2:
            return np.zeros((0, 0), dtype=np.int64)
        step = self.intervals.median() if self.intervals.n else 1.0
        n = int(round(window_s / step))
        gap = 1.5 * step
        p = self.pieces()
        first, rows, pos0, label = (p[:, i].astype(np.int64) for i in range(4))
        dt_before, dt_min, dt_max = p[:, 4], p[:, 5], p[:, 6]
        multi = rows >= 2
        if n <= 1 or np.any(multi & (dt_min <= gap) & (dt_max > gap)):
            return None
        every = multi & (dt_min > gap)  # every interval within is a gap: the rows stand alone
        brk = np.ones(p.shape[0], dtype=bool)
        brk[1:] = (label[1:] != label[:-1]) | (dt_before[1:] > gap) | (dt_before[1:] <= 0)
        runs: list[tuple[int, int, int]] = []  # `windows`' runs: (first index, rows, label)
        cur, cur_rows, cur_label = 0, 0, 0
        for i in range(p.shape[0]):  # pieces into runs (a few per record)
            if brk[i] and cur_rows:
                runs.append((cur, cur_rows, cur_label))
                cur_rows = 0
            if cur_rows == 0:
                cur, cur_label = int(first[i]), int(label[i])
            if every[i]:  # its first row ends the current run, its last starts the next (no window between)
                runs.append((cur, cur_rows + 1, cur_label))
                cur, cur_rows = int(first[i] + rows[i] - 1), 1
            else:
                cur_rows += int(rows[i])
        if cur_rows:
            runs.append((cur, cur_rows, cur_label))
        starts = [s + k * n for s, r, lab in runs if lab >= 0 for k in range(r // n)]
        if not starts:
            return np.zeros((0, n), dtype=np.int64)
        w = np.asarray(starts, dtype=np.int64)
        if w.size > max_windows:
            w = w[np.linspace(0, w.size - 1, max_windows).round().astype(np.int64)]
        q = w[:, None] + np.arange(n)
        k = np.searchsorted(first, q, side="right") - 1
        return pos0[k] + (q - first[k])


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


NAV_WINDOWS = 64  # windows navigated at once (each window's solution is its own: the same numbers in any group)


@dataclass
class _Track:
    """One output set's navigation so far: the rows of its incomplete window and the end states of the
    windows navigated, group by group ((first window, position (m, 3), attitude (m, 3, 3)))."""

    carry: np.ndarray
    ends: list[tuple[int, np.ndarray, np.ndarray]]
    done: int = 0  # windows navigated


class NavigationStream:
    """The INS test's navigation of W windows of n rows each whose rows come in pieces, in window order
    (`win.ravel()`'s): `reference` takes the orientations and rates of the next rows, `add` an output
    set's values of rows (any piece sizes, each set in that order), `errors` every set's errors once all
    rows are in. Each window is navigated once its rows are in, NAV_WINDOWS at a time, so no array of
    every window's rows or outputs is held: the reference in groups of NAV_WINDOWS windows from the first,
    an output set in groups of the windows each piece completes (its end states kept, a few per window)."""

    def __init__(self, n_windows: int, n: int, window_s: float = DEFAULT_WINDOW_S) -> None:
        self.w, self.n = n_windows, n
        self.window_s = window_s
        self.dt = window_s / n
        self._ref_rows: tuple[np.ndarray, np.ndarray] | None = None  # orientations and rates not yet navigated
        self._ref_ends: list[tuple[np.ndarray, np.ndarray]] = []
        self._ref_done = 0
        self._tracks: dict[str, _Track] = {}

    def reference(self, orientation: np.ndarray, rate: np.ndarray) -> None:
        """The next rows' orientations and rates: the reference solution of every group they complete."""
        if self._ref_rows is not None:
            orientation = np.concatenate([self._ref_rows[0], orientation])
            rate = np.concatenate([self._ref_rows[1], rate])
        at = 0
        while self._ref_done < self.w:
            m = min(NAV_WINDOWS, self.w - self._ref_done)
            k = m * self.n
            if orientation.size - at < k:
                break
            ref = reference_values(orientation[at:at + k], rate[at:at + k]).reshape(m, self.n, 6)
            self._ref_ends.append(_solution(ref[..., :3], ref[..., 3:], self.dt))
            at += k
            self._ref_done += m
        self._ref_rows = (orientation[at:].copy(), rate[at:].copy()) if at < orientation.size else None

    def add(self, name: str, piece: np.ndarray) -> None:
        """Output set `name`'s values (rows, 6) of its next rows: the windows they complete navigated."""
        track = self._tracks.setdefault(name, _Track(carry=np.zeros((0, 6)), ends=[]))
        v = np.asarray(piece, dtype=float)
        c = track.carry.shape[0]
        n = self.n
        k = (c + v.shape[0]) // n  # windows complete
        for j in range(0, k, NAV_WINDOWS):  # groups of windows from the carried rows on
            m = min(NAV_WINDOWS, k - j)
            lo, hi = j * n - c, (j + m) * n - c  # the group's rows in `v`
            vw = (np.concatenate([track.carry, v[:hi]]) if lo < 0 else v[lo:hi]).reshape(m, n, 6)
            track.ends.append((track.done, *_solution(vw[..., :3], vw[..., 3:], self.dt)))
            track.done += m
        rest = k * n - c  # the rows of `v` past the last complete window (the carry's, when none completes)
        track.carry = np.concatenate([track.carry, v]) if rest < 0 else v[rest:].copy()

    def errors(self, name: str) -> InsErrors:
        """Output set `name`'s errors averaged over the windows (every row of it and of the reference in)."""
        track = self._tracks.get(name, _Track(carry=np.zeros((0, 6)), ends=[]))
        n = self.n
        if track.done != self.w or track.carry.shape[0]:
            raise ValueError(f"outputs of {track.done * n + track.carry.shape[0]} rows given for {self.w} "
                             f"windows of {n} rows")
        if self._ref_done != self.w:
            held = 0 if self._ref_rows is None else self._ref_rows[0].size
            raise ValueError(f"reference of {self._ref_done * n + held} rows given for {self.w} windows of {n} rows")
        pos_t = np.concatenate([e[0] for e in self._ref_ends])
        att_t = np.concatenate([e[1] for e in self._ref_ends])
        dist, ang = [], []
        for w0, pos, att in track.ends:
            m = pos.shape[0]
            d, g = _errors(pos, att, pos_t[w0:w0 + m], att_t[w0:w0 + m])
            dist.append(d)
            ang.append(g)
        dd, aa = np.concatenate(dist), np.concatenate(ang)
        return InsErrors(position_m=float(dd.mean()), attitude_deg=float(aa.mean()),
                         position_m_max=float(dd.max()), n_windows=self.w, window_s=self.window_s)


class WindowNavigation:
    """The INS test's navigation of the windows `win` (W, n) of `window_rows` in the campaign arrays `a`:
    the reference solution once, then `errors` of an output set given in pieces of rows (in `win.ravel()`
    order, any sizes): each window is navigated when its rows are in (`NavigationStream`)."""

    def __init__(self, a: dict[str, np.ndarray], win: np.ndarray, window_s: float = DEFAULT_WINDOW_S) -> None:
        self.w, self.n = win.shape
        rows = win.ravel()
        self._stream = NavigationStream(self.w, self.n, window_s)
        self._stream.reference(a["orientation"][rows], a["rate"][rows])
        self._sets = 0

    def errors(self, pieces: Iterable[np.ndarray]) -> InsErrors:
        name = f"set {self._sets}"
        self._sets += 1
        for piece in pieces:
            self._stream.add(name, piece)
        return self._stream.errors(name)


def ins_errors(a: dict[str, np.ndarray], win: np.ndarray, outputs: dict[str, np.ndarray],
               window_s: float = DEFAULT_WINDOW_S) -> dict[str, InsErrors]:
    """Navigation errors of each output set over the windows `win` (W, n) of `window_rows`; an output set
    (name -> (W * n, 6)) holds the raw or compensated outputs of the rows `win.ravel()`."""
    if win.size == 0:
        return {name: InsErrors(float("nan"), float("nan"), float("nan"), 0, window_s) for name in outputs}
    nav = WindowNavigation(a, win, window_s)  # the reference solution, once for every set
    return {name: nav.errors([values]) for name, values in outputs.items()}
