"""Ramp campaigns: the plan of one orientation's slow ramp with the rate schedule repeated along it.

With a `ramp:` section a procedure does not soak at each temperature. Per orientation the chamber
is brought to the first temperature of the range and soaked there once; then the sequencer moves the
setpoint with every record step along a straight line at `ramp.c_per_min` (a staircase of a fraction
of a degree per step: a slow ramp on any controller, with no ramp program to configure) while the
table repeats the rate schedule, until the far end of the range. Each step's planned temperature is
the ramp's setpoint when the step starts; its bin (`bin_c` wide, from the start of the range) tags it,
and the calibration cuts the continuous records into temperature bins of the same width
(`labrunner.calibration.records`, `ramp_bin_c`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RampPoint:
    """One record step along a ramp."""

    temperature_c: float  # the setpoint when the step starts
    bin_index: int  # floor(|T - start| / bin_c)
    rate_index: int  # position in the rate schedule


def ramp_points(start_c: float, stop_c: float, c_per_min: float, bin_c: float,
                step_durations_s: Sequence[float]) -> list[RampPoint]:
    """The steps of one ramp from `start_c` to `stop_c`: the rate schedule (one duration per rate: settle,
    spin-up and record) repeated while the setpoint moves at `c_per_min`, the last step at `stop_c`."""
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
                return out
            out.append(RampPoint(round(start_c + sign * moved, 3), int(math.floor(moved / bin_c + 1e-9)), ri))
            elapsed += d


def ramp_duration_s(start_c: float, stop_c: float, c_per_min: float) -> float:
    """How long the chamber takes to ramp the range at `c_per_min`."""
    return abs(stop_c - start_c) / c_per_min * 60.0
