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


def read_campaign(source: str | Path | pd.DataFrame, name: str | None = None) -> pd.DataFrame:
    """Load and validate campaign data; sorted as given (time order within each run is checked)."""
    from_csv = not isinstance(source, pd.DataFrame)
    label = name or (str(source) if from_csv else "data")
    if not isinstance(source, pd.DataFrame):
        path = Path(source)
        if not path.exists():
            raise CampaignDataError(label, "file not found")
        if path.is_dir():
            raise CampaignDataError(label, "is a directory; expected a campaign CSV file")
        try:
            raw = pd.read_csv(path, dtype=str, keep_default_na=False, na_values=[], skipinitialspace=True)
        except pd.errors.EmptyDataError:
            raise CampaignDataError(label, "the file is empty; expected a header with " + ", ".join(COLUMNS)) from None
        except (pd.errors.ParserError, UnicodeDecodeError) as exc:
            raise CampaignDataError(label, f"not a readable CSV file ({str(exc).strip()})") from None
        raw.columns = [str(c).strip() for c in raw.columns]
    else:
        raw = source.reset_index(drop=True)
    missing = [c for c in COLUMNS if c not in raw.columns]
    if missing:
        raise CampaignDataError(label, "missing column(s) " + ", ".join(missing) + "; the header must name "
                                + ", ".join(COLUMNS), line=1 if from_csv else None)
    if len(raw) == 0:
        raise CampaignDataError(label, "no data rows")

    out = pd.DataFrame(index=raw.index)
    for col in ("t_s", "chamber_c", "imu_temp_c", "table_rate_dps") + OUTPUT_COLUMNS:
        series = raw[col]
        if from_csv or series.dtype == object:
            text = series.astype(str).str.strip()
            empty = text.isin(["", "nan", "NaN", "None"])
            values = pd.to_numeric(text.where(~empty, None), errors="coerce")
            bad = values.isna() & ~empty
            if bad.any():
                i = int(np.flatnonzero(bad.to_numpy())[0])
                raise CampaignDataError(label, f"{text.iloc[i]!r} is not a number", _line(i, from_csv), col)
        else:
            values = pd.to_numeric(series, errors="coerce")
        arr = values.to_numpy(dtype=float)
        if col in REQUIRED_NUMERIC:
            nan = ~np.isfinite(arr)
            if nan.any():
                i = int(np.flatnonzero(nan)[0])
                raise CampaignDataError(label, "value missing or not finite (NaN/inf)", _line(i, from_csv), col)
        elif np.isinf(arr).any():
            i = int(np.flatnonzero(np.isinf(arr))[0])
            raise CampaignDataError(label, "value is infinite", _line(i, from_csv), col)
        out[col] = arr

    if from_csv or raw["run"].dtype == object:
        runs = pd.to_numeric(raw["run"].astype(str).str.strip(), errors="coerce")
    else:
        runs = pd.to_numeric(raw["run"], errors="coerce")
    r = runs.to_numpy(dtype=float)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(r) | (np.round(r) != r) | (np.abs(r) > 2**31)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise CampaignDataError(label, f"{raw['run'].iloc[i]!r} is not an integer run number", _line(i, from_csv),
                                "run")
    out["run"] = r.astype(np.int64)

    orient = raw["orientation"].astype(str).str.strip()
    known = orient.isin(ORIENTATIONS).to_numpy()
    if not known.all():
        i = int(np.flatnonzero(~known)[0])
        raise CampaignDataError(label, f"unknown orientation {orient.iloc[i]!r}; expected one of "
                                + " ".join(ORIENTATIONS), _line(i, from_csv), "orientation")
    out["orientation"] = pd.Categorical(orient, categories=list(ORIENTATIONS))

    t = out["t_s"].to_numpy()
    run = out["run"].to_numpy()
    same_run = run[1:] == run[:-1]
    back = np.flatnonzero(same_run & (np.diff(t) < 0))
    if back.size:
        i = int(back[0]) + 1
        raise CampaignDataError(label, f"time goes backwards within run {run[i]} ({t[i - 1]} then {t[i]})",
                                _line(i, from_csv), "t_s")
    if POWER_ON in raw.columns:  # optional (docs/design.md, "The campaign CSV"): 1 on a real power-on's first row
        text = raw[POWER_ON].astype(str).str.strip()
        ok = text.isin(["0", "1", "0.0", "1.0", "True", "False", "true", "false"]).to_numpy()
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            raise CampaignDataError(label, f"{text.iloc[i]!r} is not 0 or 1", _line(i, from_csv), POWER_ON)
        out[POWER_ON] = text.isin(["1", "1.0", "True", "true"]).to_numpy().astype(np.int64)
        return out[list(COLUMNS) + [POWER_ON]]
    return out[list(COLUMNS)]


def write_campaign(frame: pd.DataFrame, path: str | Path) -> None:
    """Write a campaign frame in the CSV format (full float precision)."""
    missing = [c for c in COLUMNS if c not in frame.columns]
    if missing:
        raise ValueError("cannot write campaign CSV: missing column(s) " + ", ".join(missing))
    columns = list(COLUMNS) + ([POWER_ON] if POWER_ON in frame.columns else [])
    frame.loc[:, columns].to_csv(path, index=False, float_format="%.9g")
