"""The evaluation (`evaluation.evaluate`) of a campaign read chunk by chunk: the same splits, draws and
scores, from the records' row ranges and passes over the rows shared by every split instead of the
whole frame.

Every split is planned first: the record splits' models are fitted on their training records (no row
needed), the random split's held-out rows counted from the generator's stream (the same doubles as one
`rng.random(n)`, replayed from its saved state in each pass), and the held-out and offset rows to score
drawn as `_limit_rows` draws them (`rng.choice` over the population's size gives the positions
`rng.choice` over the row indices gives: the same generator calls in the same order; beyond
CHOICE_MAX_POP rows, 8 M, a blocked draw in bounded memory, uniform as well but of other rows). Then
the passes over the campaign's rows (`RowSource`), cut so that no record straddles a cut
(`aligned_chunks`), serve every split at once:

1. the models' data: the random split's training records, summed chunk by chunk by
   `records_from_labels` (each record within one chunk: the same sums); `time_blocks`' offset rows
   (at most OFFSET_MAX_ROWS); PX4's first pass (`Px4Stream`: each orientation's temperature range
   and sweep check); the INS test's candidate rows, held as pieces (`ins.RowRuns`);
2. only when some orientation of some split is a sweep (a field log, not the paper campaign's
   soaks): PX4's median of the filtered outputs, then a pass for its bins; also the rare cases the
   plan could not settle (the random split's training part could not be fitted, so the later draws
   differ; INS pieces that cannot tell where a gap is): their rows then;
3. the scoring: every split's held-out rows scored as they stream past, in the batches `score`
   takes (SCORE_CHUNK rows: the same sums), and the INS windows' rows (at most MAX_WINDOWS x one
   minute per split) compensated and navigated INS_CHUNK rows at a time as they do.

What is held grows with the records, the capped draws (held-out ranks, offset rows, INS windows) and
the distinct values of the quantised outputs and times, not with the rows; the numbers are those of
`evaluate` on the whole frame, bit for bit (tests/calibration/test_evaluation_chunked.py).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from labrunner.errors import UserError
from labrunner.forked import balanced_groups, configured_processes, fork_map

from . import evaluation as _evaluation
from .chunked_records import _KEYS, concat_records, join_arrays, take_rows
from .evaluation import (
    _DESCRIPTIONS,
    INS_CHUNK,
    SPLITS,
    STATIC_RATE_DPS,
    FitModels,
    Scored,
    ScoreSums,
    SplitResult,
    _apply,
    _take,
    run_offsets,
    split_plan,
)
from .ins import NavigationStream, RowRuns, windows
from .px4_reference import Px4Stream
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


INS_KEYS = ("orientation", "temp")  # what compensating a window's row reads besides its outputs (PX4: orientation)
DRAW_CHUNK = 1 << 20  # rows of the random split's stream drawn at once when its held-out rows are counted


class _WindowRows:
    """The INS windows' campaign positions (W, n), in increasing order, held as runs of consecutive
    positions (a few per window instead of n positions: 400 windows of 50 Hz rows are 9.6 MB as int64)."""

    def __init__(self, shape: tuple[int, int], first: np.ndarray, start: np.ndarray) -> None:
        self.shape = shape
        self.size = shape[0] * shape[1]
        self.first = first  # (R,) each run's first index in the windows' rows (`win.ravel()`)
        self.start = start  # (R,) its first campaign position
        self.stop = np.append(first[1:], self.size)

    @classmethod
    def of(cls, win: np.ndarray) -> _WindowRows | None:
        """The runs of `win` (W, n) (None: no window)."""
        if win.size == 0:
            return None
        flat = win.ravel()
        step = np.diff(flat)
        assert np.all(step > 0), "the INS windows' rows are not in increasing order"
        first = np.concatenate([[0], np.flatnonzero(step != 1) + 1])
        return cls((int(win.shape[0]), int(win.shape[1])), first, flat[first])

    def below(self, g: int) -> int:
        """How many of the windows' rows lie before campaign position g."""
        r = int(np.searchsorted(self.start, g)) - 1  # the last run starting before g
        return 0 if r < 0 else min(int(self.first[r]) + g - int(self.start[r]), int(self.stop[r]))

    def positions(self, lo: int, hi: int) -> np.ndarray:
        """The campaign positions of the windows' rows lo .. hi (`win.ravel()[lo:hi]`)."""
        idx = np.arange(lo, hi)
        k = np.searchsorted(self.first, idx, side="right") - 1
        return self.start[k] + (idx - self.first[k])


