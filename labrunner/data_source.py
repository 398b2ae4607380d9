"""Where analysis data comes from: a campaign CSV or a labrunner store (a SQLite file or a PostgreSQL URL),
as one frame."""

from __future__ import annotations

import builtins
import operator
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from pandas.api.extensions import ExtensionArray, ExtensionDtype, no_default, register_extension_dtype, take
from pandas.api.indexers import check_array_indexer
from pandas.api.types import is_integer, is_scalar, pandas_dtype
from pandas.arrays import NumpyExtensionArray

from labrunner.campaign_csv import CampaignDataError, read_campaign
from labrunner.errors import UserError
from labrunner.store_address import StoreAddress, is_store, is_url, store_address


@dataclass
class CampaignData:
    """Validated campaign rows (campaign CSV columns) and where they came from."""

    frame: pd.DataFrame
    provenance: dict[str, Any] = field(default_factory=dict)
    # The store read, password and all, to store a fit back into (provenance["source"] shows it masked).
    store: StoreAddress | None = field(default=None, repr=False, compare=False)


def step_progress(store: Any, campaign_id: int) -> dict[str, int]:
    """Steps planned and recorded (status done) of a stored campaign: a fit says when they differ."""
    planned, recorded = store.step_counts(campaign_id)
    return {"steps_planned": planned, "steps_recorded": recorded}


def load_campaign_data(path: str | Path | StoreAddress, campaign: int | None = None, *,
                       include_monitor: bool = False) -> CampaignData:
    """Load a campaign CSV or a store database (its latest campaign, or `campaign`).

    From a store, `include_monitor` adds the 1 s monitor rows logged while ramping and soaking
    (what a diagnosis of thermal lag or hysteresis needs); a fit uses the record steps only.
    """
    if isinstance(path, StoreAddress) or is_url(path):
        return _from_store(store_address(path), campaign, include_monitor)
    p = Path(path)
    if not p.exists():
        raise CampaignDataError(str(p), "file not found")
    if p.is_dir():
        raise CampaignDataError(str(p), "is a directory; expected a campaign CSV or a labrunner database file")
    if is_store(p):
        return _from_store(store_address(p), campaign, include_monitor)
    frame = read_campaign(p)
    return CampaignData(frame=frame, provenance={"source": str(p.resolve()), "kind": "csv", "rows": len(frame)})


def _from_store(address: StoreAddress, campaign: int | None, include_monitor: bool) -> CampaignData:
    from labrunner.store import Store

    # The sample blocks' pages are checked by reading them all (see Store.open_existing).
    with Store.open_existing(address, check_samples=False) as store:
        data = store.campaign_data(campaign, include_monitor=include_monitor)
        data.provenance.update(step_progress(store, int(data.provenance["campaign_id"])))
        data.frame = mark_power_ons(data.frame, store_power_on_events(store, int(data.provenance["campaign_id"])))
        return data


POWER_ON_TEXT = "powered on (run "  # what every message `power_on_runs` reads contains


def store_power_on_events(store: Any, campaign_id: int) -> pd.DataFrame:
    """The events `power_on_runs` reads (their messages), without reading the campaign's other events."""
    return pd.DataFrame({"message": pd.Series(store.event_messages(campaign_id, POWER_ON_TEXT), dtype=object)})


def power_on_runs(events: pd.DataFrame) -> set[int]:
    """The runs the sequencer powered the IMU on for: its "powered on (run N)" events."""
    import re

    return {int(m.group(1)) for text in events.get("message", pd.Series(dtype=str)).astype(str)
            if (m := re.search(re.escape(POWER_ON_TEXT) + r"(\d+)\)", text))}


class PowerOnMarks:
    """The store's power-on events as the campaign CSV's optional `power_on` column, chunk by chunk: 1 on
    the first row of each run the sequencer powered the IMU on for. The runs seen in earlier chunks are
    remembered, so marking a campaign's time-ordered chunks in order marks what marking the whole does."""

    def __init__(self, events: pd.DataFrame) -> None:
        self.powered = np.fromiter(power_on_runs(events), dtype=np.int64)
        self.seen: set[int] = set()

    def mark(self, frame: pd.DataFrame) -> pd.DataFrame:
        run = frame["run"].to_numpy()
        # The first row of each run: where the run changes, when no run comes back later (a store's rows
        # are in time order); else by hashing every row's run.
        change = _run_starts(run)
        if np.unique(run[change]).size == change.size:
            at = change
        else:
            at = np.flatnonzero(~frame["run"].duplicated().to_numpy())
        if self.seen:  # a run that began in an earlier chunk has its first row there
            at = at[~np.isin(run[at], np.fromiter(self.seen, dtype=np.int64, count=len(self.seen)))]
        self.seen.update(run[at].tolist())
        mark = np.zeros(run.size, dtype=np.int8)
        mark[at[np.isin(run[at], self.powered)]] = 1
        return frame.assign(power_on=mark)


