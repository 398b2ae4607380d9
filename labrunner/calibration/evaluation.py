"""Evaluation on held-out data: error before and after compensation (paper Tables 2-3).

Splits (each refits every model on its training part only):

* ``random``: a random 20 % of the rows held out, as the paper does. The held-out rows
  share their records (temperature, orientation, rate) with the training rows, so this
  measures little more than the fit itself.
* ``between_temperatures``: every other interior temperature step held out; the models
  are trained on the rest and tested between calibrated temperatures.
* ``beyond_temperatures``: the lowest and highest steps held out (extrapolation).
* ``between_rates``: every other table rate magnitude held out (gyro interpolation in
  rate). A network that only snaps readings to the reference values it was trained on
  looks perfect in ``random`` and is found out here.
* ``time_blocks``: in every run, every third block of at least an hour held out (blocks of
  max(1 h, run span / 9)), the rest trains: what a log with slow ramps and no soaks allows.
  Each power-on has its own turn-on bias, which no thermal calibration can know: every
  model's (and the raw data's) mean error over its run's training rows is removed from its
  errors on the run's held-out rows, as the power-on calibration or the estimator of the
  system it flies in would, so the scores compare the thermal part.

Every split also scores PX4's thermal calibration (`px4_reference.py`), fitted on the same
training rows, as the reference row ``px4``.

Errors are compensated minus true values. Sample statistics follow the paper (mean and
standard deviation per axis, improvement in %); record statistics (the RMS of each
held-out record's mean error) show the systematic error without the sensor noise. The
static check is the paper's: on records without rotation, |accel| - 1 g and |rate|.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .compensation import Compensated, compensate
from .ins import InsErrors, ins_errors, window_rows
from .px4_reference import Px4Reference, fit_px4
from .rbf_model import DistinctInputs, RbfModel
from .records import Records, TemperatureSteps, records_from_labels, reference_values
from .thermal_poly import PolyModel
from .triads import ORIENTATIONS, as_channel_dict

SPLITS: tuple[str, ...] = ("random", "between_temperatures", "beyond_temperatures", "between_rates", "time_blocks")
STATIC_RATE_DPS = 0.05
BLOCK_MIN_S = 3600.0  # held-out time blocks are at least this long
OFFSET_MAX_ROWS = 200_000  # training rows used for each model's per-run offset (time_blocks)

FitModels = Callable[[Records], Mapping[str, PolyModel | RbfModel]]  # training records -> {model name: model}


@dataclass
class ErrorStats:
    """Per-axis error statistics (6 channels) of one model on one held-out set."""

    mean: np.ndarray
    std: np.ndarray
    rms: np.ndarray
    n: int

    @classmethod
    def of(cls, err: np.ndarray) -> ErrorStats:
        if err.shape[0] == 0:
            nan = np.full(err.shape[1], np.nan)
            return cls(nan, nan, nan, 0)
        return cls(err.mean(axis=0), err.std(axis=0), np.sqrt(np.mean(err ** 2, axis=0)), int(err.shape[0]))

    def to_dict(self) -> dict[str, Any]:
        return {"mean": as_channel_dict(self.mean), "std": as_channel_dict(self.std),
                "rms": as_channel_dict(self.rms), "n": self.n}


@dataclass
class StaticCheck:
    """Norms on static held-out data: |accel| - 1 g and |rate| (both should be 0)."""

    accel_norm_err_mean: float
    accel_norm_err_std: float
    gyro_norm_mean: float
    gyro_norm_std: float
    record_accel_norm_err_rms: float  # from record means: no noise floor
    record_gyro_norm_rms: float
    n: int

    def to_dict(self) -> dict[str, Any]:
        return {k: (float(v) if isinstance(v, float | np.floating) else v) for k, v in self.__dict__.items()}


@dataclass
class SplitResult:
    """Held-out errors of every model for one split."""

    name: str
    description: str
    train_temps_c: list[float] = field(default_factory=list)
    test_temps_c: list[float] = field(default_factory=list)
    n_train_records: int = 0
    n_test_rows: int = 0
    samples: dict[str, ErrorStats] = field(default_factory=dict)  # model name ("raw" first) -> stats
    records: dict[str, ErrorStats] = field(default_factory=dict)
    static: dict[str, StaticCheck] = field(default_factory=dict)
    extrapolated_fraction: dict[str, float] = field(default_factory=dict)
    skipped: str | None = None
    # The paper's INS test on static held-out rows (60 s windows of one record): model -> end-of-window errors
    ins: dict[str, InsErrors] = field(default_factory=dict)
    ins_skipped: str | None = None
    px4_skipped: str | None = None  # orientations PX4's method is not applied to (their rows pass unchanged)

    def improvement(self, model: str, stat: str = "mean") -> np.ndarray:
        """Paper's improvement (%) of a model over raw: 100 (1 - |model| / |raw|)."""
        raw = np.abs(getattr(self.samples["raw"], stat))
        new = np.abs(getattr(self.samples[model], stat))
        with np.errstate(divide="ignore", invalid="ignore"):
            return 100.0 * (1.0 - new / raw)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "description": self.description}
        if self.skipped:
            out["skipped"] = self.skipped
            return out
        out.update({
            "train_temperatures_c": self.train_temps_c, "test_temperatures_c": self.test_temps_c,
            "n_train_records": self.n_train_records, "n_test_rows": self.n_test_rows,
            "samples": {k: v.to_dict() for k, v in self.samples.items()},
            "records": {k: v.to_dict() for k, v in self.records.items()},
            "improvement_pct": {k: {"mean": as_channel_dict(self.improvement(k, "mean")),
                                    "std": as_channel_dict(self.improvement(k, "std")),
                                    "rms": as_channel_dict(self.improvement(k, "rms"))}
                                for k in self.samples if k != "raw"},
            "static": {k: v.to_dict() for k, v in self.static.items()},
            "extrapolated_fraction": self.extrapolated_fraction,
            "ins": {k: v.to_dict() for k, v in self.ins.items()}, "ins_skipped": self.ins_skipped,
            "px4_skipped": self.px4_skipped,
        })
        return out


