"""Procedures: YAML -> validated model -> the expanded list of record steps.

A procedure states the temperatures (a list or start/stop/step, and the order they
are visited in), how a soak is judged, the orientations with the operator's prompt
for each remount, the rate schedule (a list or the paper's triangular pattern),
settle and record durations, the IMU sample rate, safety limits, the fault policy
and the fit to run at the end. Errors name the file, line and key.

The loop order is orientation (a remount: six per campaign, at ambient) > temperature
(a soak) > rate (a record step). With the serpentine order, temperatures are visited
upwards for one orientation and downwards for the next, so the data hold both
heating and cooling branches.
"""

from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, ClassVar, Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from labrunner.domain import ORIENTATIONS
from labrunner.ramp_plan import ramp_points
from labrunner.yaml_config import ConfigError, Range, RangedModel, load_yaml, read_text, validate

log = logging.getLogger(__name__)

SHIPPED_PACKAGE = "labrunner.procedures"  # the repository's procedures/, installed as package data

OrientationName = Literal["x_up", "x_down", "y_up", "y_down", "z_up", "z_down"]

DEFAULT_PROMPTS = {
    "x_up": "Mount the IMU with its x axis pointing up.",
    "x_down": "Mount the IMU with its x axis pointing down.",
    "y_up": "Mount the IMU with its y axis pointing up.",
    "y_down": "Mount the IMU with its y axis pointing down.",
    "z_up": "Mount the IMU with its z axis pointing up.",
    "z_down": "Mount the IMU with its z axis pointing down.",
}


def triangular_rates(max_dps: float, step_dps: float) -> list[float]:
    """The paper's triangular schedule: 0 -> +max -> -max -> 0 in steps, 4*max/step rates."""
    n = int(round(max_dps / step_dps))
    up = [step_dps * k for k in range(1, n + 1)]
    down = [max_dps - step_dps * k for k in range(1, 2 * n + 1)]
    back = [-max_dps + step_dps * k for k in range(1, n + 1)]
    return [round(r, 9) + 0.0 for r in up + down + back]


# Every duration, rate, count and temperature of a procedure: finite and physical, so nothing a
# procedure asks for can spin (a 1e-9 s poll), never end (an infinite soak) or overflow (1e308 s
# records). Checked before any other check computes with them; `labrunner check` reports each with
# file, line, key, value and this range. Counts that follow from several keys (temperatures, rates,
# steps, frames) are limited in `_cross_checks`.
TEMPERATURE_C = Range(-100.0, 250.0, "C")  # beyond any thermal chamber an IMU is calibrated in
RATE_DPS = Range(-10000.0, 10000.0, "deg/s")
RANGES: dict[str, Range] = {
    "temperatures.list_c": TEMPERATURE_C,
    "temperatures.start_c": TEMPERATURE_C,
    "temperatures.stop_c": TEMPERATURE_C,
    "temperatures.step_c": Range(0.1, 200.0, "C"),
    "soak.tolerance_c": Range(0.01, 10.0, "C"),
    "soak.stable_window_s": Range(1.0, 86400.0, "s"),
    "soak.max_wait_s": Range(1.0, 7 * 86400.0, "s"),
    "soak.poll_s": Range(0.1, 3600.0, "s"),
    "soak.predict_window_s": Range(10.0, 86400.0, "s"),
    "soak.predict_horizon_s": Range(1.0, 86400.0, "s"),
    "soak.predict_tau_max_s": Range(10.0, 7 * 86400.0, "s"),
    "soak.predict_tolerance_c": Range(0.01, 10.0, "C"),
    "soak.predict_lag_s": Range(1.0, 86400.0, "s"),
    "soak.predict_lag_tolerance_c": Range(0.001, 10.0, "C"),
    "ramp.c_per_min": Range(0.01, 10.0, "C/min"),
    "ramp.bin_c": Range(0.1, 20.0, "C"),
    "ramp.end_hold_s": Range(0.0, 86400.0, "s"),
    "remount_c": TEMPERATURE_C,
    "remount_s": Range(0.0, 86400.0, "s"),
    "rates.list_dps": RATE_DPS,
    "rates.triangular.max_dps": Range(0.01, 10000.0, "deg/s"),
    "rates.triangular.step_dps": Range(0.01, 10000.0, "deg/s"),
    "settle_s": Range(0.0, 3600.0, "s"),
    "record_s": Range(0.01, 86400.0, "s"),
    "record_poll_s": Range(0.1, 3600.0, "s"),
    "sample_rate_hz": Range(0.1, 10000.0, "Hz"),
    "safety.chamber_min_c": TEMPERATURE_C,
    "safety.chamber_max_c": TEMPERATURE_C,
    "safety.max_rate_dps": Range(0.01, 10000.0, "deg/s"),
    "safety.imu_max_temp_c": TEMPERATURE_C,
    "faults.max_dropped_frames": Range(0, 10**6, "frames", integer=True),
    "faults.max_rerecords": Range(0, 100, integer=True),
    "monitor.average_s": Range(0.01, 3600.0, "s"),
    "mount_check.max_angle_deg": Range(0.1, 45.0, "deg"),
    "mount_check.gravity_tolerance_g": Range(0.001, 0.5, "g"),
    "mount_check.read_s": Range(0.2, 60.0, "s"),
    "mount_check.tries": Range(1, 20, integer=True),
    "resume.chamber_tolerance_c": Range(0.01, 20.0, "C"),
    "fit.polynomial_order": Range(0, 6, integer=True),
    "fit.thermal_lag_s": Range(1.0, 86400.0, "s", nullable=True),
}
MAX_TEMPERATURES = 500
MAX_RATES = 2000
MAX_STEPS = 200_000  # the paper's campaign has 4080
MAX_FRAMES_PER_RECORD = 5_000_000  # one record is held in memory (~40 bytes a frame)
MAX_SAMPLES = 1_000_000_000  # ~40 GB of store
MAX_LAB_TIME_S = 365 * 86400.0  # a year of lab time: a plan beyond it is a typo, not a campaign


