"""Records of a campaign read chunk by chunk: the same records as `segment_records` of the whole frame,
without holding the campaign's rows or a per-row label of it.

The rows arrive in chunks in campaign order (any cut: a store's blocks, slices of a frame). Segment
breaks depend on a row's neighbours (a gap is an interval much longer than the intervals either side),
so a break is decided only once the row after it is at hand: the rows from the last decided segment
start onwards are carried into the next chunk (with the two rows before them as context), and every
segment closed before that start is cut into records exactly as the whole-frame code cuts it
(`record_bounds`, `records_from_labels` on the segment's rows: the same floating-point sums, each
record's rows summed in order). The records therefore do not depend on where the chunks are cut;
the carry is bounded by the longest segment, not by the campaign.

A one-row record (averaged rows a few seconds apart) stands for the campaign's typical row interval,
the median of all row intervals: `typical_interval` is asked for it at the end, only when such a
record exists (a store's caller reads the time column again; a frame's caller has it).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
import pandas as pd

from .records import (
    Outputs,
    RecordOptions,
    Records,
    ScaledColumn,
    _breaks,
    frame_arrays,
    record_bounds,
    records_from_labels,
)

log = logging.getLogger(__name__)

_KEYS = ("t", "run", "orientation", "temp", "rate")
CONTEXT_ROWS = 2  # rows before a carried segment start that its neighbours' intervals need


def take_rows(a: dict[str, Any], rows: slice | np.ndarray, keys: tuple[str, ...] = _KEYS) -> dict[str, Any]:
    """The campaign arrays `keys` and the outputs of some rows (a slice: views; indices: copies), outputs
    kept as they are held (a store's counts stay counts)."""
    out: dict[str, Any] = {k: a[k][rows] for k in keys}
    out["y"] = Outputs([ScaledColumn(c.counts[rows], c.scale) if isinstance(c, ScaledColumn) else c[rows]
                        for c in a["y"].columns])
    return out


def join_arrays(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """The campaign arrays of consecutive parts, joined (new arrays: no part is kept alive)."""
    out: dict[str, Any] = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "y"}
    cols: list[np.ndarray | ScaledColumn] = []
    for j, first in enumerate(parts[0]["y"].columns):
        col = [p["y"].columns[j] for p in parts]
        if all(isinstance(c, ScaledColumn) and c.scale == first.scale for c in col):
            cols.append(ScaledColumn(np.concatenate([c.counts for c in col]), first.scale))
        else:
            cols.append(np.concatenate([np.asarray(c[:]) for c in col]))
    out["y"] = Outputs(cols)
    return out


def concat_records(parts: list[Records]) -> Records:
    """Records of consecutive row ranges, one after the other (no per-row labels)."""
    if not parts:
        raise ValueError("no records to join")
    fields = ("run", "orientation", "rate_dps", "temp_c", "temp_span_c", "t_start_s", "t_end_s", "n_rows",
              "row_interval_s", "mean", "sem", "reference", "step", "row_start", "row_stop")
    joined = {f: np.concatenate([getattr(p, f) for p in parts]) for f in fields}
    return Records(row_record=np.zeros(0, dtype=np.int64), **joined)


class ChunkSegmenter:
    """Feed a campaign's chunks in order (`add`), then `finish` for its records (see the module docstring)."""

    def __init__(self, options: RecordOptions | None = None) -> None:
        self.opt = options or RecordOptions()
        self._buf: dict[str, Any] | None = None  # rows from the last decided segment start on
        self._g0 = 0  # campaign position of the buffer's first row
        self._ctx: dict[str, np.ndarray] | None = None  # up to CONTEXT_ROWS rows before the buffer
        self._parts: list[Records] = []
        self.n_rows = 0
        self.max_carry = 0  # the largest carry, rows (for the log: bounded by the longest segment)

    def add(self, chunk: pd.DataFrame | dict[str, Any]) -> None:
        a = frame_arrays(chunk) if isinstance(chunk, pd.DataFrame) else chunk
        n = int(a["t"].size)
        if n == 0:
            return
        self.n_rows += n
        self._buf = a if self._buf is None else join_arrays([self._buf, a])
        self._close(final=False)

    def _close(self, final: bool) -> None:
        buf = self._buf
        assert buf is not None
        n = int(buf["t"].size)
        c = 0 if self._ctx is None else int(self._ctx["t"].size)

        def window(k: str) -> np.ndarray:
            return buf[k] if self._ctx is None else np.concatenate([self._ctx[k], buf[k]])

        if n > 1:
            brk = _breaks(window("t"), window("run"), window("orientation"), window("rate"), self.opt)
            # brk[c + j - 1]: buffer row j starts a segment; decided for j <= n - 2 (its next interval is
            # known) or, at the campaign's end, for every row (the whole frame's last row has none either).
            last = n - 1 if final else n - 2
            starts = np.concatenate([[0], np.flatnonzero(brk[c:c + last]) + 1]).astype(np.int64)
        else:
            starts = np.zeros(1, dtype=np.int64)
        end = n if final else int(starts[-1])
        if end == 0:
            self.max_carry = max(self.max_carry, n)
            return
        region = buf if end == n else take_rows(buf, slice(0, end))
        seg = starts[starts < end]
        s, e, interval = record_bounds(region, seg, self.opt, None)
        if s.size:
            labels = np.full(end, -1, dtype=np.int64)
            for label, (lo, hi) in enumerate(zip(s.tolist(), e.tolist())):
                labels[lo:hi] = label
            part = records_from_labels(region, labels, interval, with_labels=False)
            part.row_start += self._g0
            part.row_stop += self._g0
            self._parts.append(part)
        if end < n:
            lo = max(end - CONTEXT_ROWS, 0)
            self._ctx = {k: buf[k][lo:end].copy() for k in _KEYS}
            self._buf = join_arrays([take_rows(buf, slice(end, n))])  # a copy: a view keeps the chunk alive
        else:
            self._buf = None
        self._g0 += end
        self.max_carry = max(self.max_carry, n - end)

    def finish(self, typical_interval: Callable[[], float] | None = None) -> Records:
        """The records; `typical_interval()` (the median positive row interval of the whole campaign)
        is called only when a one-row record needs it (without it such records are dropped)."""
        if self._buf is not None:
            self._close(final=True)
        if not self._parts:
            return concat_records([_empty()])
        records = concat_records(self._parts)
        pending = np.isnan(records.row_interval_s)
        if pending.any():
            typ = typical_interval() if typical_interval is not None else np.nan
            records.row_interval_s[pending] = typ
            keep = ~pending | (typ >= self.opt.min_duration_s)
            if not keep.all():
                records = records.subset(keep, with_labels=False)
        log.debug("records of %d rows in chunks: %d records, largest carry %d rows", self.n_rows, len(records),
                  self.max_carry)
        return records


def _empty() -> Records:
    z = np.zeros(0)
    zi = np.zeros(0, dtype=np.int64)
    return Records(row_record=zi, run=zi, orientation=zi, rate_dps=z, temp_c=z, temp_span_c=z, t_start_s=z,
                   t_end_s=z, n_rows=z, row_interval_s=z, mean=np.zeros((0, 6)), sem=np.zeros((0, 6)),
                   reference=np.zeros((0, 6)), step=zi, row_start=zi, row_stop=zi)


def segment_chunks(chunks: Iterable[pd.DataFrame], options: RecordOptions | None = None,
                   typical_interval: Callable[[], float] | None = None) -> Records:
    """The records of a campaign given as chunks in order (equal to `segment_records` of their concatenation)."""
    seg = ChunkSegmenter(options)
    for chunk in chunks:
        seg.add(chunk)
    return seg.finish(typical_interval)


def typical_interval_of(chunks: Iterable[pd.DataFrame]) -> float:
    """`records._typical_interval` of the chunks' joined time column (the intervals across cuts included);
    holds the campaign's positive intervals at once: asked for only when a one-row record exists."""
    parts: list[np.ndarray] = []
    prev: float | None = None
    for chunk in chunks:
        t = chunk["t_s"].to_numpy(dtype=float)
        if t.size == 0:
            continue
        d = np.diff(t if prev is None else np.concatenate([[prev], t]))
        parts.append(d[d > 0])
        prev = float(t[-1])
    dt = np.concatenate(parts) if parts else np.zeros(0)
    return float(np.median(dt)) if dt.size else 1.0


def frame_chunks(frame: pd.DataFrame, max_rows: int) -> Iterable[pd.DataFrame]:
    """Slices of a frame of at most `max_rows` rows (the CSV path: a frame read whole, fitted in chunks)."""
    for lo in range(0, len(frame), max_rows):
        yield frame.iloc[lo:lo + max_rows]



