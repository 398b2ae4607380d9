"""The campaign CSV format (docs/design.md, "The campaign CSV"): one row per sample, validated on the way in.

`read_campaign` accepts a CSV path or a DataFrame and returns a frame with exactly
COLUMNS, in the right dtypes, or raises `CampaignDataError` naming file, line and
column. `write_campaign` writes the format.
"""

from __future__ import annotations

import csv
import io
import logging
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np
import pandas as pd

from labrunner.domain import ACCEL_COLUMNS, GYRO_COLUMNS, ORIENTATIONS, OUTPUT_COLUMNS
from labrunner.domain import CSV_COLUMNS as COLUMNS
from labrunner.errors import UserError

if TYPE_CHECKING:
    from labrunner.store import Store, StoredBlock

log = logging.getLogger(__name__)

__all__ = ["COLUMNS", "ACCEL_COLUMNS", "GYRO_COLUMNS", "OUTPUT_COLUMNS", "export_campaign", "read_campaign",
           "read_campaign_chunk", "write_campaign"]
# Columns that must hold a number on every row; chamber_c may be empty (no chamber).
REQUIRED_NUMERIC = ("t_s", "imu_temp_c", "table_rate_dps") + OUTPUT_COLUMNS
POWER_ON = "power_on"  # optional column: 1 on the first row after a real power-on, else 0


class CampaignDataError(UserError, ValueError):
    """Bad campaign data; the message names where (file, line, column)."""

    def __init__(self, source: str, message: str, line: int | None = None, column: str | None = None):
        self.source = source
        self.line = line
        self.column = column
        where = source + (f":{line}" if line is not None else "")
        col = f" column '{column}'" if column else ""
        super().__init__(f"{where}:{col}: {message}" if col else f"{where}: {message}")


def _line(index: int, from_csv: bool) -> int:
    # File line of a data row: the header is line 1. For frames, report the row index.
    return index + 2 if from_csv else index


_EMPTY = ("", "nan", "NaN", "None")  # cells that mean "no value" (chamber_c may be empty)
_TRUE = ("1", "1.0", "True", "true")
_POWER_ON_TEXT = ("0", "0.0", "False", "false") + _TRUE


def read_campaign(source: str | Path | pd.DataFrame, name: str | None = None) -> pd.DataFrame:
    """Load and validate campaign data; sorted as given (time order within each run is checked).

    A CSV is parsed with typed columns first (numbers as float64, orientation and power_on as text
    labelled per distinct value); a file that does not parse so is read again as text,
    cell by cell, for the message that names its line and column. A frame whose columns are typed
    already (a store's) is validated without copies."""
    from_csv = not isinstance(source, pd.DataFrame)
    label = name or (str(source) if from_csv else "data")
    if not isinstance(source, pd.DataFrame):
        path = Path(source)
        if not path.exists():
            raise CampaignDataError(label, "file not found")
        if path.is_dir():
            raise CampaignDataError(label, "is a directory; expected a campaign CSV file")
        typed = _read_typed(path, label)
        if typed is not None:
            try:
                return _validate(typed, label, True)
            except CampaignDataError:
                pass  # the text reading says it as the file has it (a cell's own text, its line)
        return _validate(_read_text(path, label), label, True)
    return _validate(source.reset_index(drop=True), label, False)


def read_campaign_chunk(frame: pd.DataFrame, name: str, *, first_row: int,
                        previous: tuple[int, float] | None) -> pd.DataFrame:
    """A chunk of a campaign frame (rows `first_row`... of the whole) validated as `read_campaign` validates
    the whole: the same checks and messages, rows named by their place in the whole, and time order
    checked across the boundary (`previous`: the run and time of the row before the chunk, None for
    the first). The result's RangeIndex starts at `first_row`."""
    out = _validate(frame.reset_index(drop=True), name, False, first_row=first_row, previous=previous)
    if first_row:
        out.index = pd.RangeIndex(first_row, first_row + len(out))
    return out