class _Pick:
    """Rows picked by rank among the rows of a mask, met chunk by chunk in order (ranks None: all)."""

    def __init__(self, ranks: np.ndarray | None) -> None:
        self.ranks = ranks
        self.seen = 0

    def __call__(self, mask: np.ndarray) -> np.ndarray:
        idx = np.flatnonzero(mask)
        if self.ranks is not None:
            lo, hi = np.searchsorted(self.ranks, [self.seen, self.seen + idx.size])
            idx = idx[self.ranks[lo:hi] - self.seen]
        self.seen += int(np.count_nonzero(mask))
        return idx


class _Gather:
    """Rows picked by rank among the rows of a mask, met chunk by chunk in order (`keys` and outputs)."""

    def __init__(self, ranks: np.ndarray | None, keys: tuple[str, ...] = _KEYS) -> None:
        self.pick = _Pick(ranks)
        self.keys = keys
        self.parts: list[dict[str, Any]] = []
        self.labels: list[np.ndarray] = []

    def add(self, a: dict[str, Any], mask: np.ndarray, lab: np.ndarray) -> None:
        idx = self.pick(mask)
        if idx.size:
            self.parts.append(take_rows(a, idx, self.keys))
            self.labels.append(lab[idx])

    def arrays(self) -> tuple[dict[str, Any] | None, np.ndarray]:
        if not self.parts:
            return None, np.zeros(0, dtype=np.int64)
        return join_arrays(self.parts), np.concatenate(self.labels)


BATCH_KEYS = ("temp", "orientation", "rate", "run")  # what scoring reads of a row besides its outputs


class _Batches:
    """Held-out rows met chunk by chunk, fed to the split's `ScoreSums` in batches of exactly SCORE_CHUNK
    rows: the batches `score` takes of the same rows gathered whole, so the same sums in the same order.
    Rows wait as they are held (a store's outputs as counts) and are converted a batch at a time."""

    def __init__(self, sums: ScoreSums, size: int | None = None) -> None:
        self.sums = sums
        self.size = _evaluation.SCORE_CHUNK if size is None else size
        self.parts: list[dict[str, Any]] = []
        self.labels: list[np.ndarray] = []
        self.held = 0

    def add(self, a: dict[str, Any], idx: np.ndarray, lab: np.ndarray) -> None:
        if idx.size == 0:
            return
        self.parts.append(take_rows(a, idx, BATCH_KEYS))
        self.labels.append(lab[idx])
        self.held += int(idx.size)
        while self.held >= self.size:
            self._feed(self.size)

    def close(self, res: SplitResult) -> None:
        if self.held:
            self._feed(self.held)
        self.sums.fill(res)

    def _feed(self, m: int) -> None:
        rows = self.parts[0] if len(self.parts) == 1 else join_arrays(self.parts)
        lab = self.labels[0] if len(self.labels) == 1 else np.concatenate(self.labels)
        rest = self.held - m
        self.parts = [join_arrays([take_rows(rows, slice(m, None), BATCH_KEYS)])] if rest else []
        self.labels = [lab[m:].copy()] if rest else []
        self.held = rest
        self.sums.add(_take(rows, np.arange(m)), lab[:m])

@dataclass
class _Split:
    """One split's plan and what the passes gather for it."""

    res: SplitResult
    test_rec: np.ndarray | None  # held-out records (None: the random split, whose held-out rows are drawn)
    models: dict[str, Scored] | None = None
    fitted: bool = True  # False: the training part could not be fitted (nothing scored)
    state: dict[str, Any] | None = None  # random: the generator's state before its draw (replayed in each pass)
    after: dict[str, Any] | None = None  # random: ... and after it
    n_test: int = 0  # random: held-out rows within records
    parts: list[Records] = field(default_factory=list)  # random: training records, chunk by chunk
    test_ranks: np.ndarray | None = None
    offset_ranks: np.ndarray | None = None
    offset_rows: _Gather | None = None
    regather: bool = False  # the offset rows to gather again (drawn again after a random split failed)
    px4: Px4Stream = field(default_factory=Px4Stream)
    runs: RowRuns | None = None
    static_test: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None  # the INS rows, when pieces cannot tell
    win: _WindowRows | None = None  # the INS windows' campaign positions (None: no window)

    @property
    def random(self) -> bool:
        return self.test_rec is None

    @property
    def offsets(self) -> bool:
        """Each model's offset per run removed (time_blocks)."""
        return self.res.name == "time_blocks"

    @property
    def live(self) -> bool:
        return self.fitted and self.res.skipped is None