class _Strict(RangedModel):
    RANGES: ClassVar[dict[str, Range]] = RANGES


class Temperatures(_Strict):
    SECTION: ClassVar[str] = "temperatures"
    list_c: list[float] | None = None
    start_c: float | None = None
    stop_c: float | None = None
    step_c: float | None = Field(None, gt=0)
    order: Literal["ascending", "descending", "serpentine"] = "serpentine"

    @model_validator(mode="after")
    def _one_form(self) -> Temperatures:
        ranged = (self.start_c, self.stop_c, self.step_c)
        if self.list_c is not None:
            if any(v is not None for v in ranged):
                raise ValueError("give either list_c or start_c/stop_c/step_c, not both")
            if not self.list_c:
                raise ValueError("list_c must name at least one temperature")
            if len(set(self.list_c)) != len(self.list_c):
                raise ValueError("list_c has a temperature twice")
        else:
            if any(v is None for v in ranged):
                raise ValueError("give list_c, or all of start_c, stop_c and step_c")
            if self.stop_c < self.start_c:  # type: ignore[operator]
                raise ValueError("stop_c must be >= start_c")
        return self

    def values(self) -> list[float]:
        if self.list_c is not None:
            return sorted(float(v) for v in self.list_c)
        n = int(math.floor((self.stop_c - self.start_c) / self.step_c + 1e-9))  # type: ignore[operator]
        return [round(self.start_c + k * self.step_c, 6) for k in range(n + 1)]  # type: ignore[operator]