def _validate(raw: pd.DataFrame, label: str, from_csv: bool, *, first_row: int = 0,
              previous: tuple[int, float] | None = None) -> pd.DataFrame:
    """The campaign columns of `raw`, checked and typed; `CampaignDataError` names the first bad cell
    (rows numbered from `first_row`; `previous`: the run and time of the row before, for the time order)."""
    missing = [c for c in COLUMNS if c not in raw.columns]
    if missing:
        raise CampaignDataError(label, "missing column(s) " + ", ".join(missing) + "; the header must name "
                                + ", ".join(COLUMNS), line=1 if from_csv else None)
    if len(raw) == 0:
        raise CampaignDataError(label, "no data rows")

    out: dict[str, object] = {}
    for col in ("t_s", "chamber_c", "imu_temp_c", "table_rate_dps") + OUTPUT_COLUMNS:
        series = raw[col]
        if getattr(series.array, "finite_by_construction", False):
            # A store's integer counts x LSB (data_source.ScaledFloatArray): nothing to check, and converting
            # them for the check would cost the float64 copy the counts save.
            out[col] = series.array
            continue
        if series.dtype == object or isinstance(series.dtype, pd.StringDtype):
            text = series.astype(str).str.strip()
            empty = text.isin(_EMPTY)
            values = pd.to_numeric(text.where(~empty, None), errors="coerce")
            bad = values.isna() & ~empty
            if bad.any():
                i = int(np.flatnonzero(bad.to_numpy())[0])
                raise CampaignDataError(label, f"{text.iloc[i]!r} is not a number", _line(first_row + i, from_csv),
                                        col)
            arr = values.to_numpy(dtype=float)
        elif series.dtype == np.float64:
            arr = series.to_numpy()  # a view: the typed CSV reader's and a store's columns
        else:
            arr = pd.to_numeric(series, errors="coerce").to_numpy(dtype=float)
        if col in REQUIRED_NUMERIC:
            at = _first_where(arr, lambda a: ~np.isfinite(a))
            if at is not None:
                raise CampaignDataError(label, "value missing or not finite (NaN/inf)",
                                        _line(first_row + at, from_csv), col)
        else:
            at = _first_where(arr, np.isinf)
            if at is not None:
                raise CampaignDataError(label, "value is infinite", _line(first_row + at, from_csv), col)
        out[col] = arr

    series = raw["run"]
    if series.dtype == np.int64:
        out["run"] = series.to_numpy()
    else:
        if series.dtype == object or isinstance(series.dtype, pd.StringDtype):
            runs = pd.to_numeric(series.astype(str).str.strip(), errors="coerce")
        else:
            runs = pd.to_numeric(series, errors="coerce")
        r = runs.to_numpy(dtype=float)
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(r) | (np.round(r) != r) | (np.abs(r) > 2**31)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise CampaignDataError(label, f"{raw['run'].iloc[i]!r} is not an integer run number",
                                    _line(first_row + i, from_csv), "run")
        out["run"] = r.astype(np.int64)

    out["orientation"] = _orientations(raw["orientation"], label, from_csv, first_row)

    t = out["t_s"]
    run = out["run"]
    assert isinstance(t, np.ndarray) and isinstance(run, np.ndarray)
    if previous is not None and run[0] == previous[0] and t[0] < previous[1]:
        raise CampaignDataError(label, f"time goes backwards within run {run[0]} ({previous[1]} then {t[0]})",
                                _line(first_row, from_csv), "t_s")
    back = _backwards(t, run)
    if back is not None:
        i = back
        raise CampaignDataError(label, f"time goes backwards within run {run[i]} ({t[i - 1]} then {t[i]})",
                                _line(first_row + i, from_csv), "t_s")
    columns = list(COLUMNS)
    if POWER_ON in raw.columns:  # optional (docs/design.md, "The campaign CSV"): 1 on a real power-on's first row
        out[POWER_ON] = _power_on(raw[POWER_ON], label, from_csv, first_row)
        columns.append(POWER_ON)
    return pd.DataFrame({c: out[c] for c in columns}, copy=False)


