"""Compensation of a campaign with a model file: what `labrunner compensate MODEL DATA --csv OUT` does.

The model is a file `labrunner fit --out` wrote (`polynomial.json`, `rbf.json`) or a `fit --json`
document (its exported model: the network if one was exported, else the polynomial). Every row of the
data comes out with its compensated outputs (`<column>_comp`) and a flag, `extrapolated`, for rows whose
temperature (or network input) lies outside what the model was fitted to: flagged, not refused.
A model fitted at the lag-corrected temperature carries its `temperature_filter`: the rows' temperature
goes through it (per run, at the rows' times) before the model, as in the fit and the C header. A model
fitted per hysteresis branch carries its `branch_state`: the rows' outputs less width/2 x their branch
state go into the model.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from labrunner.campaign_csv import OUTPUT_COLUMNS
from labrunner.errors import UserError

from .branch_fit import BranchModel, branch_model_from_dict
from .compensation import compensate
from .export import FORMAT, filter_from_dict, model_from_dict
from .ins import DEFAULT_WINDOW_S, InsErrors, ins_errors, window_rows
from .rbf_model import RbfModel
from .thermal_lag_fit import TemperatureFilter
from .thermal_poly import PolyModel

log = logging.getLogger(__name__)
FIT_FORMAT = "labrunner-calibration/1"  # the `labrunner fit --json` document
COMP_SUFFIX = "_comp"


@dataclass(frozen=True)
class ModelFile:
    """A model read from a file, and which one of the file it is."""

    model: PolyModel | RbfModel
    name: str  # "polynomial", "rbf_hybrid", ...
    path: str
    temperature_filter: TemperatureFilter | None = None  # the model's temperature: the logged one through it
    branch: BranchModel | None = None  # the model's outputs: the logged ones less the branch offset

    def model_temperature(self, frame: pd.DataFrame) -> np.ndarray:
        """The temperature the model takes for the frame's rows (lag-corrected if the model says so)."""
        temp = frame["imu_temp_c"].to_numpy(dtype=float)
        if self.temperature_filter is None:
            return temp
        return self.temperature_filter.apply(frame["t_s"].to_numpy(dtype=float), temp, frame["run"].to_numpy())

    def model_outputs(self, frame: pd.DataFrame, y: np.ndarray) -> np.ndarray:
        """The outputs the model takes for the frame's rows `y` (less the branch offset if the model says so)."""
        if self.branch is None:
            return y
        s = self.branch.state.states(frame["t_s"].to_numpy(dtype=float), frame["imu_temp_c"].to_numpy(dtype=float),
                                     frame["run"].to_numpy(), frame["orientation"].astype(str).to_numpy())
        return self.branch.correct(y, s)

    @property
    def temp_range_c(self) -> tuple[float, float]:
        return self.model.t_min_c, self.model.t_max_c


def read_model(path: str | Path) -> ModelFile:
    """A calibration model from its JSON file; `UserError` naming the file and what is wrong otherwise."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"{p}: model file not found")
    if p.is_dir():
        raise UserError(f"{p}: is a directory; expected a model file (polynomial.json or rbf.json of `labrunner fit "
                        "--out`)")
    try:
        data = json.loads(p.read_text())
    except UnicodeDecodeError:
        raise UserError(f"{p}: not a text file; expected a labrunner model JSON file") from None
    except json.JSONDecodeError as exc:
        raise UserError(f"{p}:{exc.lineno}: not JSON ({exc.msg}); expected a labrunner model JSON file") from None
    fmt = data.get("format") if isinstance(data, dict) else None
    if fmt == FIT_FORMAT:  # a fit document: its exported model
        models = data.get("models") or {}
        key = "rbf" if isinstance(models.get("rbf"), dict) else "polynomial"
        d = models.get(key)
    elif fmt == FORMAT:
        d = data.get("model")
    else:
        raise UserError(f"{p}: format {fmt!r} is not a labrunner calibration model (expected {FORMAT!r}, as in the "
                        "polynomial.json and rbf.json that `labrunner fit --out` writes)")
    if not isinstance(d, dict):
        raise UserError(f"{p}: no model in the file")
    try:
        model = model_from_dict(d)
        temperature_filter = filter_from_dict(d)
        branch = branch_model_from_dict(d)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise UserError(f"{p}: the model is incomplete or malformed ({type(exc).__name__}: {exc})") from None
    name = "polynomial" if isinstance(model, PolyModel) else f"rbf_{model.variant}"
    return ModelFile(model=model, name=name, path=str(p), temperature_filter=temperature_filter, branch=branch)


@dataclass(frozen=True)
class CompensatedData:
    """The rows with compensated columns and the extrapolation flag, and what the flag says."""

    frame: pd.DataFrame
    n_rows: int
    n_extrapolated: int
    data_temp_range_c: tuple[float, float]

    def summary(self, model: ModelFile) -> str:
        lo, hi = model.temp_range_c
        pct = 100.0 * self.n_extrapolated / max(self.n_rows, 1)
        return (f"{self.n_rows:,} rows compensated with {model.name} ({model.path}); {self.n_extrapolated:,} "
                f"({pct:.2f} %) flagged as extrapolation (model fitted over {lo:.2f} .. {hi:.2f} C, data "
                f"{self.data_temp_range_c[0]:.2f} .. {self.data_temp_range_c[1]:.2f} C)")


def compensate_data(model: ModelFile, frame: pd.DataFrame) -> CompensatedData:
    """The same rows with `<output>_comp` columns and `extrapolated` (0/1) added."""
    y = np.column_stack([frame[c].to_numpy(dtype=float) for c in OUTPUT_COLUMNS])
    temp = frame["imu_temp_c"].to_numpy(dtype=float)
    comp = compensate(model.model, model.model_outputs(frame, y), model.model_temperature(frame))
    out = frame.copy()
    for j, c in enumerate(OUTPUT_COLUMNS):
        out[c + COMP_SUFFIX] = comp.values[:, j]
    out["extrapolated"] = comp.extrapolated.astype(np.int8)
    n_ex = int(comp.extrapolated.sum())
    if n_ex:
        log.info("%d rows outside the model's range", n_ex)
    rng = (float(temp.min()), float(temp.max())) if temp.size else (float("nan"), float("nan"))
    return CompensatedData(frame=out, n_rows=int(len(out)), n_extrapolated=n_ex, data_temp_range_c=rng)


def ins_of(model: ModelFile, frame: pd.DataFrame, window_s: float = DEFAULT_WINDOW_S) -> dict[str, InsErrors]:
    """The paper's INS test on any campaign data: strapdown navigation over windows of `window_s` of
    contiguous rows of one record (static or on the turning table), raw and compensated."""
    from .records import frame_arrays, segment_records

    a = frame_arrays(frame)
    labels = segment_records(frame).row_record
    win = window_rows(a, labels >= 0, labels, window_s)
    if win.size == 0:
        return {}
    rows = win.ravel()
    y = a["y"][rows] if model.branch is None else model.model_outputs(frame, np.asarray(a["y"]))[rows]
    comp = compensate(model.model, y, model.model_temperature(frame)[rows]).values
    return ins_errors(a, win, {"raw": a["y"][rows], model.name: comp}, window_s)