class _Masks:
    """Each split's held-out and training rows of the chunks of one pass (the random split's draw replayed)."""

    def __init__(self, splits: list[_Split], fraction: float) -> None:
        self.fraction = fraction
        self.replay: dict[int, np.random.Generator] = {}
        for i, s in enumerate(splits):
            if s.random:
                g = np.random.default_rng()
                assert s.state is not None
                g.bit_generator.state = s.state
                self.replay[i] = g
        self.flags = {i: (np.append(s.test_rec, False), np.append(~s.test_rec, False))
                      for i, s in enumerate(splits) if s.test_rec is not None}  # index -1 (in no record): neither

    def __call__(self, i: int, lab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if i in self.replay:
            held = self.replay[i].random(lab.size) < self.fraction
            inside = lab >= 0
            return inside & held, inside & ~held
        test, train = self.flags[i]
        return test[lab], train[lab]


_SplitMasks = list[tuple[_Split, np.ndarray, np.ndarray]]  # (split, its held-out rows, its training rows)


def _passes(source: RowSource, records: Records, n_rows: int, splits: list[_Split], fraction: float
            ) -> Iterator[tuple[int, dict[str, Any], np.ndarray, np.ndarray, _SplitMasks]]:
    """One pass: (first row's position, arrays, record labels, records there, [(split, held-out, training)])
    per chunk; every split's draw replayed in order (each must take every chunk). Checks the rows read."""
    masks = _Masks(splits, fraction)
    read = 0
    for g0, a in aligned_chunks(source, records):
        m = int(a["t"].size)
        read += m
        lab, here = _labels(records, g0, m)
        yield g0, a, lab, here, [(s, *masks(i, lab)) for i, s in enumerate(splits)]
    if read != n_rows:
        raise UserError(f"the campaign's rows changed while it was evaluated ({read:,} read, {n_rows:,} expected): "
                        "fit it again")


def _count_held(rng: np.random.Generator, records: Records, n_rows: int, fraction: float) -> int:
    """The random split's held-out rows within records: its draw (advancing `rng` as the draw of every row does)."""
    n = 0
    for lo in range(0, n_rows, DRAW_CHUNK):  # chunks cut anywhere: records' ranges clipped to them
        m = min(DRAW_CHUNK, n_rows - lo)
        held = np.concatenate([[0], np.cumsum(rng.random(m) < fraction)])
        a = np.clip(records.row_start - lo, 0, m)
        b = np.clip(records.row_stop - lo, 0, m)
        n += int((held[b] - held[a]).sum())
    return n


def _draw(splits: list[_Split], records: Records, n_rows: int, fraction: float, max_rows: int, seed: int) -> None:
    """Every split's held-out (and offset) ranks, by the generator's calls `evaluate` makes, in its order:
    the random split's stream over the rows, then its subset; a record split's offset rows, then its subset.
    A split whose training part could not be fitted draws nothing after its stream."""
    rng = np.random.default_rng(seed)
    n = records.n_rows.astype(np.int64)
    for s in splits:
        if s.random:
            if s.after is None:
                s.state = dict(rng.bit_generator.state)
                s.n_test = _count_held(rng, records, n_rows, fraction)
                s.after = dict(rng.bit_generator.state)
            else:
                rng.bit_generator.state = s.after
            if s.fitted:
                s.test_ranks = _compact(_positions(s.n_test, max_rows, rng), s.n_test)
            continue
        assert s.test_rec is not None
        if s.offsets:
            pop = int(n[~s.test_rec].sum())
            s.offset_ranks = _compact(_positions(pop, _evaluation.OFFSET_MAX_ROWS, rng), pop)
        pop = int(n[s.test_rec].sum())
        s.test_ranks = _compact(_positions(pop, max_rows, rng), pop)


def _same(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))