def campaign_chunks(path: str | Path | StoreAddress, campaign: int | None = None, *, max_rows: int = 1 << 20,
                    include_monitor: bool = False, min_gap_s: float | None = None, rows: int | None = None
                    ) -> tuple[dict[str, Any], Iterator[pd.DataFrame]]:
    """`load_campaign_data(path, campaign, include_monitor=...)` a bounded number of rows at a time: its
    provenance (the same dict, known before any sample is read: rows and time range from the block
    rows) and an iterator of validated, power-on-marked chunks whose concatenation is its frame
    (index included: a chunk's RangeIndex continues the previous one's).

    From a store, chunks are `Store.frames` chunks (whole blocks, `max_rows` and `min_gap_s` as
    there), each validated by `read_campaign_chunk` (the whole read's checks and messages, rows named
    by their place in the campaign); the store stays open until the iterator is exhausted or closed.
    `rows` (a store's `provenance["rows"]` from an earlier call) pins the samples read to the first
    `rows`, so that every pass of a fit sees one campaign while it is still being recorded.
    A campaign CSV is read whole and comes as one chunk."""
    if not (isinstance(path, StoreAddress) or is_url(path)):
        p = Path(path)
        if not (p.exists() and not p.is_dir() and is_store(p)):
            data = load_campaign_data(p, campaign, include_monitor=include_monitor)
            return data.provenance, iter([data.frame])
    from labrunner.store import Store

    address = store_address(path)
    store = Store.open_existing(address, check_samples=False)
    try:
        cid = store.resolve(campaign)
        info = store.campaign(cid)
        kinds = ("record", "monitor") if include_monitor else ("record",)
        counted = store.sample_count(cid, kinds)
        rows = counted if rows is None else min(rows, counted)
        if rows == 0:
            raise UserError(f"{store.path}: campaign {cid} has no recorded samples yet")
        provenance: dict[str, Any] = {
            "source": str(store.path.resolve()), "kind": "store", "campaign_id": cid, "campaign": info.name,
            "procedure_sha256": info.procedure_sha256, "status": info.status, "rows": rows,
            "t_range_s": list(store.time_range(cid, kinds)), "recorded_with": info.software_version,
        }
        provenance.update(step_progress(store, cid))
        marks = PowerOnMarks(store_power_on_events(store, cid))
    except BaseException:
        store.close()
        raise
    return provenance, _store_chunks(store, cid, marks, max_rows=max_rows, include_monitor=include_monitor,
                                     min_gap_s=min_gap_s, rows=rows)


def _store_chunks(store: Any, cid: int, marks: PowerOnMarks, *, max_rows: int, include_monitor: bool,
                  min_gap_s: float | None, rows: int) -> Iterator[pd.DataFrame]:
    from labrunner.campaign_csv import read_campaign_chunk

    name = f"{store.path} campaign {cid}"
    previous: tuple[int, float] | None = None
    try:
        for chunk in store.frames(cid, max_rows=max_rows, include_monitor=include_monitor, min_gap_s=min_gap_s,
                                  rows=rows):
            first = int(chunk.index[0])
            chunk = marks.mark(read_campaign_chunk(chunk, name, first_row=first, previous=previous))
            previous = (int(chunk["run"].iat[-1]), float(chunk["t_s"].iat[-1]))
            yield chunk
    finally:
        store.close()


def _run_starts(run: np.ndarray, chunk: int = 1 << 20) -> np.ndarray:
    """The rows where the run differs from the row before (and row 0), a chunk at a time (no
    full-length masks)."""
    if not run.size:
        return np.zeros(0, dtype=np.intp)
    parts = [np.zeros(1, dtype=np.intp)]
    for lo in range(1, run.size, chunk):
        hi = min(lo + chunk, run.size)
        parts.append(lo + np.flatnonzero(run[lo:hi] != run[lo - 1:hi - 1]))
    return np.concatenate(parts)


def mark_power_ons(frame: pd.DataFrame, events: pd.DataFrame) -> pd.DataFrame:
    """The store's power-on events as the campaign CSV's optional `power_on` column: 1 on the first
    row of each run the sequencer powered the IMU on for (its "powered on (run N)" event)."""
    return PowerOnMarks(events).mark(frame)


# --- float64 columns kept as the store's int16 counts ---------------------------------------------------