def _first_where(values: np.ndarray, bad: Callable[[np.ndarray], np.ndarray], chunk: int = 1 << 20) -> int | None:
    """The first row where `bad` holds, or None; a chunk at a time (no full-length temporaries: a
    campaign's 12 M rows would take fresh pages for every mask)."""
    for lo in range(0, values.size, chunk):
        hits = np.flatnonzero(bad(values[lo:lo + chunk]))
        if hits.size:
            return lo + int(hits[0])
    return None


def _backwards(t: np.ndarray, run: np.ndarray, chunk: int = 1 << 20) -> int | None:
    """The first row whose time is before its predecessor's in the same run, or None (in chunks: no
    full-length temporaries)."""
    for lo in range(1, t.size, chunk):
        hi = min(lo + chunk, t.size)
        bad = np.flatnonzero((run[lo:hi] == run[lo - 1:hi - 1]) & (t[lo:hi] < t[lo - 1:hi - 1]))
        if bad.size:
            return lo + int(bad[0])
    return None


def _categories(series: pd.Series) -> tuple[np.ndarray, list[str]]:
    """Integer codes and stripped text labels of a column: per distinct value, not per cell."""
    if isinstance(series.dtype, pd.CategoricalDtype):
        codes, uniques = np.asarray(series.array.codes), series.array.categories
    else:  # a text column (the typed CSV reader's): one hash pass, no sorting of labels as a Categorical would
        codes, uniques = pd.factorize(series, use_na_sentinel=True)
    # A missing cell (code -1) reads as the text the row-wise path saw: 'nan'.
    labels = [str(c).strip() for c in uniques] + ["nan"]
    return codes, labels


_ORIENTATION_DTYPE = pd.CategoricalDtype(list(ORIENTATIONS))  # what `_orientations` returns


def _orientations(series: pd.Series, label: str, from_csv: bool, first_row: int = 0) -> pd.Categorical:
    values = series.array
    if (isinstance(values, pd.Categorical) and values.dtype == _ORIENTATION_DTYPE
            and values.categories.dtype == _ORIENTATION_DTYPE.categories.dtype):
        # Already the six orientations as categories (a store's read): the codes are the answer unless
        # a cell is missing (code -1), which the general path names. One pass, no copy.
        codes = np.asarray(values.codes)
        if codes.size == 0 or codes.min() >= 0:
            return values
    codes, labels = _categories(series)
    known = np.array([lab in ORIENTATIONS for lab in labels])
    target = np.array([ORIENTATIONS.index(lab) if ok else -1 for lab, ok in zip(labels, known)], dtype=np.int8)
    unknown = ~known[codes]
    if unknown.any():
        i = int(np.flatnonzero(unknown)[0])
        raise CampaignDataError(label, f"unknown orientation {labels[codes[i]]!r}; expected one of "
                                + " ".join(ORIENTATIONS), _line(first_row + i, from_csv), "orientation")
    return pd.Categorical.from_codes(target[codes], categories=list(ORIENTATIONS))


def _power_on(series: pd.Series, label: str, from_csv: bool, first_row: int = 0) -> np.ndarray:
    if series.dtype == np.float64:  # the typed CSV reader's
        values = series.to_numpy()
        at = _first_where(values, lambda v: (v != 0) & (v != 1))
        if at is not None:
            cell = "nan" if np.isnan(values[at]) else f"{values[at]:g}"
            raise CampaignDataError(label, f"{cell!r} is not 0 or 1", _line(first_row + at, from_csv), POWER_ON)
        return values.astype(np.int8)
    codes, labels = _categories(series)
    ok = np.array([lab in _POWER_ON_TEXT for lab in labels])
    if not ok[codes].all():
        i = int(np.flatnonzero(~ok[codes])[0])
        raise CampaignDataError(label, f"{labels[codes[i]]!r} is not 0 or 1", _line(first_row + i, from_csv),
                                POWER_ON)
    return np.array([lab in _TRUE for lab in labels], dtype=np.int8)[codes]  # 0/1: one byte a row


