"""Compensation (paper Eq. 11) of raw samples with either model, vectorised and chunked.

Polynomial model: y = (I + S(T)) u + b(T) is inverted exactly, u = (I + S(T))^-1 (y - b(T))
(Cramer's rule on whole columns, no per-sample Python). RBF model: u = y + dU(y, T). Both
flag samples whose temperature (or, for the RBF, network input) lies outside the data the
model was fitted to.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from labrunner.campaign_csv import OUTPUT_COLUMNS

from .thermal_poly import PolyModel, TriadPoly

if TYPE_CHECKING:  # rbf_model imports this module
    from .rbf_model import RbfModel

CHUNK = 1 << 15  # rows per pass: the temporaries stay in cache


@dataclass
class Compensated:
    """Compensated outputs (N, 6) [ax ay az gx gy gz] and where the model extrapolated."""

    values: np.ndarray
    extrapolated: np.ndarray  # (N,) bool: temperature (or RBF input) outside the fitted range

    def as_frame(self, frame: pd.DataFrame) -> pd.DataFrame:
        """A copy of `frame` with compensated outputs and an `extrapolated` column."""
        out = frame.copy()
        for j, c in enumerate(OUTPUT_COLUMNS):
            out[c] = self.values[:, j]
        out["extrapolated"] = self.extrapolated
        return out


def _horner(coef: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """sum_k coef[k] tau^k for a 1-D coefficient vector."""
    out = np.full(tau.shape, coef[-1])
    for c in coef[-2::-1]:
        out *= tau
        out += c
    return out


def invert_triad(model: TriadPoly, y: np.ndarray, temp_c: np.ndarray) -> np.ndarray:
    """(N, 3) u solving (I + S(T)) u = y - b(T)."""
    tau = np.asarray(temp_c, dtype=float) - model.t_ref_c
    r0, r1, r2 = (y[:, i] - _horner(model.bias[i], tau) for i in range(3))
    s = [_horner(model.scale[i, j], tau) for i in range(3) for j in range(3)]
    a00, a01, a02 = 1 + s[0], s[1], s[2]
    a10, a11, a12 = s[3], 1 + s[4], s[5]
    a20, a21, a22 = s[6], s[7], 1 + s[8]
    c00 = a11 * a22 - a12 * a21
    c01 = a12 * a20 - a10 * a22
    c02 = a10 * a21 - a11 * a20
    inv_det = 1.0 / (a00 * c00 + a01 * c01 + a02 * c02)
    u = np.empty((tau.size, 3))
    # u = adj(A) r / det
    u[:, 0] = (c00 * r0 + (a02 * a21 - a01 * a22) * r1 + (a01 * a12 - a02 * a11) * r2) * inv_det
    u[:, 1] = (c01 * r0 + (a00 * a22 - a02 * a20) * r1 + (a02 * a10 - a00 * a12) * r2) * inv_det
    u[:, 2] = (c02 * r0 + (a01 * a20 - a00 * a21) * r1 + (a00 * a11 - a01 * a10) * r2) * inv_det
    return u


def compensate_poly(model: PolyModel, y: np.ndarray, temp_c: np.ndarray) -> Compensated:
    """Eq. 11 with the polynomial model for outputs y (N, 6) at IMU temperatures (N,)."""
    y = np.asarray(y, dtype=float)
    temp_c = np.asarray(temp_c, dtype=float)
    out = np.empty_like(y)
    for s in range(0, y.shape[0], CHUNK):
        e = slice(s, s + CHUNK)
        out[e, :3] = invert_triad(model.accel, y[e, :3], temp_c[e])
        out[e, 3:] = invert_triad(model.gyro, y[e, 3:], temp_c[e])
    extrap = (temp_c < model.t_min_c) | (temp_c > model.t_max_c)
    return Compensated(values=out, extrapolated=extrap)


def compensate(model: PolyModel | RbfModel, y: np.ndarray, temp_c: np.ndarray) -> Compensated:
    """Compensate with a PolyModel or an RbfModel."""
    if isinstance(model, PolyModel):
        return compensate_poly(model, y, temp_c)
    return model.compensate(y, temp_c)  # RbfModel


def compensate_frame(model: PolyModel | RbfModel, frame: pd.DataFrame) -> pd.DataFrame:
    """Campaign frame in, the same frame with compensated outputs (+ `extrapolated`) out."""
    y = np.column_stack([frame[c].to_numpy(dtype=float) for c in OUTPUT_COLUMNS])
    return compensate(model, y, frame["imu_temp_c"].to_numpy(dtype=float)).as_frame(frame)