@register_extension_dtype
class ScaledFloatDtype(ExtensionDtype):
    """float64 values held as integer counts times a scale (`ScaledFloatArray`): what a store's IMU
    channels are (int16 counts and their LSB), a quarter of a float64 column in memory."""

    name = "scaled_float64"
    type = float
    kind = "f"
    na_value = np.nan
    _is_numeric = True

    @classmethod
    def construct_array_type(cls) -> builtins.type[ScaledFloatArray]:
        return ScaledFloatArray


class ScaledFloatArray(ExtensionArray):
    """A float64 column stored as `counts * scale` (int16 counts: the values a store decodes, bit for bit,
    `counts * lsb` in float64). pandas sees float64 values (kind "f"): `to_numpy`, `np.asarray`,
    reductions, arithmetic and CSV writing convert; `take` and row selection keep the counts.
    `counts`/`scale` let the analysis convert a chunk at a time (`labrunner.calibration.records`)."""

    _HANDLED = (np.ndarray, int, float, np.number)

    def __init__(self, counts: np.ndarray, scale: float = 1.0) -> None:
        counts = np.asarray(counts)
        if counts.ndim != 1 or counts.dtype.kind not in "iuf":
            raise ValueError(f"ScaledFloatArray needs 1-d numeric counts, not {counts.dtype} of shape {counts.shape}")
        self._counts = counts
        self._scale = float(scale)

    # -- what the analysis reads
    @property
    def counts(self) -> np.ndarray:
        return self._counts

    @property
    def scale(self) -> float:
        return self._scale

    @property
    def finite_by_construction(self) -> bool:
        """Integer counts times a finite LSB: every value is finite (campaign_csv's check skips the column)."""
        return self._counts.dtype.kind in "iu" and bool(np.isfinite(self._scale))

    def _floats(self) -> np.ndarray:
        if self._counts.dtype == np.float64 and self._scale == 1.0:
            return self._counts
        return np.multiply(self._counts, self._scale, dtype=np.float64)

    # -- the ExtensionArray interface
    @classmethod
    def _from_sequence(cls, scalars: Any, *, dtype: Any = None, copy: bool = False) -> ScaledFloatArray:
        if isinstance(scalars, ScaledFloatArray):
            return scalars.copy() if copy else scalars
        return cls(np.array(scalars, dtype=np.float64), 1.0)

    @classmethod
    def _from_factorized(cls, values: np.ndarray, original: ScaledFloatArray) -> ScaledFloatArray:
        return cls(np.asarray(values, dtype=np.float64), 1.0)

    @classmethod
    def _concat_same_type(cls, to_concat: Sequence[ScaledFloatArray]) -> ScaledFloatArray:
        first = to_concat[0]
        if all(a._scale == first._scale and a._counts.dtype == first._counts.dtype for a in to_concat):
            return cls(np.concatenate([a._counts for a in to_concat]), first._scale)
        return cls(np.concatenate([a._floats() for a in to_concat]), 1.0)

    @property
    def dtype(self) -> ScaledFloatDtype:
        return ScaledFloatDtype()

    @property
    def nbytes(self) -> int:
        return int(self._counts.nbytes)

    def __len__(self) -> int:
        return int(self._counts.size)

    def __getitem__(self, key: Any) -> Any:
        if is_integer(key):
            return float(self._counts[key] * np.float64(self._scale))
        if isinstance(key, tuple) and len(key) == 1:
            key = key[0]
        if not isinstance(key, slice):
            key = check_array_indexer(self, key)
        return type(self)(self._counts[key], self._scale)

    def __setitem__(self, key: Any, value: Any) -> None:
        # Values that need not be whole counts: the column becomes plain float64 (scale 1).
        if not isinstance(key, slice) and not is_integer(key):
            key = check_array_indexer(self, key)
        floats = self._floats()
        self._counts = floats.copy() if floats is self._counts and not floats.flags.writeable else floats
        self._scale = 1.0
        self._counts[key] = np.asarray(value, dtype=np.float64) if not is_scalar(value) else value

    def __iter__(self) -> Iterator[float]:
        return iter(self._floats().tolist())

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> np.ndarray:
        values = self._floats()
        if copy and values is self._counts:
            values = values.copy()
        return values if dtype is None else values.astype(dtype, copy=False)

    def __array_ufunc__(self, ufunc: np.ufunc, method: str, *inputs: Any, **kwargs: Any) -> Any:
        if any(isinstance(x, pd.Series | pd.Index | pd.DataFrame) for x in inputs):
            return NotImplemented
        inputs = tuple(x._floats() if isinstance(x, ScaledFloatArray) else x for x in inputs)
        if "out" in kwargs:
            kwargs["out"] = tuple(x._floats() if isinstance(x, ScaledFloatArray) else x for x in kwargs["out"])
        return getattr(ufunc, method)(*inputs, **kwargs)

    def to_numpy(self, dtype: Any = None, copy: bool = False, na_value: Any = no_default) -> np.ndarray:
        values = self._floats()
        if na_value is not no_default and not (isinstance(na_value, float) and np.isnan(na_value)):
            missing = np.isnan(values)
            if missing.any():
                values = values.copy()
                values[missing] = na_value
        if dtype is not None:
            return np.array(values, dtype=dtype, copy=copy or None)
        return values.copy() if copy and values is self._counts else values

    def astype(self, dtype: Any, copy: bool = True) -> Any:
        dtype = pandas_dtype(dtype)
        if isinstance(dtype, ScaledFloatDtype):
            return self.copy() if copy else self
        if isinstance(dtype, np.dtype):
            return np.array(self._floats(), dtype=dtype, copy=True if copy else None)
        return super().astype(dtype, copy=copy)

    def isna(self) -> np.ndarray:
        if self._counts.dtype.kind == "f":
            return np.isnan(self._counts)
        return np.zeros(self._counts.size, dtype=bool)

    def take(self, indices: Any, *, allow_fill: bool = False, fill_value: Any = None) -> ScaledFloatArray:
        idx = np.asarray(indices, dtype=np.intp)
        if allow_fill and (idx < 0).any():
            values = take(self._floats(), idx, allow_fill=True, fill_value=np.nan if fill_value is None else fill_value)
            return type(self)(values, 1.0)
        return type(self)(self._counts.take(idx), self._scale)

    def copy(self) -> ScaledFloatArray:
        return type(self)(self._counts.copy(), self._scale)

    def _values_for_factorize(self) -> tuple[np.ndarray, float]:
        return self._floats(), np.nan

    def _values_for_argsort(self) -> np.ndarray:
        return self._floats()

    def searchsorted(self, value: Any, side: Any = "left", sorter: Any = None) -> Any:
        return self._floats().searchsorted(np.asarray(value, dtype=np.float64), side=side, sorter=sorter)

    def _reduce(self, name: str, *, skipna: bool = True, keepdims: bool = False, **kwargs: Any) -> Any:
        if name in ("min", "max") and self._counts.dtype.kind in "iu" and self._scale > 0 and len(self) \
                and not keepdims:
            # Whole counts and a positive scale: the extreme count, scaled, is the extreme value.
            return float(getattr(self._counts, name)() * np.float64(self._scale))
        return NumpyExtensionArray(self._floats())._reduce(name, skipna=skipna, keepdims=keepdims, **kwargs)

    def _accumulate(self, name: str, *, skipna: bool = True, **kwargs: Any) -> Any:
        return NumpyExtensionArray(self._floats())._accumulate(name, skipna=skipna, **kwargs)

    def _groupby_op(self, *, how: str, has_dropped_na: bool, min_count: int, ngroups: int, ids: np.ndarray,
                    **kwargs: Any) -> Any:
        # pandas' own float64 path (what a float64 column's groupby runs), on the converted values.
        from pandas.core.groupby.ops import WrappedCythonOp

        op = WrappedCythonOp(how=how, has_dropped_na=has_dropped_na)
        return op.cython_operation(values=self._floats(), axis=0, min_count=min_count, comp_ids=ids, ngroups=ngroups,
                                   **kwargs)

    def _cmp(self, other: Any, op: Callable[[Any, Any], Any]) -> Any:
        if isinstance(other, pd.Series | pd.Index | pd.DataFrame):
            return NotImplemented
        return op(self._floats(), other._floats() if isinstance(other, ScaledFloatArray) else other)

    def __eq__(self, other: Any) -> Any:
        return self._cmp(other, operator.eq)

    def __ne__(self, other: Any) -> Any:
        return self._cmp(other, operator.ne)


def _binary(op: Callable[[Any, Any], Any], reflected: bool = False) -> Callable[[ScaledFloatArray, Any], Any]:
    def method(self: ScaledFloatArray, other: Any) -> Any:
        if isinstance(other, pd.Series | pd.Index | pd.DataFrame):
            return NotImplemented
        theirs = other._floats() if isinstance(other, ScaledFloatArray) else other
        return op(theirs, self._floats()) if reflected else op(self._floats(), theirs)
    return method


for _name in ("add", "sub", "mul", "truediv", "floordiv", "mod", "pow", "lt", "le", "gt", "ge"):
    _op = getattr(operator, _name)
    setattr(ScaledFloatArray, f"__{_name}__", _binary(_op))
    if _name not in ("lt", "le", "gt", "ge"):
        setattr(ScaledFloatArray, f"__r{_name}__", _binary(_op, reflected=True))
for _name in ("neg", "pos", "abs"):
    setattr(ScaledFloatArray, f"__{_name}__", (lambda op: lambda self: op(self._floats()))(getattr(operator, _name)))