class Soak(_Strict):
    SECTION: ClassVar[str] = "soak"
    tolerance_c: float = Field(0.3, gt=0)
    stable_window_s: float = Field(600.0, gt=0)
    max_wait_s: float = Field(3 * 3600.0, gt=0)
    on_timeout: Literal["continue", "pause", "abort"] = "pause"
    sensor: Literal["imu", "chamber"] = "imu"
    poll_s: float = Field(30.0, gt=0)
    # criterion predictive (labrunner.runner.soak_predict): done when the fitted approach of the IMU
    # temperature predicts less than predict_tolerance_c (default tolerance_c) of change over the horizon
    # (default: one record_s); fitted from the soak's start over at most the last predict_window_s
    criterion: Literal["spread", "predictive"] = "spread"
    predict_window_s: float = Field(600.0, gt=0)
    predict_tolerance_c: float | None = Field(None, gt=0)
    predict_horizon_s: float | None = Field(None, gt=0)
    predict_model: Literal["single", "double"] = "single"
    predict_tau_max_s: float = Field(7200.0, gt=0)
    # the sensing element's lag behind the IMU temperature sensor (s): the prediction then also holds the
    # element's mean offset from the reading over the horizon to predict_lag_tolerance_c (default
    # predict_tolerance_c)
    predict_lag_s: float | None = Field(None, gt=0)
    predict_lag_tolerance_c: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _window_fits(self) -> Soak:
        if self.stable_window_s > self.max_wait_s:
            raise ValueError("stable_window_s must not exceed max_wait_s")
        if self.poll_s > self.stable_window_s:
            raise ValueError("poll_s must not exceed stable_window_s")
        if self.criterion == "predictive":
            if self.sensor != "imu":
                raise ValueError("criterion predictive fits the IMU temperature: it needs sensor: imu")
            if self.predict_window_s > self.max_wait_s:
                raise ValueError("predict_window_s must not exceed max_wait_s")
            if self.predict_window_s < 8 * self.poll_s:
                raise ValueError("predict_window_s must hold at least 8 polls (8 * poll_s)")
        elif self.predict_lag_s is not None or self.predict_lag_tolerance_c is not None:
            raise ValueError("predict_lag_s and predict_lag_tolerance_c apply to criterion: predictive")
        return self


class Orientation(_Strict):
    SECTION: ClassVar[str] = "orientations"
    name: OrientationName
    prompt: str | None = None


class Triangular(_Strict):
    SECTION: ClassVar[str] = "rates.triangular"
    max_dps: float = Field(gt=0)
    step_dps: float = Field(gt=0)

    @model_validator(mode="after")
    def _whole_steps(self) -> Triangular:
        n = self.max_dps / self.step_dps
        if abs(n - round(n)) > 1e-9:
            raise ValueError("max_dps must be a whole number of step_dps")
        return self


class Rates(_Strict):
    SECTION: ClassVar[str] = "rates"
    list_dps: list[float] | None = None
    triangular: Triangular | None = None

    @model_validator(mode="after")
    def _one_form(self) -> Rates:
        if (self.list_dps is None) == (self.triangular is None):
            raise ValueError("give exactly one of list_dps or triangular")
        if self.list_dps is not None and not self.list_dps:
            raise ValueError("list_dps must name at least one rate")
        return self

    def values(self) -> list[float]:
        if self.list_dps is not None:
            return [float(v) for v in self.list_dps]
        assert self.triangular is not None
        return triangular_rates(self.triangular.max_dps, self.triangular.step_dps)


class Safety(_Strict):
    SECTION: ClassVar[str] = "safety"
    chamber_min_c: float = -40.0
    chamber_max_c: float = 85.0
    max_rate_dps: float = Field(300.0, gt=0)
    imu_max_temp_c: float = 85.0

    @model_validator(mode="after")
    def _ordered(self) -> Safety:
        if self.chamber_min_c >= self.chamber_max_c:
            raise ValueError("chamber_min_c must be below chamber_max_c")
        return self


class Faults(_Strict):
    SECTION: ClassVar[str] = "faults"
    policy: Literal["pause", "abort"] = "pause"
    # Never read: the drivers retry with the lab configuration's per-instrument settings. Refused
    # when written, so a procedure does not seem to set what it does not.
    retries: int | None = None
    backoff_s: float | None = None
    max_dropped_frames: int = Field(0, ge=0)  # per record step; more and the step is recorded again
    max_rerecords: int = Field(3, ge=0)  # attempts at one step before the fault policy applies

    @field_validator("retries", "backoff_s")
    @classmethod
    def _unused(cls, v: Any, info: ValidationInfo) -> Any:
        raise ValueError(f"is not used: the drivers' {info.field_name} are set per instrument in the lab "
                         f"configuration (chamber.{info.field_name}, table.{info.field_name}); remove it")


class Monitor(_Strict):
    SECTION: ClassVar[str] = "monitor"
    enabled: bool = True  # log 1 s means of the IMU (and the chamber) while ramping and soaking
    average_s: float = Field(1.0, gt=0)