def _read_text(path: Path, label: str) -> pd.DataFrame:
    """Every cell as text: slow, but what the located messages of a file that does not parse need."""
    try:
        raw = pd.read_csv(path, dtype=str, keep_default_na=False, na_values=[], skipinitialspace=True)
    except pd.errors.EmptyDataError:
        raise CampaignDataError(label, "the file is empty; expected a header with " + ", ".join(COLUMNS)) from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise CampaignDataError(label, f"not a readable CSV file ({str(exc).strip()})") from None
    raw.columns = [str(c).strip() for c in raw.columns]
    return raw


def _read_typed(path: Path, label: str) -> pd.DataFrame | None:
    """The CSV with numeric columns parsed as float64 by pandas' C reader, or None when a cell is not
    a number (or the file is not a CSV at all): the text reader then says where."""
    try:
        header = pd.read_csv(path, nrows=0).columns
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError, ValueError):
        return None
    names = {str(c).strip(): c for c in header}
    if len(names) != len(header) or any(c not in names for c in COLUMNS):
        return None  # duplicate or missing columns: the text reader's messages
    # Text columns as categories, labelled (stripped, checked) once per distinct value afterwards: with
    # pandas 3 this is the C reader's fastest text path (object cells were a Python string a row, ~2x
    # the whole read for a power_on column). No skipinitialspace (it slowed the parser by a third): the
    # C reader takes spaces around numbers, labels are stripped per distinct value, and the cells it
    # cannot read so (a quoted number after a space, a blank of spaces) fail here or in the
    # validation, and the text reader reads them. No usecols unless the file has other columns:
    # selecting columns costs pandas' parallel chunk parsing (1.1 s against 0.5 s for 2 M rows).
    # power_on as a number (0/1): as a category its chunks' differing categories send pandas' parallel
    # read back to a serial one; a file writing True/False there is read by the text reader.
    dtype: dict[str, object] = {names[c]: ("category" if c == "orientation" else float)
                                for c in (*COLUMNS, POWER_ON) if c in names}
    usecols = None if len(dtype) == len(header) else list(dtype)
    try:
        raw = pd.read_csv(path, dtype=dtype, usecols=usecols, keep_default_na=False, na_values=list(_EMPTY))
    except (ValueError, pd.errors.ParserError, UnicodeDecodeError, OverflowError):
        return None
    raw.columns = [str(c).strip() for c in raw.columns]
    return raw


# --- writing ----------------------------------------------------------------------------------------
#
# The format's numbers are '%.9g' (full float32 precision, what the store keeps) and a missing value
# an empty cell: what `DataFrame.to_csv(float_format="%.9g")` wrote, byte for byte, from Python's own
# '%' (the same formatting pandas applies per cell). pandas spent ~8 us a row in it (102 s CPU for
# the paper store); here rows are formatted a chunk at a time: a store's int16 samples once per
# distinct count (a table of 65 536 cells per LSB size), a column that holds one value in a chunk
# once, the other numbers by one '%' each, and a chunk's cells joined in one `str.join`.

_EOL = "\n"
CHUNK_ROWS = 1 << 11  # rows decoded and formatted at a time: bounds the writer's memory whatever a block holds
_I16 = 1 << 15


@dataclass(frozen=True)
class Quantised:
    """A column of whole counts of `lsb` (an int16 store block's samples decode to counts * lsb)."""

    counts: np.ndarray  # integer
    lsb: float


@dataclass(frozen=True)
class Labels:
    """A text column as codes into its distinct cells (already CSV-quoted); code -1 is an empty cell."""

    codes: np.ndarray
    cells: list[str]


# One column of a chunk: float64 numbers ('%.9g', NaN empty), integers, Quantised, Labels, or one
# cell (already quoted) for every row.
Cells = np.ndarray | Quantised | Labels | str