def _compact(ranks: np.ndarray | None, pop: int) -> np.ndarray | None:
    """Ranks among `pop` rows as int32 when every rank does (the same values in half the memory)."""
    return ranks.astype(np.int32) if ranks is not None and pop < 2 ** 31 else ranks


def evaluate_chunks(source: RowSource, n_rows: int, records: Records, steps: TemperatureSteps,
                    fit_models: FitModels, splits: tuple[str, ...] = SPLITS, holdout_fraction: float = 0.2,
                    max_rows: int = 1_000_000, seed: int = 0,
                    progress: Callable[[str], None] | None = None,
                    settle: Callable[[], object] | None = None) -> list[SplitResult]:
    """`evaluation.evaluate` over a chunked campaign of `n_rows` rows whose records carry row ranges.

    `settle` waits for work the caller runs beside the evaluation in other threads; it is called before the
    scoring pass forks its processes (a child has no threads: a wait there for the caller's thread never ends)."""
    plan: list[_Split] = []
    for name in splits:
        if progress:
            progress(f"evaluation: {name}")
        res = SplitResult(name=name, description=_DESCRIPTIONS[name])
        usable, test_rec = split_plan(name, records, steps, res)
        s = _Split(res=res, test_rec=test_rec)
        plan.append(s)
        if not usable:
            s.fitted = False
        elif test_rec is not None:  # a record split's models need its training records only
            s.models = _models(fit_models, records.subset(~test_rec, with_labels=False), res)
            s.fitted = s.models is not None
    live = [s for s in plan if s.res.skipped is None]
    _draw(live, records, n_rows, holdout_fraction, max_rows, seed)
    if not live:
        return [s.res for s in plan]
    if progress:
        progress("evaluation: training parts, PX4's temperature ranges, INS candidates")
    _models_pass(source, records, n_rows, live, holdout_fraction)
    for s in live:
        if s.random:
            s.models = _models(fit_models, concat_records(s.parts) if s.parts else
                               records.subset(np.zeros(len(records), dtype=bool), with_labels=False), s.res)
            s.fitted = s.models is not None
            s.parts = []
    if not all(s.fitted for s in live if s.random):  # the later splits' draws come earlier in the stream
        drawn = [s.offset_ranks for s in live]
        _draw(live, records, n_rows, holdout_fraction, max_rows, seed)
        for s, before in zip(live, drawn):
            if s.offsets and not _same(before, s.offset_ranks):
                s.regather = True  # the offset rows gathered were drawn by the wrong stream: again, next pass
    for s in live:
        if s.runs is not None:
            win = s.runs.window_positions()
            if win is None:
                log.info("%s: INS windows chosen from the rows themselves (a gap threshold within a run)", s.res.name)
                s.static_test = []
            else:
                s.win = _WindowRows.of(win)
            s.runs = None
    live = [s for s in live if s.fitted]
    _more_passes(source, records, n_rows, live, holdout_fraction, progress)
    if progress:
        progress("evaluation: scoring")
    if settle is not None:
        settle()
    _score_pass(source, records, n_rows, live, holdout_fraction)
    for s in live:
        if s.random:
            s.res.ins_skipped = "held-out rows are scattered: no 60 s window of contiguous held-out rows"
    return [s.res for s in plan]


def _models(fit_models: FitModels, train: Records, res: SplitResult) -> dict[str, Scored] | None:
    res.n_train_records = len(train)
    try:
        return dict(fit_models(train))
    except ValueError as exc:  # the training part alone cannot support a model
        res.skipped = f"training part cannot be fitted: {exc}"
        return None