class MountCheck(_Strict):
    """After each remount (and at preflight) the accelerometer must show the planned axis up."""
    SECTION: ClassVar[str] = "mount_check"

    enabled: bool = True
    max_angle_deg: float = Field(10.0, gt=0, le=45)  # planned up axis vs measured specific force (45: ambiguous)
    gravity_tolerance_g: float = Field(0.2, gt=0, le=0.5)  # |a| within this of 1 g (an uncalibrated bias: 0.1 g)
    read_s: float = Field(1.0, ge=0.2, le=60)  # of IMU frames averaged for one check
    tries: int = Field(3, ge=1, le=20)  # remount prompts before the campaign pauses


class Resume(_Strict):
    """What `labrunner resume` may skip when the lab was left running."""
    SECTION: ClassVar[str] = "resume"

    in_place: bool = True  # IMU still mounted as planned and chamber near the setpoint: no remount, no ramp
    chamber_tolerance_c: float = Field(2.0, gt=0, le=20)  # "near": within this of the next step's setpoint


class Ramp(_Strict):
    """A ramp campaign (labrunner.ramp_plan): per orientation one slow ramp across the temperatures'
    range, the rate schedule repeated along it, instead of a soak at each temperature."""

    SECTION: ClassVar[str] = "ramp"
    c_per_min: float = Field(gt=0)
    bin_c: float = Field(1.0, gt=0)
    end_hold_s: float = Field(0.0, ge=0)  # the schedule repeated at the far end while the IMU catches up


class Fit(_Strict):
    SECTION: ClassVar[str] = "fit"
    run: bool = True
    polynomial_order: int = Field(3, ge=0, le=6)
    rbf: bool = True
    # The sensing element's lag behind its temperature sensor (labrunner.calibration.thermal_lag_fit): a
    # time constant (s; the diagnosis's thermal_lag finding), or thermal_lag_auto (searched by the fit).
    thermal_lag_s: float | None = None
    thermal_lag_auto: bool = False

    @model_validator(mode="after")
    def _one_lag(self) -> Fit:
        if self.thermal_lag_s is not None and self.thermal_lag_auto:
            raise ValueError("give either thermal_lag_s or thermal_lag_auto: true, not both")
        return self

    @property
    def thermal_lag(self) -> float | str | None:
        """The fit's `thermal_lag_s` option: seconds, "auto" or None."""
        return "auto" if self.thermal_lag_auto else self.thermal_lag_s


class ProcedureModel(_Strict):
    name: str
    description: str = ""
    temperatures: Temperatures
    soak: Soak = Soak()
    orientations: list[Orientation] = Field(min_length=1)
    remount_c: float = 23.0  # chamber temperature for remounting (the operator opens the door)
    remount_s: float = Field(300.0, ge=0)  # how long a remount takes (used by dry runs)
    rates: Rates
    settle_s: float = Field(5.0, ge=0)
    record_s: float = Field(60.0, gt=0)
    record_poll_s: float = Field(20.0, gt=0)  # chamber and table polled this often while recording
    sample_rate_hz: float = Field(50.0, gt=0, le=10000)
    safety: Safety = Safety()
    faults: Faults = Faults()
    monitor: Monitor = Monitor()
    mount_check: MountCheck = MountCheck()
    resume: Resume = Resume()
    fit: Fit = Fit()
    ramp: Ramp | None = None

    @field_validator("orientations", mode="before")
    @classmethod
    def _shorthand(cls, v: Any) -> Any:
        # `[x_up, x_down]` is shorthand for `[{name: x_up}, {name: x_down}]` with default prompts.
        if isinstance(v, list):
            return [{"name": o} if isinstance(o, str) else o for o in v]
        return v

    @field_validator("orientations")
    @classmethod
    def _unique(cls, v: list[Orientation]) -> list[Orientation]:
        names = [o.name for o in v]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"orientation {sorted(dup)[0]} is listed twice")
        return v


@dataclass(frozen=True)
class Step:
    """One record step of the expanded plan."""

    index: int
    orientation: str
    temperature_c: float
    rate_dps: float
    orientation_index: int
    temperature_index: int  # position in this orientation's temperature sequence
    rate_index: int