def quote_cell(text: str) -> str:
    """`text` as a CSV cell, quoted only where needed (as pandas' to_csv and the csv module write it)."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator=_EOL).writerow(["", text])  # a leading empty cell: "" alone is quoted
    return buf.getvalue()[1:-len(_EOL)]


def _escaped(text: str) -> str:
    return text.replace("%", "%%")


class RowFormatter:
    """Campaign CSV rows from columns of cells (see `Cells`); keeps the tables of quantised cells
    across chunks, so a campaign's counts are formatted once."""

    def __init__(self) -> None:
        self._tables: dict[tuple[float, str, str], tuple[np.ndarray, np.ndarray]] = {}

    def rows(self, columns: Sequence[Cells], n: int) -> np.ndarray:
        """The chunk's cells, separators included, as an (n, k) object array of str: its rows joined
        in order are the chunk's lines."""
        # Runs of constant cells and separators merge into the text around the varying columns.
        parts: list[str | Cells] = []
        for j, col in enumerate(columns):
            sep = "," if j + 1 < len(columns) else _EOL
            if isinstance(col, str):
                text = col + sep
                if parts and isinstance(parts[-1], str):
                    parts[-1] += text
                else:
                    parts.append(text)
            else:
                parts += [col, sep]
        varying = [i for i, part in enumerate(parts) if not isinstance(part, str)]
        if not varying:
            return np.full((n, 1), "".join(p for p in parts if isinstance(p, str)), dtype=object)
        out = np.empty((n, len(varying)), dtype=object)
        for k, i in enumerate(varying):
            prefix = parts[i - 1] if k == 0 and i > 0 else ""
            suffix = parts[i + 1] if i + 1 < len(parts) else ""
            assert isinstance(prefix, str) and isinstance(suffix, str)
            out[:, k] = self._cells(parts[i], prefix, suffix)  # type: ignore[arg-type]
        return out

    def _cells(self, col: np.ndarray | Quantised | Labels, prefix: str, suffix: str) -> Any:
        if isinstance(col, Quantised):
            return self._quantised(col, prefix, suffix)
        if isinstance(col, Labels):
            table = np.array([prefix + c + suffix for c in col.cells] + [prefix + suffix], dtype=object)
            return table[col.codes]
        if col.dtype.kind in "iub":
            distinct, inverse = np.unique(col, return_inverse=True)
            return np.array([prefix + str(v) + suffix for v in distinct.tolist()], dtype=object)[inverse]
        values = np.asarray(col, dtype=np.float64)
        bits = values.view(np.int64)
        nan = np.isnan(values)
        if nan.all():
            return prefix + suffix
        fmt = _escaped(prefix) + "%.9g" + _escaped(suffix)
        if not nan.any() and (bits == bits[0]).all():  # one value (bit for bit: -0 is not 0)
            return fmt % float(values[0])
        if nan.any():
            empty = prefix + suffix
            return [empty if v != v else fmt % v for v in values.tolist()]
        return [fmt % v for v in values.tolist()]

    def _quantised(self, col: Quantised, prefix: str, suffix: str) -> Any:
        index = col.counts.astype(np.int64) + _I16
        key = (col.lsb, prefix, suffix)
        if key not in self._tables:
            self._tables[key] = (np.zeros(2 * _I16, dtype=bool), np.empty(2 * _I16, dtype=object))
        done, table = self._tables[key]
        new = np.unique(index[~done[index]])
        if new.size:
            fmt = _escaped(prefix) + "%.9g" + _escaped(suffix)
            # The numbers the store's decoding gives (float64 counts times the LSB), formatted as such.
            table[new] = [fmt % v for v in ((new - _I16).astype(np.float64) * col.lsb).tolist()]
            done[new] = True
        return table[index]


def rows_text(rows: np.ndarray) -> str:
    return "".join(rows.ravel().tolist())


