"""Six RBF networks that compensate a whole IMU (paper Sec. IV-D), and two improvements.

Variants (``RbfModel.variant``):

* ``paper``  one network per sensor axis, inputs (measured value of that axis, T),
  output dU = true - measured (paper Fig. 1 and Eq. 11).
* ``triad``  one network per axis whose inputs are the whole triad's measured values and
  T, so cross-axis (misalignment) terms are visible to it; the per-axis network cannot
  tell a misaligned reading on a resting axis from a bias.
* ``hybrid`` the polynomial model first, then per-axis networks of the temperature alone
  trained on what the polynomial leaves: the polynomial carries the physics (scale,
  misalignment, smooth thermal drift) and the network the non-polynomial remainder of the
  bias, bias(T). Its input is no raw output, so the compensated output stays linear in the
  sensor's output with the fitted scale and misalignment: a real motion passes with the
  fitted gain (`gain.py` measures it). The ``paper`` and ``triad`` networks see the raw
  outputs and can learn a lookup of the calibration's reference levels instead; their
  measured gain is reported and they are not exported when it departs from the fitted scale.

Networks train on record means weighted by duration (see `rbf.py`), never on raw samples.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from .compensation import Compensated, compensate_poly
from .malloc_tuning import tuned_malloc
from .rbf import DEFAULT_WIDTHS, RbfNetwork, normalisation, train_rbf
from .records import Records
from .thermal_poly import PolyModel
from .triads import CHANNELS

VARIANTS: tuple[str, ...] = ("paper", "triad", "hybrid")


@dataclass(frozen=True)
class RbfOptions:
    """Training settings of the networks."""

    widths: tuple[float, ...] = DEFAULT_WIDTHS
    max_centres: int = 40
    max_candidates: int = 250
    patience: int = 6
    input_margin: float = 0.02  # inputs beyond the training range by more than this fraction are flagged
    # Floor of the temperature width (deg C) for the improved variants; None: the median spacing
    # of the calibration temperatures. The paper variant keeps one width for all inputs.
    min_temp_width_c: float | None = None


@dataclass
class RbfModel:
    """Six networks (accel x y z, gyro x y z) and what they need at compensation time."""

    variant: str
    networks: list[RbfNetwork]
    t_min_c: float
    t_max_c: float
    base: PolyModel | None = None  # hybrid only
    input_margin: float = 0.02
    notes: list[str] = field(default_factory=list)

    def inputs(self, y: np.ndarray, temp_c: np.ndarray, channel: int) -> np.ndarray:
        """(N, d) network inputs of one channel from outputs y (N, 6) and temperature."""
        return network_inputs(self.variant, y, temp_c, channel)

    def compensate(self, y: np.ndarray, temp_c: np.ndarray, base: Compensated | None = None,
                   distinct: DistinctInputs | None = None) -> Compensated:
        """Compensated outputs of y (N, 6) at temperatures (N,). `base`: the base polynomial's compensation
        of the same rows when the caller has it already (hybrid only; not modified). `distinct`: these
        rows' distinct inputs, shared by the models compensating them (each column factorised once)."""
        y = np.asarray(y, dtype=float)
        temp_c = np.asarray(temp_c, dtype=float)
        if self.base is not None:
            if base is None:
                base = compensate_poly(self.base, y, temp_c)
            out, extrap = base.values.copy(), base.extrapolated.copy()
        else:
            out = y.copy()
            extrap = (temp_c < self.t_min_c) | (temp_c > self.t_max_c)
        shared = distinct if distinct is not None and distinct.of(y, temp_c) else None
        for lo in range(0, y.shape[0], DISTINCT_CHUNK):
            rows = slice(lo, lo + DISTINCT_CHUNK)
            found = shared.chunk(lo) if shared is not None else _Distinct.of(y[rows], temp_c[rows])
            self._add_networks(y[rows], temp_c[rows], out[rows], extrap[rows], found)
        return Compensated(values=out, extrapolated=extrap)

    def _add_networks(self, y: np.ndarray, temp_c: np.ndarray, out: np.ndarray, extrap: np.ndarray,
                      distinct: _Distinct) -> None:
        """Add the networks' corrections to `out` and their extrapolation flags to `extrap` (in place)."""
        columns = distinct.columns
        inputs: dict[tuple[int, ...], np.ndarray] = {}  # a triad's three networks share theirs
        for k, net in enumerate(self.networks):
            used = input_columns(self.variant, k)
            found = distinct.rows(used)
            if used not in inputs:
                # each distinct input once (the outputs are quantised): the same values, gathered
                inputs[used] = self.inputs(y, temp_c, k) if found is None else np.column_stack(
                    [columns[c][found[0]] for c in used])
            x = inputs[used]
            outside = net.outside(x, self.input_margin)
            extrap |= outside if found is None else outside[found[1]]
            if net.n_centres == 0:  # nothing left for the network: the output is the base's
                continue
            if self.variant == "hybrid":  # bias(T) held at its edge value beyond the training temperatures
                x = np.clip(x, net.input_min, net.input_max)
            pred = net.predict(x)
            out[:, k] += pred if found is None else pred[found[1]]

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": "rbf", "variant": self.variant,
            "inputs": {c: input_names(self.variant, k) for k, c in enumerate(CHANNELS)},
            "output": "correction added to the measured value (paper Eq. 11)" if self.base is None
            else "correction added to the polynomial model's compensated value",
            "temperature_range_c": [self.t_min_c, self.t_max_c], "input_margin": self.input_margin,
            "networks": {c: net.to_dict() for c, net in zip(CHANNELS, self.networks)},
            "base": self.base.to_dict() if self.base is not None else None, "notes": self.notes,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RbfModel:
        lo, hi = d["temperature_range_c"]
        return cls(variant=d["variant"], networks=[RbfNetwork.from_dict(d["networks"][c]) for c in CHANNELS],
                   t_min_c=float(lo), t_max_c=float(hi),
                   base=PolyModel.from_dict(d["base"]) if d.get("base") else None,
                   input_margin=float(d.get("input_margin", 0.02)), notes=list(d.get("notes", [])))