@dataclass(frozen=True)
class Procedure:
    model: ProcedureModel
    text: str
    source: str

    @property
    def name(self) -> str:
        return self.model.name

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.text.encode("utf-8")).hexdigest()

    def orientations(self) -> list[tuple[str, str]]:
        """(name, operator prompt) in procedure order."""
        out: list[tuple[str, str]] = []
        for o in self.model.orientations:
            out.append((o.name, o.prompt or DEFAULT_PROMPTS[o.name]))
        return out

    def prompt_for(self, orientation: str) -> str:
        return dict(self.orientations())[orientation]

    def temperatures_for(self, orientation_index: int) -> list[float]:
        temps = self.model.temperatures.values()
        order = self.model.temperatures.order
        if order == "descending" or (order == "serpentine" and orientation_index % 2 == 1):
            return temps[::-1]
        return temps

    def steps(self) -> list[Step]:
        out: list[Step] = []
        rates = self.model.rates.values()
        ramp = self.model.ramp
        for oi, (name, _) in enumerate(self.orientations()):
            if ramp is not None:  # one slow ramp per orientation; temperature_index is the bin
                temps = self.temperatures_for(oi)
                for pt in ramp_points(temps[0], temps[-1], ramp.c_per_min, ramp.bin_c, self._rate_durations_s(),
                                      ramp.end_hold_s):
                    out.append(Step(len(out), name, pt.temperature_c, rates[pt.rate_index], oi, pt.bin_index,
                                    pt.rate_index))
                continue
            for ti, temp in enumerate(self.temperatures_for(oi)):
                for ri, rate in enumerate(rates):
                    out.append(Step(len(out), name, temp, rate, oi, ti, ri))
        return out

    def _rate_durations_s(self) -> list[float]:
        """Each rate step's settle, spin-up (~100 deg/s^2) and record: how far apart a ramp's steps are."""
        m = self.model
        return [m.settle_s + m.record_s + abs(r) / 100.0 for r in m.rates.values()]

    @property
    def frames_per_record(self) -> int:
        return int(round(self.model.record_s * self.model.sample_rate_hz))

    def estimated_duration_s(self, ramp_c_per_min: float = 2.0, imu_lag_s: float = 600.0) -> float:
        """A lab-time estimate: records, settling, ramps, soaks and remounts.

        A soak judged on the IMU lasts until the IMU's first-order approach (time constant
        `imu_lag_s`, typical of a small IMU on a metal plate) spreads less than the
        tolerance over the window: about tau * ln(window * dT / (tau * tolerance)).
        """
        m = self.model
        if m.ramp is not None:  # the steps' ends, and the way back to the remount temperature
            ends = self.estimated_step_ends_s(ramp_c_per_min, imu_lag_s)
            last = self.temperatures_for(len(m.orientations) - 1)[-1]
            return (ends[-1] if ends else 0.0) + abs(last - m.remount_c) / ramp_c_per_min * 60.0 + m.remount_s
        total = 0.0
        for oi, _ in enumerate(self.orientations()):
            prev = m.remount_c
            for temp in self.temperatures_for(oi):
                total += self._soak_estimate_s(temp - prev, ramp_c_per_min, imu_lag_s) + self._rates_estimate_s()
                prev = temp
            total += abs(prev - m.remount_c) / ramp_c_per_min * 60.0 + m.remount_s
        return total

    def estimated_step_ends_s(self, ramp_c_per_min: float = 2.0, imu_lag_s: float = 600.0) -> list[float]:
        """The same estimate step by step: the lab time at which each record step of `steps()` ends.

        A step's share is what the sequencer does before it: its settle and record, and for the first
        rate at a temperature the ramp and soak (for an orientation's first step also the remount, the
        chamber's way to the remount temperature included). After the last step nothing waits on the
        lab (it parks while fitting), so the last end is `estimated_duration_s` less that last ramp back.
        The live ETA (`labrunner.runner.pace`) counts progress in these lab seconds, not in steps: a
        soak takes a hundred times longer than a record.
        """
        m = self.model
        ends: list[float] = []
        t = 0.0
        prev = m.remount_c
        prev_o = -1
        for step in self.steps():
            first = step.orientation_index != prev_o  # an orientation's first step: a remount before it
            if first:
                t += abs(prev - m.remount_c) / ramp_c_per_min * 60.0 + m.remount_s
                prev = m.remount_c
            # Along a ramp the setpoint moves with the steps: a soak only at the ramp's start.
            if first or (m.ramp is None and step.rate_index == 0):
                t += self._soak_estimate_s(step.temperature_c - prev, ramp_c_per_min, imu_lag_s)
            prev, prev_o = step.temperature_c, step.orientation_index
            t += m.settle_s + m.record_s + abs(step.rate_dps) / 100.0
            ends.append(t)
        return ends

    def _rates_estimate_s(self) -> float:
        """Settling and recording every rate at one temperature (the table spins up at ~100 deg/s^2)."""
        m = self.model
        return sum(m.settle_s + m.record_s + abs(r) / 100.0 for r in m.rates.values())

    def _soak_estimate_s(self, step_c: float, ramp_c_per_min: float, imu_lag_s: float) -> float:
        """Ramping `step_c` and soaking until stable (see `estimated_duration_s`)."""
        s = self.model.soak
        ramp = abs(step_c) / ramp_c_per_min * 60.0
        if s.sensor != "imu":
            return ramp + s.stable_window_s
        if s.criterion == "predictive":  # until the drift over the horizon, not the window's spread, is tolerable
            shrink = 1.0 - math.exp(-(s.predict_horizon_s or self.model.record_s) / imu_lag_s)
            tol = s.predict_tolerance_c or s.tolerance_c
            follow = imu_lag_s * math.log(max(max(abs(step_c), tol) * shrink / tol, 1.0))
            return ramp + max(follow, 8 * s.poll_s)  # fitted from the soak's start: 8 polls at least
        follow = imu_lag_s * math.log(max(s.stable_window_s * max(abs(step_c), s.tolerance_c)
                                          / (imu_lag_s * s.tolerance_c), 1.0))
        return ramp + max(follow, s.stable_window_s)

