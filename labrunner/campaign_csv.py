"""The campaign CSV format (docs/design.md, "The campaign CSV"): one row per sample, validated on the way in.

`read_campaign` accepts a CSV path or a DataFrame and returns a frame with exactly
COLUMNS, in the right dtypes, or raises `CampaignDataError` naming file, line and
column. `write_campaign` writes the format.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from labrunner.domain import ACCEL_COLUMNS, GYRO_COLUMNS, ORIENTATIONS, OUTPUT_COLUMNS
from labrunner.domain import CSV_COLUMNS as COLUMNS
from labrunner.errors import UserError

__all__ = ["COLUMNS", "ACCEL_COLUMNS", "GYRO_COLUMNS", "OUTPUT_COLUMNS", "read_campaign", "write_campaign"]
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

    A CSV is parsed with typed columns first (numbers as float64, orientation and power_on as
    categories: no Python object per cell); a file that does not parse so is read again as text,
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


def _validate(raw: pd.DataFrame, label: str, from_csv: bool) -> pd.DataFrame:
    """The campaign columns of `raw`, checked and typed; `CampaignDataError` names the first bad cell."""
    missing = [c for c in COLUMNS if c not in raw.columns]
    if missing:
        raise CampaignDataError(label, "missing column(s) " + ", ".join(missing) + "; the header must name "
                                + ", ".join(COLUMNS), line=1 if from_csv else None)
    if len(raw) == 0:
        raise CampaignDataError(label, "no data rows")

    out: dict[str, object] = {}
    for col in ("t_s", "chamber_c", "imu_temp_c", "table_rate_dps") + OUTPUT_COLUMNS:
        series = raw[col]
        if series.dtype == object or isinstance(series.dtype, pd.StringDtype):
            text = series.astype(str).str.strip()
            empty = text.isin(_EMPTY)
            values = pd.to_numeric(text.where(~empty, None), errors="coerce")
            bad = values.isna() & ~empty
            if bad.any():
                i = int(np.flatnonzero(bad.to_numpy())[0])
                raise CampaignDataError(label, f"{text.iloc[i]!r} is not a number", _line(i, from_csv), col)
            arr = values.to_numpy(dtype=float)
        elif series.dtype == np.float64:
            arr = series.to_numpy()  # a view: the typed CSV reader's and a store's columns
        else:
            arr = pd.to_numeric(series, errors="coerce").to_numpy(dtype=float)
        if col in REQUIRED_NUMERIC:
            nan = ~np.isfinite(arr)
            if nan.any():
                i = int(np.flatnonzero(nan)[0])
                raise CampaignDataError(label, "value missing or not finite (NaN/inf)", _line(i, from_csv), col)
        elif np.isinf(arr).any():
            i = int(np.flatnonzero(np.isinf(arr))[0])
            raise CampaignDataError(label, "value is infinite", _line(i, from_csv), col)
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
                                    _line(i, from_csv), "run")
        out["run"] = r.astype(np.int64)

    out["orientation"] = _orientations(raw["orientation"], label, from_csv)

    t = out["t_s"]
    run = out["run"]
    assert isinstance(t, np.ndarray) and isinstance(run, np.ndarray)
    back = _backwards(t, run)
    if back is not None:
        i = back
        raise CampaignDataError(label, f"time goes backwards within run {run[i]} ({t[i - 1]} then {t[i]})",
                                _line(i, from_csv), "t_s")
    columns = list(COLUMNS)
    if POWER_ON in raw.columns:  # optional (docs/design.md, "The campaign CSV"): 1 on a real power-on's first row
        out[POWER_ON] = _power_on(raw[POWER_ON], label, from_csv)
        columns.append(POWER_ON)
    return pd.DataFrame({c: out[c] for c in columns}, copy=False)


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
    cat = series.array if isinstance(series.dtype, pd.CategoricalDtype) else pd.Categorical(series)
    codes = np.asarray(cat.codes)
    # A missing cell (code -1) reads as the text the row-wise path saw: 'nan'.
    labels = [str(c).strip() for c in cat.categories] + ["nan"]
    return codes, labels


def _orientations(series: pd.Series, label: str, from_csv: bool) -> pd.Categorical:
    codes, labels = _categories(series)
    known = np.array([lab in ORIENTATIONS for lab in labels])
    target = np.array([ORIENTATIONS.index(lab) if ok else -1 for lab, ok in zip(labels, known)], dtype=np.int8)
    unknown = ~known[codes]
    if unknown.any():
        i = int(np.flatnonzero(unknown)[0])
        raise CampaignDataError(label, f"unknown orientation {labels[codes[i]]!r}; expected one of "
                                + " ".join(ORIENTATIONS), _line(i, from_csv), "orientation")
    return pd.Categorical.from_codes(target[codes], categories=list(ORIENTATIONS))


def _power_on(series: pd.Series, label: str, from_csv: bool) -> np.ndarray:
    codes, labels = _categories(series)
    ok = np.array([lab in _POWER_ON_TEXT for lab in labels])
    if not ok[codes].all():
        i = int(np.flatnonzero(~ok[codes])[0])
        raise CampaignDataError(label, f"{labels[codes[i]]!r} is not 0 or 1", _line(i, from_csv), POWER_ON)
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
        header = pd.read_csv(path, nrows=0, skipinitialspace=True).columns
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError, ValueError):
        return None
    names = {str(c).strip(): c for c in header}
    if len(names) != len(header) or any(c not in names for c in COLUMNS):
        return None  # duplicate or missing columns: the text reader's messages
    dtype: dict[str, object] = {names[c]: float for c in COLUMNS if c != "orientation"}
    dtype[names["orientation"]] = "category"
    wanted = set(COLUMNS)
    if POWER_ON in names:
        dtype[names[POWER_ON]] = "category"
        wanted.add(POWER_ON)
    try:
        raw = pd.read_csv(path, dtype=dtype, usecols=[names[c] for c in names if c in wanted],
                          keep_default_na=False, na_values=list(_EMPTY), skipinitialspace=True)
    except (ValueError, pd.errors.ParserError, UnicodeDecodeError, OverflowError):
        return None
    raw.columns = [str(c).strip() for c in raw.columns]
    return raw


def write_campaign(frame: pd.DataFrame, path: str | Path) -> None:
    """Write a campaign frame in the CSV format (full float precision)."""
    missing = [c for c in COLUMNS if c not in frame.columns]
    if missing:
        raise ValueError("cannot write campaign CSV: missing column(s) " + ", ".join(missing))
    columns = list(COLUMNS) + ([POWER_ON] if POWER_ON in frame.columns else [])
    frame.loc[:, columns].to_csv(path, index=False, float_format="%.9g")