def _models_pass(source: RowSource, records: Records, n_rows: int, live: list[_Split], fraction: float) -> None:
    """Pass 1: the random split's training records, PX4's ranges, time_blocks' offset rows, INS candidates."""
    for s in live:
        if s.offsets:
            s.offset_rows = _Gather(s.offset_ranks)
        if not s.random and s.fitted:
            s.runs = RowRuns()
    n_held = {id(s): 0 for s in live}
    for g0, a, lab, here, masks in _passes(source, records, n_rows, live, fraction):
        static = np.abs(a["rate"]) < STATIC_RATE_DPS
        for s, test, train in masks:
            if s.random:
                n_held[id(s)] += int(np.count_nonzero(test))
                if here.size:
                    local = np.where(lab >= 0, lab - here[0], -1)
                    part = records_from_labels(a, local, records.row_interval_s[here], train, with_labels=False)
                    if len(part):
                        part.row_start += g0
                        part.row_stop += g0
                        s.parts.append(part)
            elif not s.fitted:
                continue
            s.px4.add(a, train)
            if s.offset_rows is not None:
                s.offset_rows.add(a, train, lab)
            if s.runs is not None:
                sel = np.flatnonzero(test & static)
                s.runs.add(a["t"][sel], lab[sel], g0 + sel)
    for s in live:
        assert not s.random or n_held[id(s)] == s.n_test, "the random split's draw was not replayed"
        s.px4.end_pass()


def _more_passes(source: RowSource, records: Records, n_rows: int, live: list[_Split], fraction: float,
                 progress: Callable[[str], None] | None) -> None:
    """PX4's further passes (sweeps only) and what the plan could not settle: offset rows drawn again,
    INS windows that need their rows."""
    while True:
        want = [s for s in live if s.px4.needs_pass or s.regather or s.static_test is not None]
        if not want:
            break
        if progress:
            progress("evaluation: PX4's sweeps" if any(s.px4.needs_pass for s in want) else "evaluation: rows again")
        for s in want:
            if s.regather:
                s.offset_rows = _Gather(s.offset_ranks)
        for g0, a, lab, _, masks in _passes(source, records, n_rows, want, fraction):
            for s, test, train in masks:
                s.px4.add(a, train)
                if s.regather and s.offset_rows is not None:
                    s.offset_rows.add(a, train, lab)
                if s.static_test is not None:
                    sel = np.flatnonzero(test & (np.abs(a["rate"]) < STATIC_RATE_DPS))
                    s.static_test.append((g0 + sel, a["t"][sel], lab[sel]))
        for s in want:
            if s.px4.needs_pass:
                s.px4.end_pass()
            s.regather = False
            if s.static_test is not None:
                pos = np.concatenate([p[0] for p in s.static_test])
                idx = windows(np.concatenate([p[1] for p in s.static_test]),
                              np.concatenate([p[2] for p in s.static_test]))
                s.win = _WindowRows.of(pos[idx] if idx.size else idx)
                s.static_test = None


def _score_pass(source: RowSource, records: Records, n_rows: int, live: list[_Split], fraction: float) -> None:
    """The last pass: every split's held-out rows scored as they stream past, and its INS windows'
    rows compensated and navigated as they do. The splits are scored independently, so they are shared
    among the usable cores (`forked.fork_map`: each group of splits reads its own pass of the rows)."""
    groups = balanced_groups([_score_weight(s) for s in live], min(configured_processes(), len(live)))
    done = fork_map(lambda g: _score_group(source, records, n_rows, [live[i] for i in g], fraction), groups)
    for g, results in zip(groups, done):
        for i, res in zip(g, results):
            live[i].res = res


def _score_weight(s: _Split) -> float:
    """A split's share of the scoring, as measured on the paper campaign: 2.4-2.9 s a split (the models'
    compensation of batches of held-out rows, whatever their number), 3.6 s for time_blocks (its models'
    offsets per run removed)."""
    return 1.5 if s.offsets else 1.0