def _cross_checks(model: ProcedureModel, positions: dict[tuple[Any, ...], int], source: str) -> list[str]:
    """Checks across sections (temperatures against safety limits, rates against the rate limit)."""
    def at(*path: Any) -> str:
        for n in range(len(path), -1, -1):
            if path[:n] in positions:
                return f"{source}:{positions[path[:n]]}"
        return source

    # First the counts the plan would expand to, before anything expands it.
    t = model.temperatures
    n_temps = len(t.list_c) if t.list_c is not None else math.floor(
        (t.stop_c - t.start_c) / t.step_c + 1e-9) + 1  # type: ignore[operator]
    r = model.rates
    n_rates = len(r.list_dps) if r.list_dps is not None else 4 * round(
        r.triangular.max_dps / r.triangular.step_dps)  # type: ignore[union-attr]
    problems = []
    if n_temps > MAX_TEMPERATURES:
        problems.append(f"{at('temperatures')}: temperatures: {n_temps:,} temperatures; at most {MAX_TEMPERATURES}")
    if n_rates > MAX_RATES:
        problems.append(f"{at('rates')}: rates: {n_rates:,} rate steps; at most {MAX_RATES}")
    n_steps = n_temps * n_rates * len(model.orientations)
    if not problems and n_steps > MAX_STEPS:
        problems.append(f"{at('orientations')}: {len(model.orientations)} orientations x {n_temps} temperatures x "
                        f"{n_rates} rates = {n_steps:,} record steps; at most {MAX_STEPS:,}")
    frames = model.record_s * model.sample_rate_hz
    if frames > MAX_FRAMES_PER_RECORD:
        problems.append(f"{at('record_s')}: record_s x sample_rate_hz = {frames:,.0f} frames per record; at most "
                        f"{MAX_FRAMES_PER_RECORD:,}")
    if model.monitor.average_s * model.sample_rate_hz < 1.0 - 1e-9:
        problems.append(f"{at('monitor', 'average_s')}: monitor.average_s must be at least one IMU frame "
                        f"(1 / sample_rate_hz = {1.0 / model.sample_rate_hz:g} s)")
    if problems:
        return problems
    s = model.safety
    temps = model.temperatures.values()
    bad = [t for t in temps if not s.chamber_min_c <= t <= s.chamber_max_c]
    if bad:
        problems.append(f"{at('temperatures')}: temperatures {bad[0]} C is outside the safety limits "
                        f"safety.chamber_min_c..chamber_max_c ({s.chamber_min_c}..{s.chamber_max_c} C)")
    if not s.chamber_min_c <= model.remount_c <= s.chamber_max_c:
        problems.append(f"{at('remount_c')}: remount_c {model.remount_c} C is outside the safety limits")
    hottest = max(temps + [model.remount_c])
    if s.imu_max_temp_c <= hottest:
        # The IMU follows the chamber (and warms itself): its interlock would trip at the first reading.
        problems.append(f"{at('safety', 'imu_max_temp_c')}: safety.imu_max_temp_c {s.imu_max_temp_c:g} C is not "
                        f"above the plan's highest temperature ({hottest:g} C): the IMU interlock would trip")
    rates = model.rates.values()
    fast = [r for r in rates if abs(r) > s.max_rate_dps]
    if fast:
        problems.append(f"{at('rates')}: rates {fast[0]} deg/s exceeds safety.max_rate_dps ({s.max_rate_dps})")
    if model.record_poll_s > model.record_s:
        problems.append(f"{at('record_poll_s')}: record_poll_s must not exceed record_s")
    if abs(frames - round(frames)) > 1e-6 or round(frames) < 1:
        problems.append(f"{at('record_s')}: record_s x sample_rate_hz must be a whole number of frames")
    return problems


