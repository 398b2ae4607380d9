"""The evaluation (`evaluation.evaluate`) of a campaign read chunk by chunk: the same splits, draws and
scores, from the records' row ranges and passes over the rows instead of the whole frame.

Each split passes over the campaign's rows (`RowSource`: a fresh pass of chunks in order) cut so that
no record straddles a cut (`aligned_chunks`), and keeps only what its scores need:

* ``random``: the held-out draw is the generator's stream over the rows in order, the same doubles
  as one `rng.random(n)` (replayed from the generator's saved state in the second pass); the training
  records are summed chunk by chunk by `records_from_labels` (each record within one chunk: the same
  sums);
* the held-out rows scored are drawn as `_limit_rows` draws them (`rng.choice` over the population's
  size gives the positions `rng.choice` over the row indices gives: the same generator calls in the
  same order), and only those rows (at most `max_rows`) are gathered; beyond CHOICE_MAX_POP rows
  (8 M: 2.3x the paper campaign's largest held-out part) a blocked draw in bounded memory, uniform
  as well but of other rows;
* PX4's reference is fitted on the static training rows, gathered (their outputs as the store's
  counts): PX4's median filter and sweep run over each orientation's whole static log;
* the INS test takes the times and records of the static held-out rows to choose its windows
  (`ins.windows`), then gathers the windows' rows (at most MAX_WINDOWS x one minute).

What is held per row is therefore the static rows of a split (5 % of the paper campaign's rows), not
the campaign; the numbers are those of `evaluate` on the whole frame, bit for bit
(tests/calibration/test_evaluation_chunked.py).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any

import numpy as np
import pandas as pd

from labrunner.errors import UserError

from . import evaluation as _evaluation
from .chunked_records import _KEYS, concat_records, join_arrays, take_rows
from .evaluation import (
    _DESCRIPTIONS,
    SPLITS,
    STATIC_RATE_DPS,
    FitModels,
    Scored,
    SplitResult,
    _apply,
    _take,
    score,
    split_plan,
)
from .ins import ins_errors, windows
from .px4_reference import fit_px4
from .records import Records, TemperatureSteps, frame_arrays, records_from_labels
from .triads import ORIENTATIONS

log = logging.getLogger(__name__)

RowSource = Callable[[], Iterable[pd.DataFrame]]  # a fresh pass over the campaign's chunks, in row order


def aligned_chunks(source: RowSource, records: Records) -> Iterator[tuple[int, dict[str, Any]]]:
    """(first row's campaign position, campaign arrays) of the source's rows, cut only where no record
    is open (a record's rows always in one piece)."""
    starts, stops = records.row_start, records.row_stop
    buf: dict[str, Any] | None = None
    g0 = 0
    for chunk in source():
        a = frame_arrays(chunk)
        if a["t"].size == 0:
            continue
        buf = a if buf is None else join_arrays([buf, a])
        end = g0 + int(buf["t"].size)
        k = int(np.searchsorted(starts, end, side="left")) - 1  # the last record starting before `end`
        cut = end if k < 0 or stops[k] <= end else int(starts[k])
        if cut <= g0:
            continue
        m = cut - g0
        yield g0, (buf if m == buf["t"].size else take_rows(buf, slice(0, m)))
        buf = None if m == buf["t"].size else join_arrays([take_rows(buf, slice(m, None))])
        g0 = cut
    if buf is not None:
        yield g0, buf


def _labels(records: Records, g0: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """(m,) the record index of rows g0 .. g0 + m (-1 outside records) and the records there."""
    lo = int(np.searchsorted(records.row_stop, g0, side="right"))
    hi = int(np.searchsorted(records.row_start, g0 + m, side="left"))
    lab = np.full(m, -1, dtype=np.int64)
    for r in range(lo, hi):
        lab[int(records.row_start[r]) - g0:int(records.row_stop[r]) - g0] = r
    return lab, np.arange(lo, hi)


# Above this many rows, `rng.choice(pop, size)` would shuffle an (pop,) int64 array (numpy's tail shuffle,
# used whenever size > pop / 50): 8 bytes per held-out row. Up to it (every split of the paper campaign,
# 2.4-3.5 M) the draw is `_limit_rows`'s; beyond it, `_blocked_choice` draws an equally uniform subset in
# blocks: other rows than the whole-frame code would draw, in bounded memory.
CHOICE_MAX_POP = 1 << 23
CHOICE_BLOCK = 1 << 21


def _positions(pop: int, max_rows: int, rng: np.random.Generator) -> np.ndarray | None:
    """`evaluation._limit_rows` as ranks among the population's rows (None: all of them)."""
    if pop <= max_rows:
        return None
    if pop <= CHOICE_MAX_POP:
        return np.sort(rng.choice(pop, size=max_rows, replace=False))
    return _blocked_choice(pop, max_rows, rng)


def _blocked_choice(pop: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted `size` distinct ranks of `pop`, uniform over the subsets of that size: how many fall in each
    block of CHOICE_BLOCK ranks is one multivariate hypergeometric draw, then a choice within each block."""
    blocks = np.full(-(-pop // CHOICE_BLOCK), CHOICE_BLOCK, dtype=np.int64)
    blocks[-1] = pop - CHOICE_BLOCK * (blocks.size - 1)
    counts = rng.multivariate_hypergeometric(blocks, size, method="marginals")
    parts = [b * CHOICE_BLOCK + np.sort(rng.choice(int(blocks[b]), size=int(k), replace=False))
             for b, k in enumerate(counts.tolist()) if k]
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)


INS_CHUNK = 1 << 19  # INS rows compensated at once
PX4_KEYS = ("orientation", "temp", "rate")  # what fit_px4 reads of a row besides its outputs


class _Gather:
    """Rows picked by rank among the rows of a mask, met chunk by chunk in order (`keys` and outputs)."""

    def __init__(self, ranks: np.ndarray | None, keys: tuple[str, ...] = _KEYS) -> None:
        self.ranks = ranks
        self.keys = keys
        self.seen = 0
        self.parts: list[dict[str, Any]] = []
        self.labels: list[np.ndarray] = []

    def add(self, a: dict[str, Any], mask: np.ndarray, lab: np.ndarray) -> None:
        idx = np.flatnonzero(mask)
        if self.ranks is not None:
            lo, hi = np.searchsorted(self.ranks, [self.seen, self.seen + idx.size])
            self.seen += idx.size
            idx = idx[self.ranks[lo:hi] - (self.seen - idx.size)]
        if idx.size:
            self.parts.append(take_rows(a, idx, self.keys))
            self.labels.append(lab[idx])

    def arrays(self) -> tuple[dict[str, Any] | None, np.ndarray]:
        if not self.parts:
            return None, np.zeros(0, dtype=np.int64)
        return join_arrays(self.parts), np.concatenate(self.labels)


def evaluate_chunks(source: RowSource, n_rows: int, records: Records, steps: TemperatureSteps,
                    fit_models: FitModels, splits: tuple[str, ...] = SPLITS, holdout_fraction: float = 0.2,
                    max_rows: int = 1_000_000, seed: int = 0,
                    progress: Callable[[str], None] | None = None) -> list[SplitResult]:
    """`evaluation.evaluate` over a chunked campaign of `n_rows` rows whose records carry row ranges."""
    rng = np.random.default_rng(seed)
    results: list[SplitResult] = []
    for name in splits:
        if progress:
            progress(f"evaluation: {name}")
        res = SplitResult(name=name, description=_DESCRIPTIONS[name])
        usable, test_rec = split_plan(name, records, steps, res)
        if not usable:
            results.append(res)
            continue
        if test_rec is None:
            _random_split(source, n_rows, records, fit_models, holdout_fraction, max_rows, rng, res)
        else:
            _record_split(source, records, test_rec, fit_models, name == "time_blocks", max_rows, rng, res)
        results.append(res)
    return results


def _models(fit_models: FitModels, train: Records, res: SplitResult) -> dict[str, Scored] | None:
    res.n_train_records = len(train)
    try:
        return dict(fit_models(train))
    except ValueError as exc:  # the training part alone cannot support a model
        res.skipped = f"training part cannot be fitted: {exc}"
        return None


def _add_px4(models: dict[str, Scored], static_train: _Gather, res: SplitResult) -> None:
    a, _ = static_train.arrays()
    if a is None:  # no static training rows: fit_px4 of an empty selection
        a = {k: np.zeros(0) for k in ("rate", "temp")} | {"orientation": np.zeros(0, dtype=np.int8)}
    px4 = fit_px4(a, np.ones(a["rate"].size, dtype=bool))
    if px4.fits:
        models["px4"] = px4
    if px4.skipped:
        res.px4_skipped = px4.skipped_sentence(ORIENTATIONS)


def _random_split(source: RowSource, n_rows: int, records: Records, fit_models: FitModels, fraction: float,
                  max_rows: int, rng: np.random.Generator, res: SplitResult) -> None:
    state = rng.bit_generator.state  # the draw replayed in the second pass
    parts: list[Records] = []
    static_train = _Gather(None, PX4_KEYS)
    n_test = 0
    drawn = 0
    for g0, a in aligned_chunks(source, records):
        m = int(a["t"].size)
        held = rng.random(m) < fraction
        drawn += m
        lab, here = _labels(records, g0, m)
        test = (lab >= 0) & held
        train = (lab >= 0) & ~held
        n_test += int(np.count_nonzero(test))
        if here.size:
            local = np.where(lab >= 0, lab - (here[0] if here.size else 0), -1)
            part = records_from_labels(a, local, records.row_interval_s[here], train, with_labels=False)
            if len(part):
                part.row_start += g0
                part.row_stop += g0
                parts.append(part)
        static_train.add(a, train & (np.abs(a["rate"]) < STATIC_RATE_DPS), lab)
    if drawn != n_rows:
        raise UserError(f"the campaign's rows changed while it was evaluated ({drawn:,} read, {n_rows:,} expected): "
                        "fit it again")
    train_rec = concat_records(parts) if parts else records.subset(np.zeros(len(records), dtype=bool),
                                                                    with_labels=False)
    models = _models(fit_models, train_rec, res)
    if models is None:
        return
    _add_px4(models, static_train, res)
    test_rows = _Gather(_positions(n_test, max_rows, rng))
    replay = np.random.default_rng()
    replay.bit_generator.state = state
    for g0, a in aligned_chunks(source, records):
        m = int(a["t"].size)
        held = replay.random(m) < fraction
        lab, _ = _labels(records, g0, m)
        test_rows.add(a, (lab >= 0) & held, lab)
    _score(models, test_rows, None, res)
    res.ins_skipped = "held-out rows are scattered: no 60 s window of contiguous held-out rows"


def _record_split(source: RowSource, records: Records, test_rec: np.ndarray, fit_models: FitModels,
                  offsets: bool, max_rows: int, rng: np.random.Generator, res: SplitResult) -> None:
    models = _models(fit_models, records.subset(~test_rec, with_labels=False), res)
    if models is None:
        return
    n = records.n_rows.astype(np.int64)
    offset_rows = _Gather(_positions(int(n[~test_rec].sum()), _evaluation.OFFSET_MAX_ROWS, rng)) if offsets else None
    test_rows = _Gather(_positions(int(n[test_rec].sum()), max_rows, rng))
    static_train = _Gather(None, PX4_KEYS)
    static_test: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # campaign position, t, record
    flag = np.append(test_rec, False)  # index -1 (rows in no record): neither part
    train_flag = np.append(~test_rec, False)
    for g0, a in aligned_chunks(source, records):
        m = int(a["t"].size)
        lab, _ = _labels(records, g0, m)
        test, train = flag[lab], train_flag[lab]
        static = np.abs(a["rate"]) < STATIC_RATE_DPS
        static_train.add(a, train & static, lab)
        if offset_rows is not None:
            offset_rows.add(a, train, lab)
        test_rows.add(a, test, lab)
        sel = np.flatnonzero(test & static)
        static_test.append((g0 + sel, a["t"][sel], lab[sel]))
    _add_px4(models, static_train, res)
    _score(models, test_rows, offset_rows, res)
    pos = np.concatenate([p[0] for p in static_test]) if static_test else np.zeros(0, dtype=np.int64)
    t = np.concatenate([p[1] for p in static_test]) if static_test else np.zeros(0)
    lab_s = np.concatenate([p[2] for p in static_test]) if static_test else np.zeros(0, dtype=np.int64)
    _ins(models, source, records, pos, t, lab_s, res)


def _score(models: Mapping[str, Scored], test_rows: _Gather, offset_rows: _Gather | None, res: SplitResult) -> None:
    a, labels = test_rows.arrays()
    n_test = int(labels.size)
    if offset_rows is not None:
        b, lab_b = offset_rows.arrays()
        if b is not None:
            a = b if a is None else join_arrays([a, b])
            labels = np.concatenate([labels, lab_b])
    if a is None:
        a = _empty_arrays()
    off = np.arange(n_test, labels.size) if offset_rows is not None else None
    score(models, a, np.arange(n_test), labels, res, off)


def _empty_arrays() -> dict[str, Any]:
    from .records import Outputs

    return {k: np.zeros(0, dtype=np.int64 if k in ("run", "orientation") else float) for k in _KEYS} | {
        "y": Outputs([np.zeros(0) for _ in range(6)])}


def _ins(models: Mapping[str, Scored], source: RowSource, records: Records, pos: np.ndarray, t: np.ndarray,
         lab: np.ndarray, res: SplitResult) -> None:
    """`evaluation.ins_test` from the static held-out rows' positions, times and records."""
    idx = windows(t, lab)
    if idx.size == 0:
        res.ins_skipped = "no 60 s window of contiguous static held-out rows (records are shorter)"
        return
    win = pos[idx]
    want = np.unique(win.ravel())
    parts: list[dict[str, Any]] = []
    for g0, a in aligned_chunks(source, records):
        m = int(a["t"].size)
        lo, hi = np.searchsorted(want, [g0, g0 + m])
        if hi > lo:
            parts.append(take_rows(a, want[lo:hi] - g0))
    rows_a = join_arrays(parts)
    del parts
    local = np.searchsorted(want, win)
    flat = local.ravel()
    n = int(flat.size)
    # One model's outputs at a time, computed INS_CHUNK rows at a time: up to MAX_WINDOWS minutes of rows
    # (1.2 M at 50 Hz) would otherwise be compensated at once for every model. Each model's errors are its
    # own; compensation is row by row, so up to INS_CHUNK rows (the paper campaign: 288 000) the numbers
    # are the whole-frame code's bit for bit.
    res.ins = {}
    for name, model in {"raw": None, **models}.items():
        values = np.concatenate([
            _apply(model, _take(rows_a, flat[lo:lo + INS_CHUNK]), done={})[0]
            for lo in range(0, n, INS_CHUNK)])
        res.ins.update(ins_errors(rows_a, local, {name: values}))
        del values
