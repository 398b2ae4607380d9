"""Synthesize a campaign without instruments: the simulated lab's physics run open-loop.

The sequencer's dry run exercises the protocols; this exercises only the physics
(`SimWorld`, `ImuModel`) and is fast, so analysis tests and benchmarks can make the
campaign designs they need: serpentine temperature order (heating and cooling
branches), power cycles at every temperature, ramps logged as averaged 1 s rows,
quantised temperature, no chamber column, no table. The output has the columns of
the campaign CSV format.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from labrunner.drivers.imu_frames import ACCEL_LSB_G, GYRO_LSB_DPS, TEMP_LSB_C
from labrunner.imu.model import ORIENTATIONS, ModelState

from .world import SimLabConfig, SimWorld

CSV_COLUMNS = (
    "t_s", "run", "orientation", "chamber_c", "imu_temp_c", "table_rate_dps",
    "ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps",
)


def triangular_rates(max_dps: float = 100.0, step_dps: float = 10.0) -> list[float]:
    """0 -> +max -> -max -> 0 in steps (the paper's triangular schedule): 4*max/step steps."""
    n = int(round(max_dps / step_dps))
    up = [step_dps * k for k in range(1, n + 1)]
    down = [max_dps - step_dps * k for k in range(1, 2 * n + 1)]
    back = [-max_dps + step_dps * k for k in range(1, n + 1)]
    return up + down + back


@dataclass
class CampaignPlan:
    """What to run; defaults give a small but complete six-position thermal campaign."""

    orientations: Sequence[str] = ORIENTATIONS
    temperatures_c: Sequence[float] = (-25.0, -5.0, 15.0, 35.0, 55.0)
    rates_dps: Sequence[float] = field(default_factory=lambda: triangular_rates(100.0, 50.0))
    temperature_order: str = "serpentine"  # or "ascending"
    settle_s: float = 5.0
    record_s: float = 60.0
    sample_rate_hz: float = 50.0
    average_s: float | None = None  # None: raw samples; else rows are means over this many seconds
    soak_tolerance_c: float = 0.1  # IMU temperature change over soak_window_s that counts as stable
    soak_window_s: float = 600.0
    soak_max_s: float = 4 * 3600.0
    log_ramps: bool = False  # also log (averaged) rows while ramping and soaking
    ramp_row_s: float = 1.0
    power_cycle: str = "orientation"  # "orientation": at each remount; "temperature": also at every temperature
    power_off_s: float = 600.0  # time powered down at a power cycle (the die cools back to the case)
    remount_at_ambient: bool = True
    chamber_column: bool = True
    table: bool = True
    temperature_quantum_c: float | None = None  # quantise imu_temp_c like a coarse logger
    chamber_quantum_c: float = 0.1


def synthesize(plan: CampaignPlan, sim: SimLabConfig | None = None,
               progress: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Run the plan on a simulated lab and return campaign rows (CSV columns)."""
    sim = sim or SimLabConfig()
    if plan.temperature_order not in ("serpentine", "ascending"):
        raise ValueError("temperature_order must be 'serpentine' or 'ascending'")
    if plan.power_cycle not in ("orientation", "temperature"):
        raise ValueError("power_cycle must be 'orientation' or 'temperature'")
    world = SimWorld(SimLabConfig(**{**sim.__dict__, "orientation": plan.orientations[0]}), start_t=0.0)
    model = sim.imu_model
    rng = np.random.default_rng([sim.seed, 0x5CA1E])
    fs = plan.sample_rate_hz
    sigma_full = model.noise_sigma(fs)
    state = ModelState()
    chunks: list[pd.DataFrame] = []
    t = 0.0

    def emit(times: np.ndarray, per_row_samples: float) -> None:
        """Evaluate the IMU at `times`; rows stand for means of `per_row_samples` raw samples."""
        nonlocal state
        if times.size == 0:
            return
        world.advance(float(times[-1]) + 1.0)
        inputs = world.imu_inputs(times)
        err, state = model.deterministic_error(inputs, state, rng)
        truth = np.concatenate([inputs.force_g, inputs.rate_dps], axis=1)
        out = truth + err + rng.standard_normal(err.shape) * (sigma_full / np.sqrt(per_row_samples))[None, :]
        temp = inputs.temp_c
        if per_row_samples == 1:
            out[:, :3] = np.rint(out[:, :3] / ACCEL_LSB_G) * ACCEL_LSB_G
            out[:, 3:] = np.rint(out[:, 3:] / GYRO_LSB_DPS) * GYRO_LSB_DPS
            temp = np.rint(temp / TEMP_LSB_C) * TEMP_LSB_C
        if plan.temperature_quantum_c:
            temp = np.rint(temp / plan.temperature_quantum_c) * plan.temperature_quantum_c
        air = world.air_at(times)
        chamber = np.rint(air / plan.chamber_quantum_c) * plan.chamber_quantum_c if plan.chamber_column \
            else np.full(times.size, np.nan)
        rate = world.table.rate_at(times)
        rate = np.rint(rate / world.table.p.encoder_resolution_dps) * world.table.p.encoder_resolution_dps
        chunks.append(pd.DataFrame({
            "t_s": times, "run": world.run, "orientation": world.orientation, "chamber_c": chamber,
            "imu_temp_c": temp, "table_rate_dps": rate,
            "ax_g": out[:, 0], "ay_g": out[:, 1], "az_g": out[:, 2],
            "gx_dps": out[:, 3], "gy_dps": out[:, 4], "gz_dps": out[:, 5],
        }))

    def wait(duration: float, log: bool) -> None:
        """Let time pass; the IMU state is tracked at 1 s (and logged if asked)."""
        nonlocal t, state
        step = plan.ramp_row_s
        times = t + step * np.arange(1, int(duration / step) + 1)
        if log and world.powered:
            emit(times, per_row_samples=step * fs)
        elif world.powered and times.size:
            world.advance(float(times[-1]))
            _, state = model.deterministic_error(world.imu_inputs(times), state, rng)
        t += duration
        world.advance(t)

    def soak(setpoint: float) -> None:
        world.chamber.set_setpoint(setpoint)
        temps: list[float] = []
        waited = 0.0
        while waited < plan.soak_max_s:
            wait(60.0, plan.log_ramps)
            waited += 60.0
            temps.append(float(world.imu_temperature_at(np.array([t]))[0]))
            n = int(plan.soak_window_s / 60.0)
            if abs(world.chamber.air_c - setpoint) < 0.5 and len(temps) > n and \
                    max(temps[-n - 1:]) - min(temps[-n - 1:]) < plan.soak_tolerance_c:
                return

    def power_cycle(orientation: str) -> None:
        nonlocal t
        world.power_off()
        t += plan.power_off_s
        world.advance(t)
        world.remount(orientation, t)

    ambient = sim.chamber.ambient_c
    for i, orient in enumerate(plan.orientations):
        temps = sorted(plan.temperatures_c)
        if plan.temperature_order == "serpentine" and i % 2 == 1:
            temps = temps[::-1]
        if i > 0:
            if plan.remount_at_ambient:
                soak(ambient)
            power_cycle(orient)
        for temp in temps:
            if progress:
                progress(f"{orient} {temp:+.0f} C")
            soak(temp)
            if plan.power_cycle == "temperature":
                power_cycle(orient)
                wait(plan.soak_window_s, plan.log_ramps)
            rates = plan.rates_dps if plan.table else [0.0]
            for rate in rates:
                world.table.command(t, rate if plan.table else 0.0)
                wait(plan.settle_s + abs(rate) / world.table.p.accel_dps2, plan.log_ramps)
                if plan.average_s:
                    n_rows = int(round(plan.record_s / plan.average_s))
                    times = t + plan.average_s * (np.arange(n_rows) + 0.5)
                    emit(times, per_row_samples=plan.average_s * fs)
                else:
                    n = int(round(plan.record_s * fs))
                    times = t + np.arange(n) / fs
                    emit(times, per_row_samples=1)
                t += plan.record_s
                world.advance(t)
            world.table.command(t, 0.0)
    frame = pd.concat(chunks, ignore_index=True)
    frame["orientation"] = pd.Categorical(frame["orientation"], categories=list(ORIENTATIONS))
    return frame.loc[:, list(CSV_COLUMNS)]
