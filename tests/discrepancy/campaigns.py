"""Simulated campaigns with hidden effects, for the diagnosis tests and the benchmark.

Each `draw_<cause>` picks random parameters (from the given seeded generator) within
realistic ranges and returns the sims effect and what a correct diagnosis must report.
The campaign is then synthesized with that effect switched on and handed to
`diagnose` as rows only: the analysis never sees these settings.

Two styles of campaign:
- "sims": this project's own synthesizer output, averaged 1 s rows, ramps logged only
  where the cause needs them (5 s rows there, to keep the tests quick);
- "reallog": what a real logger produces: 1 s rows throughout, ramps included, the IMU
  temperature rounded to a coarse step, and a slow random-walk bias drift as a nuisance.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from labrunner.imu.model import ACCEL_CHANNELS, CHANNELS, GYRO_CHANNELS, default_imu_model
from labrunner.sims.campaign import CampaignPlan, synthesize
from labrunner.sims.world import SimLabConfig

TEMPERATURES = (-25.0, -5.0, 15.0, 35.0, 55.0)
LOG_TEMPERATURES = (-25.0, 0.0, 30.0, 55.0)  # real logs include the ramps: four soaks cover the range
RATES = (50.0, 100.0, 50.0, 0.0, -50.0, -100.0, -50.0, 0.0)


@dataclass
class Hidden:
    """A hidden effect and what a correct diagnosis reports about it."""

    cause: str
    effect: dict[str, Any]  # keyword arguments of the sims effect
    channels: set[str]
    needs_ramps: bool = False
    power_cycle: str = "orientation"
    many_temperatures: bool = False
    truth: dict[str, Any] = field(default_factory=dict)


def _pick(rng: np.random.Generator, pool: tuple[str, ...], low: int, high: int) -> list[str]:
    n = int(rng.integers(low, high + 1))
    return sorted(rng.choice(pool, size=n, replace=False).tolist(), key=CHANNELS.index)


def _signed(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi) * rng.choice([-1.0, 1.0]))


def _by_channel(rng: np.random.Generator, channels: list[str], accel: tuple[float, float],
                gyro: tuple[float, float], signed: bool = True) -> dict[str, float]:
    out = {}
    for c in channels:
        lo, hi = accel if c in ACCEL_CHANNELS else gyro
        out[c] = _signed(rng, lo, hi) if signed else float(rng.uniform(lo, hi))
    return out


def draw_thermal_lag(rng: np.random.Generator) -> Hidden:
    tau = float(np.exp(rng.uniform(np.log(60.0), np.log(600.0))))
    chans = _pick(rng, CHANNELS, 1, 3)
    return Hidden("thermal_lag", {"tau_s": tau, "channels": chans}, set(chans), needs_ramps=True)


def draw_hysteresis(rng: np.random.Generator) -> Hidden:
    chans = _pick(rng, CHANNELS, 1, 2)
    width = _by_channel(rng, chans, (1.0e-3, 3.0e-3), (0.03, 0.15))
    return Hidden("hysteresis", {"width": width, "travel_c": float(rng.uniform(1.0, 4.0))}, set(chans))


def draw_warmup(rng: np.random.Generator) -> Hidden:
    chans = _pick(rng, CHANNELS, 1, 2)
    amp = _by_channel(rng, chans, (1.5e-3, 6.0e-3), (0.05, 0.3))
    return Hidden("warmup", {"tau_s": float(rng.uniform(150.0, 1200.0)), "amplitude": amp}, set(chans),
                  needs_ramps=True)


def draw_turn_on_bias(rng: np.random.Generator) -> Hidden:
    chans = _pick(rng, CHANNELS, 1, 2)
    sigma = _by_channel(rng, chans, (1.0e-3, 4.0e-3), (0.02, 0.1), signed=False)
    return Hidden("turn_on_bias", {"sigma": sigma}, set(chans), power_cycle="temperature")


def draw_g_sensitivity(rng: np.random.Generator) -> Hidden:
    m = np.zeros((3, 3))
    rows = _pick(rng, GYRO_CHANNELS, 1, 3)
    for c in rows:
        m[GYRO_CHANNELS.index(c), int(rng.integers(0, 3))] = _signed(rng, 0.015, 0.08)
    return Hidden("g_sensitivity", {"matrix_dps_per_g": m.tolist()}, set(rows), power_cycle="temperature")


def draw_scale_nonlinearity(rng: np.random.Generator) -> Hidden:
    chans = _pick(rng, CHANNELS, 1, 2)
    k2 = _by_channel(rng, chans, (0.8e-3, 3.0e-3), (8e-6, 4e-5))
    # An accelerometer's squared input changes only with the orientation: with power-ons only at
    # the remounts it is confounded with turn-on bias (the diagnosis says so); power-cycling at
    # every temperature lets it be named alone.
    power_cycle = "temperature" if any(c in ACCEL_CHANNELS for c in chans) else "orientation"
    return Hidden("scale_nonlinearity", {"k2_per_dps": k2}, set(chans), power_cycle=power_cycle)


def draw_temperature_nonlinearity(rng: np.random.Generator) -> Hidden:
    chans = _pick(rng, CHANNELS, 1, 2)
    amp = _by_channel(rng, chans, (1.5e-3, 4.0e-3), (0.06, 0.2))
    effect = {"amplitude": amp, "center_c": float(rng.uniform(0.0, 30.0)), "width_c": float(rng.uniform(3.0, 8.0))}
    return Hidden("temperature_nonlinearity", effect, set(chans), needs_ramps=True)


def draw_lever_arm(rng: np.random.Generator) -> Hidden:
    chans = _pick(rng, ACCEL_CHANNELS, 1, 2)
    r = [0.0, 0.0, 0.0]
    for c in chans:
        r[ACCEL_CHANNELS.index(c)] = _signed(rng, 0.02, 0.08)
    return Hidden("lever_arm", {"r_m": r}, set(chans))


DRAWS = {
    "thermal_lag": draw_thermal_lag, "hysteresis": draw_hysteresis, "warmup": draw_warmup,
    "turn_on_bias": draw_turn_on_bias, "g_sensitivity": draw_g_sensitivity,
    "scale_nonlinearity": draw_scale_nonlinearity, "temperature_nonlinearity": draw_temperature_nonlinearity,
    "lever_arm": draw_lever_arm,
}


def drift_effect(rng: np.random.Generator) -> dict[str, Any]:
    """A slow random-walk bias drift (the nuisance of real logs): bias instability of a few
    0.1 mg and 0.01 deg/s over a two-day campaign."""
    sigma = {c: float(rng.uniform(1.5e-7, 4e-7)) for c in ACCEL_CHANNELS}
    sigma |= {c: float(rng.uniform(1.5e-5, 4e-5)) for c in GYRO_CHANNELS}
    return {"sigma_per_sqrt_s": sigma}


def plan_for(hidden: list[Hidden], style: str, rng: np.random.Generator, **overrides: Any) -> CampaignPlan:
    ramps = style == "reallog" or any(h.needs_ramps for h in hidden)
    power_cycle = "temperature" if any(h.power_cycle == "temperature" for h in hidden) else "orientation"
    kwargs: dict[str, Any] = {
        "temperatures_c": LOG_TEMPERATURES if style == "reallog" else TEMPERATURES, "rates_dps": RATES,
        "average_s": 1.0, "log_ramps": ramps, "soak_window_s": 300.0,
        "ramp_row_s": 1.0 if style == "reallog" else 5.0, "power_cycle": power_cycle, "soak_tolerance_c": 0.25,
        "temperature_quantum_c": float(rng.choice([0.1, 0.25])) if style == "reallog" else None,
    }
    kwargs.update(overrides)
    return CampaignPlan(**kwargs)


def campaign(hidden: list[Hidden], style: str, seed: int, **overrides: Any) -> tuple[pd.DataFrame, SimLabConfig]:
    """Synthesize a campaign with the hidden effects (and, for real logs, drift) switched on."""
    rng = np.random.default_rng([seed, 0xD1A6])
    effects = {h.cause: h.effect for h in hidden}
    if style == "reallog":
        effects["bias_random_walk"] = drift_effect(rng)
    model = default_imu_model(seed=seed).with_effects(**effects)
    config = SimLabConfig(seed=seed, imu_model=model)
    return synthesize(plan_for(hidden, style, rng, **overrides), config), config