class _Moments:
    """Running count, mean, standard deviation and RMS of columns fed in chunks.

    The sums are taken about a shift (the first chunk's mean), so the variance does not lose the
    digits a raw sum of squares would when the mean is large against the spread."""

    def __init__(self, width: int) -> None:
        self.n = 0
        self.shift = np.zeros(width)
        self.s1 = np.zeros(width)
        self.s2 = np.zeros(width)
        self.sq = np.zeros(width)

    def add(self, x: np.ndarray) -> None:
        if x.shape[0] == 0:
            return
        if self.n == 0:
            self.shift = x.mean(axis=0)
        d = x - self.shift
        self.n += x.shape[0]
        # Row-major rows: the sum over rows taken as d.sum(axis=0) takes it (row after row into each column),
        # without the reduction's per-row loop over six columns (4x faster). Other layouts sum along the
        # column in another order: those keep sum.
        self.s1 += np.einsum("ij->j", d) if d.flags.c_contiguous else d.sum(axis=0)
        self.s2 += np.einsum("ij,ij->j", d, d)
        self.sq += np.einsum("ij,ij->j", x, x)

    def stats(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mean, std, rms), NaN without data."""
        if self.n == 0:
            nan = np.full(self.s1.shape, np.nan)
            return nan, nan, nan
        m1 = self.s1 / self.n
        return self.shift + m1, np.sqrt(np.maximum(self.s2 / self.n - m1 ** 2, 0.0)), np.sqrt(self.sq / self.n)


class _BatchRows:
    """What every model's sums over a batch of rows share: the rows' records, which rows are static, the
    rows per record (counted once per batch, not once per model)."""

    def __init__(self, lab: np.ndarray, static: np.ndarray, n_records: int) -> None:
        self.lab = lab
        self.static = static
        self.count = np.bincount(lab, minlength=n_records)
        self.static_lab = lab[static]
        self.static_count = np.bincount(self.static_lab, minlength=n_records)


class _Scores:
    """One model's running sums over a split's held-out rows, fed chunk by chunk: sample moments,
    per-record error sums, static norms and per-record static means, extrapolated rows."""

    def __init__(self, n_records: int) -> None:
        self.samples = _Moments(6)
        self.rec_sum = np.zeros((n_records, 6))
        self.rec_cnt = np.zeros(n_records)
        self.norms = _Moments(2)  # |accel| - 1 g, |rate| of static rows
        self.static_sum = np.zeros((n_records, 6))
        self.static_cnt = np.zeros(n_records)
        self.extrapolated = 0
        self.n = 0

    def add(self, values: np.ndarray, err: np.ndarray, extrap: np.ndarray, rows: _BatchRows) -> None:
        n_rec = self.rec_cnt.size
        lab = rows.lab
        self.n += err.shape[0]
        self.extrapolated += int(np.count_nonzero(extrap))
        self.samples.add(err)
        self.rec_cnt += rows.count
        for j in range(6):
            self.rec_sum[:, j] += np.bincount(lab, weights=err[:, j], minlength=n_rec)
        v = values[rows.static]
        if v.shape[0] == 0:
            return
        ls = rows.static_lab
        self.norms.add(np.column_stack([np.linalg.norm(v[:, :3], axis=1) - 1.0, np.linalg.norm(v[:, 3:], axis=1)]))
        self.static_cnt += rows.static_count
        for j in range(6):
            self.static_sum[:, j] += np.bincount(ls, weights=v[:, j], minlength=n_rec)

    def sample_stats(self) -> ErrorStats:
        mean, std, rms = self.samples.stats()
        return ErrorStats(mean, std, rms, self.samples.n)

    def record_stats(self) -> ErrorStats:
        seen = self.rec_cnt > 0
        return ErrorStats.of(self.rec_sum[seen] / self.rec_cnt[seen, None])

    def static_check(self) -> StaticCheck:
        if self.norms.n == 0:
            return StaticCheck(*(np.nan,) * 6, n=0)
        mean, std, _ = self.norms.stats()
        seen = self.static_cnt > 0
        mean_v = self.static_sum[seen] / self.static_cnt[seen, None]
        ra = np.linalg.norm(mean_v[:, :3], axis=1) - 1.0
        rg = np.linalg.norm(mean_v[:, 3:], axis=1)
        return StaticCheck(float(mean[0]), float(std[0]), float(mean[1]), float(std[1]),
                           float(np.sqrt(np.mean(ra ** 2))), float(np.sqrt(np.mean(rg ** 2))), n=self.norms.n)


Scored = PolyModel | RbfModel | Px4Reference
# The INS windows' rows compensated at once, here and in the chunked evaluation (an RBF network's float32
# outputs depend on the rows computed with them at the last bit): ~3 MB temporaries per model.
INS_CHUNK = 1 << 16
# Held-out rows scored per batch: every model's temporaries ~3 MB (the paper fit's two processes peaked at
# 630 MB PSS with 2^18, 425 MB with 2^16, in the same time).
SCORE_CHUNK = 1 << 16


def _take(a: dict[str, Any], rows: np.ndarray) -> dict[str, np.ndarray]:
    """The campaign arrays of the given rows (a mask or indices), taken once for every model scored."""
    idx = np.flatnonzero(rows) if rows.dtype == bool else rows
    return {k: a[k][idx] for k in ("y", "temp", "orientation", "rate", "run")}


def _apply(model: Scored | None, a: dict[str, Any], rows: np.ndarray | None = None,
           done: dict[int, Compensated] | None = None,
           distinct: DistinctInputs | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Compensated outputs of the given rows (all of `a`'s: None) and their extrapolation flags (model
    None: the raw data). `done` keeps the polynomials' compensations of these rows (by model id): the
    hybrid network starts from its base polynomial's, which is scored itself. `distinct`: the distinct
    network inputs of `a`'s rows, shared by the networks scored on them. Callers must not modify the
    arrays returned."""
    if rows is not None:
        a = _take(a, rows)
    y, temp = a["y"], a["temp"]
    if model is None:
        return y, np.zeros(y.shape[0], dtype=bool)
    if isinstance(model, Px4Reference):
        return model.compensate_rows(y, temp, a["orientation"]), np.zeros(y.shape[0], dtype=bool)
    done = {} if done is None else done
    if isinstance(model, PolyModel):
        if id(model) not in done:
            done[id(model)] = compensate(model, y, temp)
        comp = done[id(model)]
    else:
        base = done.get(id(model.base)) if model.base is not None else None
        if model.base is not None and base is None:
            base = done[id(model.base)] = compensate(model.base, y, temp)
        comp = model.compensate(y, temp, base=base, distinct=distinct)
    return comp.values, comp.extrapolated