def write_campaign(frame: pd.DataFrame, path: str | Path) -> None:
    """Write a campaign frame in the CSV format (float32 precision: '%.9g'), `CHUNK_ROWS` rows at a time."""
    missing = [c for c in COLUMNS if c not in frame.columns]
    if missing:
        raise ValueError("cannot write campaign CSV: missing column(s) " + ", ".join(missing))
    columns = list(COLUMNS) + ([POWER_ON] if POWER_ON in frame.columns else [])
    cells = [_frame_column(frame[c]) for c in columns]
    if any(c is None for c in cells):  # a dtype the chunk writer does not format as pandas does
        frame.loc[:, columns].to_csv(path, index=False, float_format="%.9g", lineterminator=_EOL)
        return
    fmt = RowFormatter()
    with _output(Path(path)) as out:
        out.write(",".join(quote_cell(c) for c in columns) + _EOL)
        for lo in range(0, len(frame), CHUNK_ROWS):
            hi = min(lo + CHUNK_ROWS, len(frame))
            out.write(rows_text(fmt.rows([_rows_of(c, lo, hi) for c in cells if c is not None], hi - lo)))


def _rows_of(cells: Cells, lo: int, hi: int) -> Cells:
    if isinstance(cells, Labels):
        return Labels(cells.codes[lo:hi], cells.cells)
    if isinstance(cells, Quantised):
        return Quantised(cells.counts[lo:hi], cells.lsb)
    if isinstance(cells, str):
        return cells
    return cells[lo:hi]


def _frame_column(series: pd.Series) -> np.ndarray | Labels | None:
    """A frame's column as cells, or None when its dtype is one pandas formats otherwise (e.g. nullable
    integers, dates): the frame is then written by pandas."""
    dtype = series.dtype
    if isinstance(dtype, np.dtype) and dtype.kind in "fiub":
        return series.to_numpy()
    if isinstance(dtype, pd.CategoricalDtype):
        codes, uniques = np.asarray(series.array.codes), series.array.categories
    elif (isinstance(dtype, np.dtype) and dtype.kind == "O") or isinstance(dtype, pd.StringDtype):
        codes, uniques = pd.factorize(series, use_na_sentinel=True)
    else:
        return None
    if not all(isinstance(u, str) for u in uniques):  # numbers in a text column: pandas' own str()
        return None
    return Labels(np.asarray(codes), [quote_cell(u) for u in uniques])


@contextmanager
def _output(path: Path) -> Iterator[TextIO]:
    """A text file written in full or not at all: a regular file is written beside its place and renamed
    over it at the end (an export that fails, e.g. on a damaged store, leaves no partial CSV, and an
    old one in place); anything else (a device, a FIFO) is written directly."""
    if path.exists() and not path.is_file():
        with open(path, "w", encoding="utf-8", newline="") as f:
            yield f
        return
    tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)  # the umask's permissions, as open() gives
    try:
        with open(fd, "w", encoding="utf-8", newline="") as f:
            yield f
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# --- a store's campaign, block by block ---------------------------------------------------------------


def export_campaign(store: Store, campaign_id: int, out: str | Path | TextIO, *, include_monitor: bool = False,
                    force: bool = False) -> int:
    """Write a stored campaign as campaign CSV (a path or a text stream) block by block; returns the rows.

    The bytes `write_campaign(store.samples_frame(...))` would write, in memory bounded by a block (or
    `CHUNK_ROWS`) instead of the whole campaign. A path may not be the store (or its -wal/-shm), an
    existing file is replaced only with `force`, and only once the whole campaign is written."""
    from labrunner.output_paths import check_output

    kinds = ("record", "monitor") if include_monitor else ("record",)
    target = check_output(out, store=store.path, force=force, option="--csv") if isinstance(out, str | Path) else None
    if store.sample_count(campaign_id, kinds) == 0:
        raise UserError(f"{store.path}: campaign {campaign_id} has no recorded samples to export")
    if target is None:
        assert not isinstance(out, str | Path)
        return write_blocks(store.stored_blocks(campaign_id, kinds), out, time_order=include_monitor)
    with _output(target) as f:
        return write_blocks(store.stored_blocks(campaign_id, kinds), f, time_order=include_monitor)


