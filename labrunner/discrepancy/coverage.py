"""What a campaign can identify: facts about its design, and the causes/channels it cannot test.

A campaign without table rotation says nothing about gyro scale factors; one run says
nothing about turn-on bias; three orientations cannot separate accelerometer bias from
scale factor. These are decided from the design of the data (orientations, runs,
rates, temperatures), with messages that say what is missing: the baseline's here, each
cause's by its effect class (`Effect.coverage_gaps`); anything subtler is caught
numerically during the search (a term whose columns add nothing identifiable).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import ORIENTATIONS, UP_VECTORS
from labrunner.imu.effect import RAMP_C_PER_MIN
from labrunner.imu.effects import REGISTRY

from .measurements import Measurements
from .summary import weighted_percentile
from .temperature import branch_state, temperature_rate

AXES = ("x", "y", "z")
_ROTATING_DPS = 1.0


@dataclass
class Coverage:
    rows: int
    runs: int
    orientations: list[str]
    rotating: bool
    max_rate_dps: float
    chamber_logged: bool
    temperature_range_c: tuple[float, float]
    temperature_levels: int
    max_temperature_rate_c_per_min: float
    branch_overlap_c: float  # temperature span reached both while heating and while cooling
    branch_rows: tuple[int, int]  # heating rows, cooling rows inside the range reached heating
    orientation_changes_without_power_on: int
    power_ons_within_an_orientation: int
    temperature_quantum_c: float | None
    temperature_jitter_c: float = 0.0
    temperature_smoothing_s: float = 0.0
    power_on_source: str = "column"  # "column" (power_on column or store events) or "assumed" (run changes)
    run_changes_without_power_on: int = 0
    not_identifiable: list[str] = field(default_factory=list)
    excluded: dict[str, set[str]] = field(default_factory=dict)  # cause -> channels it cannot be tested on
    notes: list[str] = field(default_factory=list)
    # Orientation facts the effects' identifiability depends on (labrunner.imu.effect.CampaignFacts).
    vertical: tuple[bool, bool, bool] = (False, False, False)  # each body axis vertical in some orientation
    both_ways: tuple[bool, bool, bool] = (False, False, False)  # ... and both up and down
    bias_separable: bool = False  # the orientations separate accelerometer bias from scale factor

    def to_json(self) -> dict[str, Any]:
        return {
            "rows": self.rows, "runs": self.runs, "orientations": self.orientations,
            "table_rotation": self.rotating, "max_rate_dps": round(self.max_rate_dps, 3),
            "chamber_logged": self.chamber_logged,
            "temperature_range_c": [round(v, 2) for v in self.temperature_range_c],
            "temperature_levels": self.temperature_levels,
            "max_temperature_rate_c_per_min": round(self.max_temperature_rate_c_per_min, 3),
            "heating_and_cooling_overlap_c": round(self.branch_overlap_c, 2),
            "branch_rows": {"heating": self.branch_rows[0], "cooling_inside_heated_range": self.branch_rows[1]},
            "orientation_changes_without_power_on": self.orientation_changes_without_power_on,
            "power_ons_within_an_orientation": self.power_ons_within_an_orientation,
            "temperature_quantum_c": self.temperature_quantum_c,
            "temperature_jitter_c": round(self.temperature_jitter_c, 4),
            "temperature_smoothing_s": round(self.temperature_smoothing_s, 1),
            "power_ons": {"count": self.runs, "source": self.power_on_source,
                          "run_changes_without_power_on": self.run_changes_without_power_on},
            "notes": self.notes,
        }


def assess(meas: Measurements) -> Coverage:
    present = sorted({int(i) for i in np.unique(meas.orientation)})
    names = [ORIENTATIONS[i] for i in present]
    rate = np.abs(meas.table_rate_dps)
    rotating = bool(rate.max() > _ROTATING_DPS)
    temp = meas.temp_c
    dtdt = temperature_rate(meas.t_s, temp, meas.run) * 60.0
    h = branch_state(temp, 1.0, meas.remounts)
    # Rows that summarise raw samples count as their samples (the figures are the same as from the samples).
    n = meas.summary.samples if meas.summary is not None else None
    up, down = h > 0.5, h < -0.5
    heating, cooling = temp[up], temp[down]
    n_up = n[up] if n is not None else None
    n_down = n[down] if n is not None else None
    overlap = _branch_overlap(heating, cooling, n_up, n_down)
    inside_rows = (cooling >= heating.min()) & (cooling <= heating.max()) if heating.size else np.zeros(0, bool)
    inside = int(np.sum(inside_rows if n_down is None else n_down[inside_rows])) if heating.size else 0
    levels = _levels(temp, n)
    run_change = np.flatnonzero(meas.run[1:] != meas.run[:-1]) + 1
    orient_change = np.flatnonzero(meas.orientation[1:] != meas.orientation[:-1]) + 1
    cov = Coverage(
        rows=meas.sample_count, runs=int(np.unique(meas.run).size), orientations=names, rotating=rotating,
        max_rate_dps=float(rate.max()), chamber_logged=bool(np.isfinite(meas.chamber_c).any()),
        temperature_range_c=(float(temp.min()), float(temp.max())), temperature_levels=levels,
        max_temperature_rate_c_per_min=weighted_percentile(np.abs(dtdt), n, 99.5), branch_overlap_c=overlap,
        branch_rows=(int(heating.size if n_up is None else n_up.sum()), inside),
        orientation_changes_without_power_on=int(np.setdiff1d(orient_change, run_change).size),
        power_ons_within_an_orientation=int(np.setdiff1d(run_change, orient_change).size),
        temperature_quantum_c=meas.temperature_quantum_c, temperature_jitter_c=meas.temperature_jitter_c,
        temperature_smoothing_s=meas.temperature_smoothing_s, power_on_source=meas.power_on_source,
        run_changes_without_power_on=meas.continuous_run_changes,
    )
    _judge(cov, present)
    return cov


def _levels(temp: np.ndarray, samples: np.ndarray | None = None) -> int:
    """Distinct temperature levels: 2 degC bins holding at least 0.5 % of the rows (of the samples
    when rows summarise them)."""
    bins = np.floor(temp / 2.0).astype(np.int64)
    if samples is None:
        _, counts = np.unique(bins, return_counts=True)
        total = temp.size
    else:
        keys, inverse = np.unique(bins, return_inverse=True)
        counts = np.bincount(inverse, weights=samples, minlength=keys.size)
        total = int(samples.sum())
    return int(np.sum(counts >= max(0.005 * total, 3)))


def _branch_overlap(heating: np.ndarray, cooling: np.ndarray, n_heating: np.ndarray | None = None,
                    n_cooling: np.ndarray | None = None) -> float:
    if heating.size < 10 or cooling.size < 10:
        return 0.0
    lo = max(weighted_percentile(heating, n_heating, 2), weighted_percentile(cooling, n_cooling, 2))
    hi = min(weighted_percentile(heating, n_heating, 98), weighted_percentile(cooling, n_cooling, 98))
    return float(max(hi - lo, 0.0))


def _exclude(cov: Coverage, cause: str, channels: tuple[str, ...] | list[str], message: str) -> None:
    cov.excluded.setdefault(cause, set()).update(channels)
    if message not in cov.not_identifiable:
        cov.not_identifiable.append(message)


def _judge(cov: Coverage, present: list[int]) -> None:
    up = UP_VECTORS[present]  # (k, 3)
    vertical = [bool(np.any(up[:, j] != 0)) for j in range(3)]
    both = [bool(np.any(up[:, j] > 0) and np.any(up[:, j] < 0)) for j in range(3)]
    static = np.column_stack([np.ones(len(present)), up])
    rank = int(np.linalg.matrix_rank(static))
    expected = 1 + sum(vertical)
    cov.vertical = (vertical[0], vertical[1], vertical[2])
    cov.both_ways = (both[0], both[1], both[2])
    cov.bias_separable = rank >= expected

    # The baseline's own blind spots.
    for j, axis in enumerate(AXES):
        if not vertical[j]:
            cov.not_identifiable.append(
                f"accelerometer scale factor/misalignment along {axis} (S_x{axis}, S_y{axis}, S_z{axis}): "
                f"the {axis} axis was never vertical")
            if cov.rotating:
                cov.not_identifiable.append(f"gyro scale factor/misalignment about {axis}: no rotation about the "
                                            f"{axis} axis (never vertical)")
    if rank < expected:
        cov.not_identifiable.append(
            "accelerometer bias vs scale factor/misalignment: with orientations " + ", ".join(cov.orientations)
            + " no axis was both up and down, so the bias is identifiable only in combination with them")
    if not cov.rotating:
        cov.not_identifiable.append("gyro scale factor and misalignment: no table rotation in the data")
    if cov.temperature_levels < 4 and cov.max_temperature_rate_c_per_min < RAMP_C_PER_MIN:
        cov.not_identifiable.append(
            f"the cubic temperature dependence of biases and scale factors: {cov.temperature_levels} temperature "
            f"level(s); only terms up to degree {max(cov.temperature_levels - 1, 0)} are determined")

    # Each effect's: what it needs to be identifiable, in its own words.
    for name, effect in REGISTRY.items():
        for gap in effect.coverage_gaps(cov):
            if gap.channels:
                _exclude(cov, name, gap.channels, gap.message)
            elif gap.message not in cov.not_identifiable:
                cov.not_identifiable.append(gap.message)

    if not cov.chamber_logged:
        cov.notes.append("chamber_c is empty: no cause needs it (all errors are modelled against the IMU's own "
                         "temperature sensor)")
    if cov.orientation_changes_without_power_on == 0 and cov.runs > 1 and len(present) > 1:
        cov.notes.append("every orientation change coincides with a power-on: per-orientation effects "
                         "(g-sensitivity, accelerometer squared-force) are also explained by per-run offsets")
    if cov.power_on_source == "assumed":
        cov.notes.append(
            f"power-ons assumed: the data has no power_on column, so each change of run after a gap in time was "
            f"taken as a power-on ({cov.runs - 1} after the first row)"
            + (f"; {cov.run_changes_without_power_on} change(s) of run without a gap were taken as one continuous "
               "recording (time since power-on runs on)" if cov.run_changes_without_power_on else ""))
    elif cov.run_changes_without_power_on:
        cov.notes.append(f"{cov.run_changes_without_power_on} change(s) of run without a power_on mark: one "
                         "continuous recording there (time since power-on runs on)")
    if cov.temperature_smoothing_s:
        cov.notes.append(f"imu_temp_c jitters by {cov.temperature_jitter_c:.3f} degC from row to row: heating/"
                         f"cooling, dT/dt and the errors' temperature use its centred "
                         f"{cov.temperature_smoothing_s:.0f} s moving mean")
    elif cov.temperature_quantum_c:
        cov.notes.append(f"imu_temp_c is quantised to {cov.temperature_quantum_c:g} degC: heating/cooling is "
                         "judged on the de-dithered temperature")