def _run_offsets(model: Scored | None, sub: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Runs (R,) and the mean error (R, 6) of a model on the training rows `sub` (`_take`) of each run:
    its offset at that power-on."""
    values, _ = _apply(model, sub)
    err = values - reference_values(sub["orientation"], sub["rate"])
    runs, inv = np.unique(sub["run"], return_inverse=True)
    cnt = np.bincount(inv, minlength=runs.size).astype(float)
    sums = np.column_stack([np.bincount(inv, weights=err[:, j], minlength=runs.size) for j in range(6)])
    return runs, sums / cnt[:, None]


def _remove_offsets(err: np.ndarray, run: np.ndarray, offsets: tuple[np.ndarray, np.ndarray]) -> None:
    """Subtract each row's run offset (rows of runs without one keep their error)."""
    runs, off = offsets
    if runs.size == 0:
        return
    pos = np.minimum(np.searchsorted(runs, run), runs.size - 1)
    has = runs[pos] == run
    if has.all():  # the usual case: no mask to gather the rows through and scatter them back (the same values)
        err -= off[pos]
    else:
        err[has] -= off[pos[has]]


def run_offsets(models: Mapping[str, Scored], sub: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Raw data's and every model's offset per run over the training rows `sub` (`_take`)."""
    scored: dict[str, Scored | None] = {"raw": None, **models}
    return {name: _run_offsets(model, sub) for name, model in scored.items()}


class ScoreSums:
    """Raw data's and every model's running sums over a split's held-out rows, fed a batch of rows at a
    time (`add`, the rows `_take`n and their records): `score` feeds its rows SCORE_CHUNK at a time, and
    the chunked evaluation feeds the same batches as the rows stream past (the same sums, bit for bit).
    `offsets` (`run_offsets`): each model's offset per run, removed from its errors in that run."""

    def __init__(self, models: Mapping[str, Scored], n_records: int,
                 offsets: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None) -> None:
        self.scored: dict[str, Scored | None] = {"raw": None, **models}
        self.offsets = dict(offsets or {})
        self.sums = {name: _Scores(n_records) for name in self.scored}
        self.n_records = n_records
        self.n = 0

    def add(self, sub: dict[str, np.ndarray], lab: np.ndarray) -> None:
        self.n += int(lab.size)
        # the outputs as float arrays once, not once per model (the same values)
        sub = sub | {"y": np.asarray(sub["y"], dtype=float), "temp": np.asarray(sub["temp"], dtype=float)}
        ref = reference_values(sub["orientation"], sub["rate"])
        rows = _BatchRows(lab, np.abs(sub["rate"]) < STATIC_RATE_DPS, self.n_records)
        done: dict[int, Compensated] = {}
        distinct = DistinctInputs(sub["y"], sub["temp"])  # the networks' distinct inputs, found once
        for name, model in self.scored.items():
            values, extrap = _apply(model, sub, done=done, distinct=distinct)
            err = values - ref
            if name in self.offsets:
                _remove_offsets(err, sub["run"], self.offsets[name])
            self.sums[name].add(values, err, extrap, rows)

    def fill(self, result: SplitResult) -> None:
        result.n_test_rows = self.n
        for name, acc in self.sums.items():
            if name != "raw":
                result.extrapolated_fraction[name] = acc.extrapolated / acc.n if acc.n else 0.0
            result.samples[name] = acc.sample_stats()
            result.records[name] = acc.record_stats()
            result.static[name] = acc.static_check()


def score(models: Mapping[str, Scored], a: dict[str, np.ndarray], rows: np.ndarray, labels: np.ndarray,
          result: SplitResult, offset_rows: np.ndarray | None = None, chunk: int | None = None) -> None:
    """Fill `result` with the errors of raw data and every model on the given rows. With `offset_rows`
    (training rows), each model's mean error per run over them is removed from its errors in that run.

    The rows are scored `chunk` (default SCORE_CHUNK) at a time into running sums (no held-out error array
    is kept)."""
    chunk = SCORE_CHUNK if chunk is None else chunk
    idx = np.flatnonzero(rows) if rows.dtype == bool else np.asarray(rows, dtype=np.int64)
    offsets = run_offsets(models, _take(a, offset_rows)) if offset_rows is not None else None
    n_rec = int(labels.max()) + 1 if labels.size else 0
    sums = ScoreSums(models, n_rec, offsets)
    for lo in range(0, idx.size, chunk):
        part = idx[lo:lo + chunk]
        sums.add(_take(a, part), labels[part])
    sums.fill(result)


def _draw(rng: np.random.Generator, n: int, fraction: float, chunk: int = 1 << 20) -> np.ndarray:
    """(n,) bool: uniform draws below `fraction`, in chunks (the generator's stream is the same as one
    `rng.random(n)`: the same rows, without n doubles at once)."""
    out = np.empty(n, dtype=bool)
    for lo in range(0, n, chunk):
        hi = min(lo + chunk, n)
        out[lo:hi] = rng.random(hi - lo) < fraction
    return out


def _limit_rows(rows: np.ndarray, max_rows: int, rng: np.random.Generator) -> np.ndarray:
    idx = np.flatnonzero(rows)
    if idx.size > max_rows:
        idx = np.sort(rng.choice(idx, size=max_rows, replace=False))
    out = np.zeros_like(rows)
    out[idx] = True
    return out


def rate_levels(records: Records, tol: float = 0.5) -> np.ndarray:
    """Distinct nonzero table rate magnitudes (clustered within tol), ascending."""
    mags = np.sort(np.abs(records.rate_dps[np.abs(records.rate_dps) > STATIC_RATE_DPS]))
    if mags.size == 0:
        return mags
    new = np.concatenate(([True], np.diff(mags) > tol))
    groups = np.cumsum(new) - 1
    return np.array([mags[groups == g].mean() for g in range(int(groups[-1]) + 1)])


def split_plan(name: str, records: Records, steps: TemperatureSteps,
               res: SplitResult) -> tuple[bool, np.ndarray | None]:
    """What split `name` holds out: (usable, held-out records as a mask over `records`, or None for the
    random split, whose held-out rows are drawn). Fills `res`'s temperatures and description, or says in
    `res.skipped` why the data cannot support the split (usable False). One plan for `evaluate` and
    `evaluation_chunked.evaluate_chunks`."""
    order = np.argsort(steps.temp_c)
    all_temps = [round(float(t), 2) for t in steps.temp_c[order]]
    if name == "random":
        res.train_temps_c = res.test_temps_c = all_temps
        return True, None
    if name in ("between_temperatures", "beyond_temperatures"):
        k = len(steps)
        if name == "between_temperatures":
            held = order[1:-1:2] if k >= 3 else np.zeros(0, dtype=np.int64)
            need = "at least 3 temperature steps"
        else:
            held = order[[0, -1]] if k >= 4 else np.zeros(0, dtype=np.int64)
            need = "at least 4 temperature steps"
        if held.size == 0:
            res.skipped = f"needs {need}; the data has {k}"
            return False, None
        res.train_temps_c = [round(float(t), 2) for t in np.sort(steps.temp_c[np.setdiff1d(order, held)])]
        res.test_temps_c = [round(float(t), 2) for t in np.sort(steps.temp_c[held])]
        return True, np.isin(records.step, held)
    if name == "time_blocks":
        blocks, why = time_blocks(records)
        if blocks is None:
            res.skipped = why
            return False, None
        res.train_temps_c = res.test_temps_c = all_temps
        res.description += f" ({why})"
        return True, blocks
    if name == "between_rates":
        levels = rate_levels(records)
        if levels.size < 3:
            res.skipped = f"needs at least 3 distinct table rate magnitudes; the data has {levels.size}"
            return False, None
        held_levels = levels[1:-1:2]
        mag = np.abs(records.rate_dps)
        res.train_temps_c = res.test_temps_c = all_temps
        res.description += f" (held out: {', '.join(f'{v:g}' for v in np.round(held_levels, 3))} deg/s)"
        return True, np.any(np.abs(mag[:, None] - held_levels[None, :]) <= 0.5, axis=1)
    raise ValueError(f"unknown evaluation split {name!r}; expected one of {', '.join(SPLITS)}")


def evaluate(a: dict[str, np.ndarray], records: Records, steps: TemperatureSteps, fit_models: FitModels,
             splits: tuple[str, ...] = SPLITS, holdout_fraction: float = 0.2, max_rows: int = 1_000_000,
             seed: int = 0, progress: Callable[[str], None] | None = None) -> list[SplitResult]:
    """Refit on each split's training part and score the held-out part."""
    rng = np.random.default_rng(seed)
    labels = records.row_record
    in_record = labels >= 0
    results: list[SplitResult] = []
    for name in splits:
        if progress:
            progress(f"evaluation: {name}")
        res = SplitResult(name=name, description=_DESCRIPTIONS[name])
        usable, test_rec = split_plan(name, records, steps, res)
        if not usable:
            results.append(res)
            continue
        if test_rec is None:  # rows drawn at random
            test_rows = in_record & _draw(rng, labels.size, holdout_fraction)
            train_rec = records_from_labels(a, labels, records.row_interval_s, in_record & ~test_rows,
                                            with_labels=False)
        else:
            train_rec = records.subset(~test_rec, with_labels=False)
            test_rows = in_record & test_rec[np.maximum(labels, 0)]
        res.n_train_records = len(train_rec)
        try:
            models: dict[str, Scored] = dict(fit_models(train_rec))
        except ValueError as exc:  # the training part alone cannot support a model
            res.skipped = f"training part cannot be fitted: {exc}"
            results.append(res)
            continue
        train_rows = in_record & ~test_rows
        px4 = fit_px4(a, train_rows)
        if px4.fits:
            models["px4"] = px4
        if px4.skipped:
            res.px4_skipped = px4.skipped_sentence(ORIENTATIONS)
        offsets = _limit_rows(train_rows, OFFSET_MAX_ROWS, rng) if name == "time_blocks" else None
        score(models, a, _limit_rows(test_rows, max_rows, rng), labels, res, offsets)
        if name == "random":
            res.ins_skipped = "held-out rows are scattered: no 60 s window of contiguous held-out rows"
        else:
            ins_test(models, a, test_rows, labels, res)
        results.append(res)
    return results


def ins_test(models: Mapping[str, Scored], a: dict[str, np.ndarray], rows: np.ndarray, labels: np.ndarray,
             result: SplitResult) -> None:
    """The paper's INS test (Sec. V.C) on the static held-out rows: navigation errors after 60 s windows."""
    win = window_rows(a, rows & (np.abs(a["rate"]) < STATIC_RATE_DPS), labels)
    if win.size == 0:
        result.ins_skipped = "no 60 s window of contiguous static held-out rows (records are shorter)"
        return
    rows_w = win.ravel()
    scored: dict[str, Scored | None] = {"raw": None, **models}
    outputs: dict[str, list[np.ndarray]] = {name: [] for name in scored}
    for lo in range(0, rows_w.size, INS_CHUNK):  # the groups the chunked evaluation compensates
        sub = _take(a, rows_w[lo:lo + INS_CHUNK])
        done: dict[int, Compensated] = {}
        for name, model in scored.items():
            outputs[name].append(_apply(model, sub, done=done)[0])
    result.ins = ins_errors(a, win, {name: np.concatenate(parts) for name, parts in outputs.items()})


def time_blocks(records: Records) -> tuple[np.ndarray | None, str]:
    """Records held out by the `time_blocks` split (by their middle time) and a description; None and
    why when no run is long enough for three blocks of BLOCK_MIN_S."""
    held = np.zeros(len(records), dtype=bool)
    mid = 0.5 * (records.t_start_s + records.t_end_s)
    lengths = []
    longest = 0.0
    for r in np.unique(records.run):
        sel = records.run == r
        t0, t1 = float(records.t_start_s[sel].min()), float(records.t_end_s[sel].max())
        recorded = float(records.duration_s[sel].sum())
        longest = max(longest, recorded)
        if t1 - t0 < 3 * BLOCK_MIN_S or recorded < 3 * BLOCK_MIN_S:
            continue
        length = max(BLOCK_MIN_S, (t1 - t0) / 9)
        lengths.append(length)
        held[sel] = (np.floor((mid[sel] - t0) / length).astype(np.int64) % 3) == 1
    if not held.any() or held.all():
        return None, (f"needs a run with at least {3 * BLOCK_MIN_S / 3600:g} h of records (three blocks of "
                      f"{BLOCK_MIN_S / 3600:g} h); the longest has {longest / 3600:.2f} h")
    return held, (f"blocks of {min(lengths) / 3600:.2f} .. {max(lengths) / 3600:.2f} h held out in "
                  f"{len(lengths)} run(s)")


_DESCRIPTIONS = {
    "random": "random 20 % of the rows held out (the paper's validation)",
    "between_temperatures": "every other interior temperature step held out (interpolation in temperature)",
    "beyond_temperatures": "lowest and highest temperature steps held out (extrapolation in temperature)",
    "between_rates": "every other table rate magnitude held out (interpolation in rate)",
    "time_blocks": "every third time block of at least 1 h held out in each run, each model's offset per run from "
                   "the run's training rows removed",
}