def input_names(variant: str, channel: int) -> list[str]:
    cols = ("ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps")
    if variant == "triad":
        base = 0 if channel < 3 else 3
        return [cols[base], cols[base + 1], cols[base + 2], "imu_temp_c"]
    if variant == "hybrid":
        return ["imu_temp_c"]
    return [cols[channel], "imu_temp_c"]


def input_columns(variant: str, channel: int) -> tuple[int, ...]:
    """The network's inputs as columns of (y, temperature): 0-5 the outputs, -1 the temperature, in the
    order of `network_inputs`."""
    if variant == "triad":
        base = 0 if channel < 3 else 3
        return (base, base + 1, base + 2, -1)
    if variant == "hybrid":
        return (-1,)
    return (channel, -1)


DISTINCT_MIN_ROWS = 4096  # below this, evaluating every row costs less than finding the distinct ones
DISTINCT_MAX_FRACTION = 0.5  # more distinct inputs than this fraction of the rows: evaluate every row
DISTINCT_CHUNK = 1 << 18  # rows searched for distinct inputs at a time: the hash tables stay in cache


class _Distinct:
    """The distinct rows of sets of input columns, each column factorised once (hashing, no sort).

    Logged outputs are quantised (int16 counts) and so is the temperature, so a million rows hold a few
    thousand distinct (output, temperature) pairs: a network evaluated once per distinct input gives
    the same values at a fraction of the kernels. Codes and row indices are kept as int32 when they fit
    (half the memory: `DistinctInputs` keeps them while several models use them)."""

    def __init__(self, columns: dict[int, np.ndarray]) -> None:
        self.columns = columns
        self.n = next(iter(columns.values())).shape[0]
        self._codes: dict[int, tuple[np.ndarray, int] | None] = {}
        self._rows: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray] | None] = {}

    @classmethod
    def of(cls, y: np.ndarray, temp_c: np.ndarray) -> _Distinct:
        """Of the columns of outputs y (N, 6) (0-5) and the temperature (-1)."""
        return cls({c: (y[:, c] if c >= 0 else temp_c) for c in range(-1, 6)})

    def _column(self, c: int) -> tuple[np.ndarray, int] | None:
        if c not in self._codes:
            codes, uniques = pd.factorize(self.columns[c], use_na_sentinel=True)
            # NaN inputs (code -1) take the direct path, which propagates them as before
            self._codes[c] = None if codes.size and codes.min() < 0 else (_small(codes), len(uniques))
        return self._codes[c]

    def rows(self, used: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray] | None:
        """(one row index per distinct input, each row's index into them), or None: evaluate every row."""
        if self.n < DISTINCT_MIN_ROWS:
            return None
        if used not in self._rows:
            self._rows[used] = self._find(used)
        return self._rows[used]

    def _find(self, used: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray] | None:
        code: np.ndarray | None = None
        card = 1
        dense = False  # code is one column's codes: dense already, in order of first appearance
        for c in used:
            got = self._column(c)
            if got is None:
                return None
            codes, size = got
            card *= max(size, 1)
            if card > self.n / DISTINCT_MAX_FRACTION or card > 1 << 62:
                # too many combinations to code densely: find the distinct combined codes so far
                if code is None:
                    return None
                # (refactoring one column's codes would return them as they are)
                code, size_c = (code, card // max(size, 1)) if dense else _refactor(code)
                card = size_c * max(size, 1)
                if size_c > DISTINCT_MAX_FRACTION * self.n:
                    return None
            dense = code is None
            code = codes if code is None else code.astype(np.int64, copy=False) * size + codes
        assert code is not None
        # one column's codes are its distinct inputs numbered by first appearance: refactoring returns them
        inverse, n_distinct = (code, card) if dense else _refactor(code)
        if n_distinct > DISTINCT_MAX_FRACTION * self.n:
            return None
        first = np.empty(n_distinct, dtype=np.int64)
        first[inverse] = np.arange(self.n)  # any row of a distinct input stands for all of them
        return first, _small(inverse)


class DistinctInputs:
    """The distinct inputs of one set of rows (y, temperature), found once for every model compensating
    them (`RbfModel.compensate(..., distinct=)`): the paper, triad and hybrid networks of a scoring
    batch factorise each column once, not once each. Keeps every chunk's codes (int32: up to 64 B a
    row) while it lives: for a batch of rows, not a campaign."""

    def __init__(self, y: np.ndarray, temp_c: np.ndarray) -> None:
        self.y = y
        self.temp_c = temp_c
        self._chunks: dict[int, _Distinct] = {}

    def of(self, y: np.ndarray, temp_c: np.ndarray) -> bool:
        """Whether these are the rows (the same arrays)."""
        return y is self.y and temp_c is self.temp_c

    def chunk(self, lo: int) -> _Distinct:
        """The distinct inputs of the DISTINCT_CHUNK rows from `lo`."""
        if lo not in self._chunks:
            rows = slice(lo, lo + DISTINCT_CHUNK)
            self._chunks[lo] = _Distinct.of(self.y[rows], self.temp_c[rows])
        return self._chunks[lo]


def _small(codes: np.ndarray) -> np.ndarray:
    """Non-negative integer codes as int32 when they fit (the same values)."""
    return codes.astype(np.int32) if codes.size and int(codes.max()) < 2 ** 31 else codes


def _refactor(code: np.ndarray) -> tuple[np.ndarray, int]:
    """Dense codes 0..k-1 of integer codes, and k."""
    inverse, uniques = pd.factorize(code)
    return inverse.astype(np.int64, copy=False), len(uniques)


def network_inputs(variant: str, y: np.ndarray, temp_c: np.ndarray, channel: int) -> np.ndarray:
    if variant == "triad":
        base = 0 if channel < 3 else 3
        return np.column_stack([y[:, base:base + 3], temp_c])
    if variant == "hybrid":
        return np.asarray(temp_c, dtype=float)[:, None]
    return np.column_stack([y[:, channel], temp_c])


def step_spacing(temp_c: np.ndarray, step: np.ndarray | None = None, gap_c: float = 2.0) -> float:
    """Median spacing of the calibration temperatures (0 with fewer than two): the mean temperatures of
    the records' temperature steps (soaks, or the bins of a ramp) when they are known, else clusters of
    record temperatures separated by more than `gap_c`."""
    t = np.asarray(temp_c, dtype=float)
    if step is not None and step.size == t.size and step.size and step.min() >= 0:
        k = int(step.max()) + 1
        cnt = np.bincount(step, minlength=k)
        levels = np.sort((np.bincount(step, weights=t, minlength=k) / np.maximum(cnt, 1))[cnt > 0])
    else:
        t = np.sort(t)
        if t.size < 2:
            return 0.0
        levels = t[np.concatenate(([True], np.diff(t) > gap_c))]
    return float(np.median(np.diff(levels))) if levels.size > 1 else 0.0


def train_rbf_model(records: Records, variant: str = "paper", base: PolyModel | None = None,
                    options: RbfOptions | None = None,
                    progress: Callable[[str], None] | None = None) -> RbfModel:
    """Train the six networks of a variant on record means (targets: true - measured, or
    true - polynomial-compensated for ``hybrid``)."""
    return train_rbf_models(records, (variant,), base, options, progress)[variant]


def train_rbf_models(records: Records, variants: Sequence[str], base: PolyModel | None = None,
                     options: RbfOptions | None = None,
                     progress: Callable[[str], None] | None = None) -> dict[str, RbfModel]:
    """`train_rbf_model` of each variant, the networks trained concurrently (TRAIN_WORKERS threads).

    Every network is trained on its own inputs, from its own arrays, with no random draw: the same
    networks bit for bit as one at a time, on all cores (numpy and BLAS release the GIL in the
    products that take the time)."""
    opt = options or RbfOptions()
    plans = [_VariantPlan.of(records, v, base, opt) for v in variants]
    jobs = [(p, k) for p in plans for k in range(len(CHANNELS))]
    if progress:
        progress(f"RBF ({', '.join(variants)}): {len(jobs)} networks on {len(records)} records")
    nets = _map(lambda job: job[0].train(job[1]), jobs)
    out: dict[str, RbfModel] = {}
    for i, p in enumerate(plans):
        out[p.variant] = p.model(nets[i * len(CHANNELS):(i + 1) * len(CHANNELS)])
    return out


# One by default: measured on the paper store (2 vCPUs), two training threads gained 0.6 s of a 29 s fit's
# wall at load 0-1 for +3 s CPU (+10 %; +1.4 s at load 4-6): the cores share their caches and the GIL, so a
# busy machine would be made slower. More threads: set this (the networks are the same bit for bit).
TRAIN_WORKERS = 1


def _map(fn: Callable[[Any], RbfNetwork], items: list[Any]) -> list[RbfNetwork]:
    """fn over items, in order, on TRAIN_WORKERS threads."""
    if TRAIN_WORKERS == 1 or len(items) < 2:
        return [fn(i) for i in items]
    tuned_malloc()
    with ThreadPoolExecutor(min(TRAIN_WORKERS, len(items))) as pool:
        out = list(pool.map(fn, items))
    return out



@dataclass
class _VariantPlan:
    """One variant's training data: inputs, targets and weights of its six networks."""

    variant: str
    records: Records
    target: np.ndarray  # (n, 6)
    within: np.ndarray  # (n, 6) each record's sum of squares about its mean
    temp_width: float
    spacing: float
    base: PolyModel | None
    options: RbfOptions

    @classmethod
    def of(cls, records: Records, variant: str, base: PolyModel | None, opt: RbfOptions) -> _VariantPlan:
        if variant not in VARIANTS:
            raise ValueError(f"unknown RBF variant {variant!r}; expected one of {', '.join(VARIANTS)}")
        if variant == "hybrid" and base is None:
            raise ValueError("the hybrid RBF variant needs the polynomial model it refines")
        y = records.mean
        temp = records.temp_c
        start = compensate_poly(base, y, temp).values if variant == "hybrid" and base is not None else y
        target = records.reference - start
        runs = np.unique(records.run)
        if variant == "hybrid" and runs.size > 1:
            # The polynomial fits the gyro around each run's turn-on bias (fit.py); so does its remainder,
            # or the network would learn the runs' offsets as a function of the temperatures they covered.
            w_rec = records.duration_s
            for r in runs:
                sel = records.run == r
                target[sel, 3:] -= np.average(target[sel, 3:], axis=0, weights=w_rec[sel])
        # Train as on the samples themselves: record means weigh by their row counts, and the
        # rows' scatter about each mean enters GCV as the constant it is (see rbf.train_rbf).
        w = records.n_rows
        within = np.where(np.isfinite(records.sem), records.sem ** 2, 0.0) * (w * (w - 1))[:, None]
        spacing = step_spacing(temp, records.step)
        temp_width = opt.min_temp_width_c if opt.min_temp_width_c is not None else spacing
        return cls(variant=variant, records=records, target=target, within=within, temp_width=temp_width,
                   spacing=spacing, base=base if variant == "hybrid" else None, options=opt)

    def train(self, k: int) -> RbfNetwork:
        """The network of channel k."""
        opt, rec = self.options, self.records
        x = network_inputs(self.variant, rec.mean, rec.temp_c, k)
        offset, scale = normalisation(x)
        floor = np.zeros(x.shape[1])
        if self.variant != "paper":
            floor[-1] = self.temp_width / scale[-1]
        return train_rbf(x, self.target[:, k], rec.n_rows, widths=opt.widths, max_centres=opt.max_centres,
                         max_candidates=opt.max_candidates, patience=opt.patience, min_width=floor,
                         in_offset=offset, in_scale=scale, counts=True, within_ss=float(self.within[:, k].sum()))

    def model(self, nets: list[RbfNetwork]) -> RbfModel:
        notes: list[str] = []
        if self.spacing == 0:
            notes.append("one temperature only: the networks cannot learn a temperature dependence")
        temp = self.records.temp_c
        return RbfModel(variant=self.variant, networks=nets, t_min_c=float(temp.min()), t_max_c=float(temp.max()),
                        base=self.base, input_margin=self.options.input_margin, notes=notes)
