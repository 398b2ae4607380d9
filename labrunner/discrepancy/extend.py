"""The extended simulation model: the sims' `ImuModel` with the fitted baseline and the found effects.

Written with `ImuModel.save`, it is a configuration the sims load
(`SimLabConfig.from_dict({"imu_model": path})`), so a dry run reproduces what was
measured. `check_model` evaluates any `ImuModel` on a measured campaign -- the way to
verify that the residual structure is gone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from labrunner.domain import ACCEL_CHANNELS, CHANNELS, GYRO_CHANNELS
from labrunner.imu.model import ImuModel, TriadModel

from .blocks import Blocks
from .measurements import Measurements


@dataclass
class ChannelNoise:
    white_rms: float  # RMS of the white noise over this log's rows, sensor units
    noise_density: float  # sensor units per sqrt(Hz), as labrunner.imu.model.TriadModel
    drift_per_sqrt_s: float  # random-walk bias drift, sensor units per sqrt(s)
    drift_evidence: float  # 2 log-likelihood ratio of the drift against none


def noise_density(meas: Measurements, blocks: Blocks) -> np.ndarray:
    """(6,) white-noise density (sensor units per sqrt(Hz), as labrunner.imu.model.TriadModel).

    A row that averages (or samples at the rate of) its spacing dt has white RMS
    density / sqrt(2 dt), so two neighbours differ by density / sqrt(dt): the differences
    of consecutive rows within blocks, scaled by sqrt(dt), give the density whatever mix
    of row spacings the log has (robustly, by the median absolute deviation).
    """
    err = meas.error
    same = np.repeat(np.arange(len(blocks)), blocks.count)
    dt = np.diff(meas.t_s)
    pair = (same[1:] == same[:-1]) & (dt > 0)
    if pair.sum() < 10:
        return np.full(6, np.nan)
    d = np.diff(err, axis=0)[pair] * np.sqrt(dt[pair])[:, None]
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)


def white_rms(density: float, spacing_s: np.ndarray) -> float:
    """RMS of white noise of this density over rows with these spacings (each row averaging
    its spacing): what measured-minus-model reaches when the model is complete."""
    return float(density * np.sqrt(np.mean(1.0 / (2.0 * spacing_s))))


def row_spacing(meas: Measurements) -> np.ndarray:
    """(N,) each row's spacing to its neighbour within the run (typical spacing where alone)."""
    assert meas.row_spacing_s is not None  # Measurements.__post_init__ fills it when it is not given
    return meas.row_spacing_s


def build_model(coefficients: dict[str, np.ndarray], effects: dict[str, dict[str, Any]],
                noise: dict[str, ChannelNoise], seed: int = 0) -> ImuModel:
    """An ImuModel from per-channel baseline coefficients (16 each) and effect parameters."""
    accel = np.stack([coefficients[c] for c in ACCEL_CHANNELS])
    gyro = np.stack([coefficients[c] for c in GYRO_CHANNELS])

    def density(channels: tuple[str, ...]) -> float:
        values = [noise[c].noise_density for c in channels if np.isfinite(noise[c].noise_density)]
        return float(np.mean(values)) if values else 0.0

    model = ImuModel(accel=TriadModel.from_coefficients(accel, density(ACCEL_CHANNELS)),
                     gyro=TriadModel.from_coefficients(gyro, density(GYRO_CHANNELS)), effects={}, seed=seed)
    return model.with_effects(**effects)


def check_model(model: ImuModel, meas: Measurements) -> dict[str, float]:
    """Per-channel RMS of measured minus the model's prediction (no noise, pinned run offsets)."""
    predicted, _ = model.deterministic_error(meas.imu_inputs())
    resid = meas.error - predicted
    return {c: float(np.sqrt(np.mean(resid[:, i] ** 2))) for i, c in enumerate(CHANNELS)}


def with_noise(model: ImuModel, white: np.ndarray, instability: np.ndarray | None,
               walk: np.ndarray | None) -> ImuModel:
    """The model with its noise model replaced: white density per triad (the mean of its channels'),
    and, when given, bias instability B and rate random walk K per channel (sensor units)."""
    import copy

    out = copy.deepcopy(model)
    out.accel.noise_density = float(np.mean(white[:3]))
    out.gyro.noise_density = float(np.mean(white[3:]))
    effects: dict[str, Any] = {"bias_instability": None, "bias_random_walk": None}
    if instability is not None and np.any(instability > 0):
        effects["bias_instability"] = {"b": {c: float(v) for c, v in zip(CHANNELS, instability)}}
    if walk is not None and np.any(walk > 0):
        effects["bias_random_walk"] = {"sigma_per_sqrt_s": {c: float(v) for c, v in zip(CHANNELS, walk)}}
    return out.with_effects(**effects)
