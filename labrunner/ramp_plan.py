"""Ramp campaigns: the plan of one orientation's slow ramp with the rate schedule repeated along it.

With a `ramp:` section a procedure does not soak at each temperature. Per orientation the chamber
is brought to the first temperature of the range and soaked there once; then the sequencer moves the
setpoint with every record step along a straight line at `ramp.c_per_min` (a staircase of a fraction
of a degree per step: a slow ramp on any controller, with no ramp program to configure) while the
table repeats the rate schedule, until the far end of the range. Each step's planned temperature is
the ramp's setpoint when the step starts; its bin (`bin_c` wide, from the start of the range) tags it,
and the calibration cuts the continuous records into temperature bins of the same width
(`labrunner.calibration.records`, `ramp_bin_c`).

The bin tag is stored with the step without a column of its own: a step row holds its plan index and
the campaign row the procedure text, whose plan gives each index its bin (`stored_bins` reads it back).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

if TYPE_CHECKING:
    from labrunner.store import Store

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RampPoint:
    """One record step along a ramp."""

    temperature_c: float  # the setpoint when the step starts
    bin_index: int  # floor(|T - start| / bin_c)
    rate_index: int  # position in the rate schedule


def ramp_points(start_c: float, stop_c: float, c_per_min: float, bin_c: float,
                step_durations_s: Sequence[float], end_hold_s: float = 0.0) -> list[RampPoint]:
    """The steps of one ramp from `start_c` to `stop_c`: the rate schedule (one duration per rate: settle,
    spin-up and record) repeated while the setpoint moves at `c_per_min`, the last step at `stop_c`; then,
    with `end_hold_s`, the schedule repeated at `stop_c` for that long (whole passes) while the IMU catches up
    with the far end, so that an orientation ramped up and one ramped down cover the same temperatures."""
    if not step_durations_s:
        return []
    span = abs(stop_c - start_c)
    if span == 0.0:  # a ramp of no width is one pass of the schedule at its temperature
        return [RampPoint(start_c, 0, ri) for ri in range(len(step_durations_s))]
    sign = 1.0 if stop_c >= start_c else -1.0
    out: list[RampPoint] = []
    elapsed = 0.0
    while True:
        for ri, d in enumerate(step_durations_s):
            moved = c_per_min * elapsed / 60.0
            if moved > span + 1e-9:
                return out + _hold(out[-1], end_hold_s, step_durations_s)
            out.append(RampPoint(round(start_c + sign * moved, 3), int(math.floor(moved / bin_c + 1e-9)), ri))
            elapsed += d


def _hold(last: RampPoint, hold_s: float, step_durations_s: Sequence[float]) -> list[RampPoint]:
    """Whole passes of the schedule at the ramp's last setpoint and bin, for at least `hold_s`."""
    per_pass = float(sum(step_durations_s))
    passes = int(math.ceil(hold_s / per_pass - 1e-9)) if hold_s > 0 and per_pass > 0 else 0
    return [RampPoint(last.temperature_c, last.bin_index, ri) for _ in range(passes)
            for ri in range(len(step_durations_s))]


def ramp_duration_s(start_c: float, stop_c: float, c_per_min: float) -> float:
    """How long the chamber takes to ramp the range at `c_per_min`."""
    return abs(stop_c - start_c) / c_per_min * 60.0


def stored_bins(store: Store, campaign_id: int) -> pd.DataFrame:
    """The stored steps of a campaign with their temperature-bin tag: `idx`, `orientation`, `temperature_c`,
    `t_start`, `t_end`, `bin_index` (the plan's, from the stored procedure; -1 for a campaign without a
    ramp, whose steps are soaks) and `bin_lo_c`, `bin_hi_c` (the bin's setpoint range)."""
    from labrunner.procedure import parse_procedure

    info = store.campaign(campaign_id)
    proc = parse_procedure(info.procedure_text, info.procedure_path or f"campaign {campaign_id}")
    plan = proc.steps()
    steps = store.steps_frame(campaign_id)[["idx", "orientation", "temperature_c", "t_start", "t_end"]].copy()
    ramp = proc.model.ramp
    idx = steps["idx"].to_numpy(dtype=np.int64)
    if ramp is None:
        steps["bin_index"] = -1
        steps["bin_lo_c"] = steps["bin_hi_c"] = np.nan
        return steps
    bins = np.array([plan[i].temperature_index for i in idx], dtype=np.int64)
    starts = np.array([proc.temperatures_for(plan[i].orientation_index)[0] for i in idx], dtype=float)
    sign = np.array([1.0 if proc.temperatures_for(plan[i].orientation_index)[-1] >= s else -1.0
                     for i, s in zip(idx, starts, strict=True)])
    edge = starts + sign * bins * ramp.bin_c
    steps["bin_index"] = bins
    steps["bin_lo_c"] = np.minimum(edge, edge + sign * ramp.bin_c)
    steps["bin_hi_c"] = np.maximum(edge, edge + sign * ramp.bin_c)
    return steps