def write_blocks(blocks: Iterable[StoredBlock], out: TextIO, *, time_order: bool = False) -> int:
    """Write stored sample blocks as campaign CSV, header first; returns the rows written.

    Rows come out in the blocks' order, or with `time_order` (records and monitor rows together) in
    time order as a stable sort of them all would give (ties in block order). That merge holds back
    only the rows later than the next block's start: the blocks come in start-time order and a block's
    samples do not precede its start (its counters ascend). A block is decoded `CHUNK_ROWS` rows at a
    time, so memory does not grow with the length of a block."""
    fmt = RowFormatter()
    out.write(",".join(quote_cell(c) for c in COLUMNS) + _EOL)
    written = 0
    held: list[tuple[np.ndarray, np.ndarray]] = []  # time_order: rows not yet written, as sorted runs in order
    ahead = iter(b for b in blocks if len(b))
    b = next(ahead, None)
    while b is not None:
        following = next(ahead, None)  # read one block early: its start bounds every later row
        later = following.t0_s if following is not None else np.inf
        for t, rows, rest in _chunks(b, fmt):
            if not time_order:
                out.write(rows_text(rows))
                written += t.size
                continue
            if held and held[-1][0][-1] > t[0]:  # overlapping rows: merge them (a stable sort)
                held = [_merge(held + [(t, rows)])]
            else:
                held.append((t, rows))
            bound = min(later, rest)  # no row still to come is earlier
            while held:
                t_run, rows_run = held[0]
                k = int(np.searchsorted(t_run, bound, side="right"))
                out.write(rows_text(rows_run[:k]))
                written += k
                if k < t_run.size:
                    held[0] = (t_run[k:], rows_run[k:])
                    break
                held.pop(0)
        b = following
    return written


_SAMPLE_COLUMNS = (("accel_g", 0), ("gyro_dps", 1))  # (n, 3) blobs and their LSB's place


def _chunks(b: StoredBlock, fmt: RowFormatter) -> Iterator[tuple[np.ndarray, np.ndarray, float]]:
    """A block's times and formatted rows `CHUNK_ROWS` at a time, with the time its next chunk starts at
    (inf for the last); chamber and table readings interpolated to the sample times as
    `Store.samples_frame` does (point by point: a chunk's values are the whole block's)."""
    from labrunner.store import interp_readings

    run, orientation = str(b.run), quote_cell(b.orientation)
    n = len(b)
    for lo in range(0, n, CHUNK_ROWS):
        hi = min(lo + CHUNK_ROWS, n)
        t = b.times(lo, hi)
        cells: list[Cells] = [t, run, orientation, interp_readings(t, b.chamber), _samples(b, "temp_c", 2, lo, hi),
                              interp_readings(t, b.table, default=0.0)]
        for column, which in _SAMPLE_COLUMNS:
            block = _samples(b, column, which, lo, hi)
            cells += [_column(block, j) for j in range(3)]
        yield t, fmt.rows(cells, t.size), float(b.times(hi, hi + 1)[0]) if hi < n else np.inf


def _samples(b: StoredBlock, column: str, which: int, lo: int, hi: int) -> np.ndarray | Quantised:
    """Rows lo:hi of a block's samples: an int16 block's counts as they are stored (their cells are
    those of the decoded values, counts x LSB, from the formatter's table), else the float values."""
    if b.lsb is None:
        return b.values(column, lo, hi)
    return Quantised(b.counts(column, lo, hi), b.lsb[which])


def _column(samples: np.ndarray | Quantised, j: int) -> np.ndarray | Quantised:
    if isinstance(samples, Quantised):
        return Quantised(samples.counts[:, j], samples.lsb)
    return samples[:, j]


def _merge(runs: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Runs of rows merged by time, a stable sort (at equal times the earlier run's row first), each row
    as one line (the runs' cells may split differently)."""
    lines = np.array(["".join(r) for _, rows in runs for r in rows.tolist()], dtype=object)
    t = np.concatenate([t for t, _ in runs])
    order = np.argsort(t, kind="stable")
    return t[order], lines[order][:, None]
