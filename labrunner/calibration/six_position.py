"""Six-position calibration at each temperature step (paper Eq. 2-3).

At one temperature the model is y = (I + S) u + b. Each record gives one column of the
paper's measurement matrix (its mean output) and of the reference matrix U = [u; 1];
Eq. 3, E = Y U' (U U')^-1, is the least-squares solution, computed here per output
channel with the records weighted by duration. Every record counts: the accelerometer
reference is 1 g in all of them, the gyro reference is each record's table rate about
the up axis, so all rate steps (both directions) are used, not a single rate.
Uncertainties come from the residual scatter of the record means.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .lsq import weighted_lstsq
from .records import Records, TemperatureSteps
from .triads import ORIENTATIONS, TRIAD_SLICE, TRIADS, describe_missing


@dataclass
class StepCalibration:
    """Bias, scale factor and misalignment of one triad at one temperature step."""

    triad: str
    temp_c: float
    bias: np.ndarray  # (3,) sensor units; nan where not identifiable
    scale: np.ndarray  # (3, 3) S: scale-factor error on the diagonal, misalignment off it
    bias_std: np.ndarray  # (3,)
    scale_std: np.ndarray  # (3, 3)
    n_records: int
    orientations: list[str]
    dof: int
    not_fitted: list[str] = field(default_factory=list)

    def params(self) -> np.ndarray:
        """(3, 4) [bias, S[:,0], S[:,1], S[:,2]] per channel."""
        return np.column_stack([self.bias, self.scale])

    def params_std(self) -> np.ndarray:
        return np.column_stack([self.bias_std, self.scale_std])

    def to_dict(self) -> dict[str, Any]:
        return {
            "triad": self.triad, "temp_c": float(self.temp_c), "n_records": self.n_records,
            "orientations": self.orientations, "dof": self.dof,
            "bias": _nan_to_none(self.bias), "bias_std": _nan_to_none(self.bias_std),
            "scale": _nan_to_none(self.scale), "scale_std": _nan_to_none(self.scale_std),
            "not_fitted": self.not_fitted,
        }


def _nan_to_none(a: np.ndarray) -> Any:
    arr = np.asarray(a, dtype=float)
    out = arr.astype(object)
    out[~np.isfinite(arr)] = None
    return out.tolist()


def is_rotating(records: Records, tol_dps: float = 0.05) -> bool:
    return bool(np.any(np.abs(records.rate_dps) > tol_dps))


def six_position(records: Records, triad: str, temp_c: float | None = None) -> StepCalibration:
    """Eq. 3 for one triad over the given records (normally the records of one temperature step)."""
    sl = TRIAD_SLICE[triad]
    u = records.reference[:, sl]
    x = np.column_stack([np.ones(len(records)), u])
    fit = weighted_lstsq(x, records.mean[:, sl] - u, records.duration_s, known_var=records.sem[:, sl] ** 2)
    params = fit.coef.T  # (3 channels, 4 blocks)
    std = fit.std.T
    missing = [(c, b) for c in range(3) for b in range(4) if not fit.identifiable[b]]
    not_fitted = [describe_missing(triad, missing, records.orientation, is_rotating(records))] if missing else []
    if temp_c is None:
        w = records.duration_s
        temp_c = float(np.sum(w * records.temp_c) / np.sum(w)) if len(records) else float("nan")
    return StepCalibration(
        triad=triad, temp_c=float(temp_c), bias=params[:, 0], scale=params[:, 1:], bias_std=std[:, 0],
        scale_std=std[:, 1:], n_records=len(records),
        orientations=[ORIENTATIONS[i] for i in sorted(set(records.orientation.tolist()))], dof=fit.dof,
        not_fitted=not_fitted,
    )


def calibrate_steps(records: Records, steps: TemperatureSteps) -> dict[str, list[StepCalibration]]:
    """Six-position calibration of both triads at every temperature step."""
    out: dict[str, list[StepCalibration]] = {t: [] for t in TRIADS}
    for k in range(len(steps)):
        sub = records.subset(records.step == k, with_labels=False)
        for triad in TRIADS:
            out[triad].append(six_position(sub, triad, float(steps.temp_c[k])))
    return out