# Keys an earlier labrunner accepted and never read, now refused when written: a campaign stored
# with them still resumes (the key is dropped, with a warning), as its plan never depended on them.
_RETIRED_KEYS = {"faults": ("retries", "backoff_s")}


def _drop_retired(data: Any, source: str) -> None:
    for section, keys in _RETIRED_KEYS.items():
        part = data.get(section) if isinstance(data, dict) else None
        for key in keys:
            if isinstance(part, dict) and key in part:
                del part[key]
                log.warning("%s: %s.%s is no longer read; ignored for this stored campaign", source, section,
                               key)


def parse_procedure(text: str, source: str, *, stored: bool = False) -> Procedure:
    """A procedure from its text. `stored`: the text a campaign was started with, read back on resume,
    where keys retired since are dropped rather than refused."""
    data, positions = load_yaml(text, source)
    if stored:
        _drop_retired(data, source)
    model = validate(ProcedureModel, data, positions, source)
    problems = _cross_checks(model, positions, source)
    if problems:
        raise ConfigError(problems)
    procedure = Procedure(model=model, text=text, source=source)
    samples = len(procedure.steps()) * procedure.frames_per_record
    if samples > MAX_SAMPLES:
        problems.append(f"{source}:1: the plan records {samples:,} samples; at most {MAX_SAMPLES:,} (the paper's "
                        "campaign has 12,240,000)")
    lab_s = procedure.estimated_duration_s()
    if lab_s > MAX_LAB_TIME_S:
        problems.append(f"{source}:1: the plan takes about {lab_s / 86400:,.0f} days of lab time; at most "
                        f"{MAX_LAB_TIME_S / 86400:.0f} (the paper's campaign: about 6)")
    if problems:
        raise ConfigError(problems)
    return procedure


def shipped_procedures() -> list[str]:
    """Names of the procedures installed with labrunner (`labrunner run quick` finds them anywhere)."""
    return sorted(f.name.removesuffix(".yaml") for f in resources.files(SHIPPED_PACKAGE).iterdir()
                  if f.name.endswith(".yaml"))


def load_procedure(path: str | Path) -> Procedure:
    """A procedure file; if `path` does not exist and is a bare name (`quick`, `quick.yaml`), the
    shipped procedure of that name. Neither: a ConfigError naming the file and the shipped ones."""
    p = Path(path)
    if not p.exists() and p.parent == Path("."):
        name = p.name.removesuffix(".yaml")
        shipped = resources.files(SHIPPED_PACKAGE) / f"{name}.yaml"
        if shipped.is_file():
            log.info("%s: no such file; using the shipped procedure %r (%s)", p, name, shipped)
            return parse_procedure(shipped.read_text(encoding="utf-8"), str(shipped))
    if not p.exists():
        raise ConfigError([f"{p}: file not found (shipped procedures, usable by name: "
                           f"{', '.join(shipped_procedures())})"])
    log.debug("procedure from %s", p)
    return parse_procedure(read_text(p), str(p))


__all__ = ["ORIENTATIONS", "Procedure", "ProcedureModel", "Step", "load_procedure", "parse_procedure",
           "shipped_procedures", "triangular_rates"]