def _score_group(source: RowSource, records: Records, n_rows: int, live: list[_Split],
                 fraction: float) -> list[SplitResult]:
    """`_score_pass` of some splits in one pass of the rows; their results (in their order)."""
    batches: dict[int, _Batches] = {}
    picks: dict[int, _Pick] = {}
    ins: dict[int, _InsStream] = {}
    for s in live:
        assert s.models is not None
        px4 = s.px4.result()
        if px4.fits:
            s.models["px4"] = px4
        if px4.skipped:
            s.res.px4_skipped = px4.skipped_sentence(ORIENTATIONS)
        offsets = None
        if s.offset_rows is not None:
            b, _ = s.offset_rows.arrays()
            offsets = run_offsets(s.models, _take(b if b is not None else _empty_arrays(), np.arange(
                0 if b is None else b["t"].size)))
            s.offset_rows = None
        batches[id(s)] = _Batches(ScoreSums(s.models, len(records), offsets))
        picks[id(s)] = _Pick(s.test_ranks)
        s.test_ranks = None
        if s.win is not None:
            ins[id(s)] = _InsStream(s.models, s.win)
        s.win = None
    _score_chunks(source, records, n_rows, live, fraction, batches, picks, ins)
    for s in live:  # the last chunk and its masks are not held by now (the function's)
        batches.pop(id(s)).close(s.res)
        if s.random:
            continue
        if id(s) in ins:
            ins.pop(id(s)).close(s.res)
        else:
            s.res.ins_skipped = "no 60 s window of contiguous static held-out rows (records are shorter)"
    return [s.res for s in live]


def _score_chunks(source: RowSource, records: Records, n_rows: int, live: list[_Split], fraction: float,
                  batches: dict[int, _Batches], picks: dict[int, _Pick], ins: dict[int, _InsStream]) -> None:
    for g0, a, lab, _, masks in _passes(source, records, n_rows, live, fraction):
        for s, test, _ in masks:
            batches[id(s)].add(a, picks[id(s)](test), lab)
            if id(s) in ins:
                ins[id(s)].add(g0, a)


def _empty_arrays() -> dict[str, Any]:
    from .records import Outputs

    return {k: np.zeros(0, dtype=np.int64 if k in ("run", "orientation") else float) for k in _KEYS} | {
        "y": Outputs([np.zeros(0) for _ in range(6)])}


class _InsStream:
    """`evaluation.ins_test` of one split, fed by the scoring pass: its windows' rows are gathered as they
    stream past, and every INS_CHUNK of them (in `win.ravel()` order) is compensated by each model and
    navigated at once (`ins.NavigationStream`, whose reference solution takes the rows as they come): at
    most INS_CHUNK rows wait, not every window's (up to MAX_WINDOWS minutes, 1.2 M rows at 50 Hz, per
    split), and their outputs, temperatures and orientations only. The groups are those the chunked code has
    always compensated: an RBF network's outputs depend on the rows computed with them at the last bit;
    the whole-frame code compensates the same groups (`evaluation.ins_test`): its numbers, bit for bit."""

    def __init__(self, models: Mapping[str, Scored], win: _WindowRows) -> None:
        self.models: dict[str, Scored | None] = {"raw": None, **models}
        self.win = win
        self.nav = NavigationStream(*win.shape)
        self.next = 0  # the windows' rows gathered so far
        self.parts: list[dict[str, Any]] = []
        self.held = 0

    def add(self, g0: int, a: dict[str, Any]) -> None:
        """The rows of the chunk whose first row is the campaign's g0 (chunks in order)."""
        hi = self.win.below(g0 + int(a["t"].size))
        if hi == self.next:
            return
        rows = self.win.positions(self.next, hi) - g0
        self.nav.reference(a["orientation"][rows], a["rate"][rows])
        self.parts.append(take_rows(a, rows, INS_KEYS))
        self.held += hi - self.next
        self.next = hi
        while self.held >= INS_CHUNK:
            self._group(INS_CHUNK)

    def close(self, res: SplitResult) -> None:
        if self.next != self.win.size:
            raise UserError(f"{res.name}: the INS windows' rows were not all read ({self.next:,} of "
                            f"{self.win.size:,}): fit it again")
        if self.held:
            self._group(self.held)
        res.ins = {name: self.nav.errors(name) for name in self.models}

    def _group(self, m: int) -> None:
        rows = self.parts[0] if len(self.parts) == 1 else join_arrays(self.parts)
        rest = self.held - m
        self.parts = [join_arrays([take_rows(rows, slice(m, None), INS_KEYS)])] if rest else []
        self.held = rest
        idx = np.arange(m)
        sub = {k: rows[k][idx] for k in INS_KEYS} | {"y": rows["y"][idx]}
        del rows
        for name, model in self.models.items():  # one model's outputs at a time
            self.nav.add(name, _apply(model, sub, done={})[0])
