"""The simulated lab's physical state: chamber air, rate table, and an IMU mounted on the table.

One object, one lock, one clock: the chamber server, the table server and the IMU
stream all read it, so every simulated instrument sees the same moment. The IMU's
case follows the chamber air with a first-order lag; its die (where the temperature
sensor is) runs warmer by a self-heating rise that builds after each power-on.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from labrunner.imu.model import ImuInputs, ImuModel, default_imu_model, up_vector

from .chamber_plant import ChamberParams, ChamberPlant
from .table_plant import TableParams, TablePlant

HISTORY_S = 6 * 3600.0  # how far back IMU temperatures can be asked for
_FEW_RUNS = 64  # horizons given in at most this many runs of one value are looked up run by run


@dataclass
class ImuThermalParams:
    case_tau_s: float = 600.0  # the IMU case lags the chamber air (a small board on a metal plate, forced air)
    self_heat_c: float = 4.0  # die above case once warm, while powered
    self_heat_tau_s: float = 300.0


@dataclass
class SimOperatorParams:
    """How the dry run's operator remounts: the first `wrong_mounts` remounts of a session go wrong,
    turning the IMU to `mounts_as` (None: the remount is skipped, the IMU stays as it was)."""

    wrong_mounts: int = 0
    mounts_as: str | None = None

    def __post_init__(self) -> None:
        if isinstance(self.wrong_mounts, bool) or not isinstance(self.wrong_mounts, int) \
                or not 0 <= self.wrong_mounts <= 1000:
            raise ValueError(f"operator.wrong_mounts must be a whole number 0..1000, got {self.wrong_mounts!r}")
        if self.mounts_as is not None:
            try:
                up_vector(str(self.mounts_as))
            except ValueError as exc:
                raise ValueError(f"operator.mounts_as: {exc}") from None


@dataclass
class SimLabConfig:
    """Everything that defines a simulated lab (loadable from a YAML/JSON sim configuration)."""

    seed: int = 0
    chamber: ChamberParams = field(default_factory=ChamberParams)
    table: TableParams = field(default_factory=TableParams)
    imu_thermal: ImuThermalParams = field(default_factory=ImuThermalParams)
    imu_model: ImuModel = field(default_factory=default_imu_model)
    imu_rate_hz: float = 50.0
    imu_format: str = "labrunner_frame"  # the IMU's wire format (sims.imu_stream.IMU_FORMATS), e.g. xsens_mti
    orientation: str = "z_up"
    faults: dict[str, Any] = field(default_factory=dict)
    operator: SimOperatorParams = field(default_factory=SimOperatorParams)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SimLabConfig:
        """Build from a mapping; unknown keys are refused with their name."""
        known = {f.name for f in fields(cls)}  # every field is a key (as sim_config checks them)
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown sim configuration key(s): {', '.join(sorted(unknown))}")

        def sub(klass: type, key: str) -> Any:
            value = data.get(key) or {}
            if not isinstance(value, dict):
                raise ValueError(f"sim configuration {key} must be a mapping")
            try:
                return klass(**value)
            except TypeError as exc:
                raise ValueError(f"sim configuration {key}: {exc}") from None

        model = data.get("imu_model")
        if isinstance(model, str):
            imu_model = ImuModel.load(model)
        elif isinstance(model, dict):
            imu_model = ImuModel.from_dict(model)
        else:
            imu_model = default_imu_model()
        seed = int(data.get("seed", 0))
        imu_model.seed = int(model.get("seed", seed)) if isinstance(model, dict) else seed
        up_vector(str(data.get("orientation", "z_up")))  # validates
        imu_format = data.get("imu_format", "labrunner_frame")
        from .imu_stream import IMU_FORMATS  # here: imu_stream imports this module

        if imu_format not in IMU_FORMATS:
            raise ValueError(f"sim configuration imu_format must be one of {', '.join(IMU_FORMATS)}, "
                             f"got {imu_format!r}")
        return cls(seed=seed, chamber=sub(ChamberParams, "chamber"), table=sub(TableParams, "table"),
                   imu_thermal=sub(ImuThermalParams, "imu_thermal"), imu_model=imu_model,
                   imu_rate_hz=float(data.get("imu_rate_hz", 50.0)), imu_format=str(imu_format),
                   orientation=str(data.get("orientation", "z_up")),
                   faults=dict(data.get("faults") or {}), operator=sub(SimOperatorParams, "operator"))


class SimWorld:
    """Physical state of the simulated lab, advanced lazily to the clock's time."""

    def __init__(self, config: SimLabConfig, start_t: float) -> None:
        self.config = config
        self.lock = threading.RLock()
        self.chamber = ChamberPlant(config.chamber, start_t=start_t, seed=config.seed)
        self.table = TablePlant(config.table, start_t=start_t, seed=config.seed)
        self.model = config.imu_model
        self.thermal = config.imu_thermal
        self.case_c = config.chamber.ambient_c
        self.orientation = config.orientation
        self.powered = True
        self.run = 1
        self.t_on = float(start_t)
        self.imu_extra_heat_c = 0.0  # fault injection: a component overheating inside the IMU
        # History on the integration grid: columns t, case, air; grows, then drops its oldest half.
        self._hist = np.empty((4096, 3))
        self._hist[0] = (float(start_t), self.case_c, self.chamber.air_c)
        self._n = 1

    @property
    def t(self) -> float:
        return self.chamber.t

    def advance(self, t: float) -> None:
        """Integrate chamber air and IMU case temperature up to time t (1 s grid)."""
        with self.lock:
            step = self.chamber.p.step_s
            n, tt = 0, self.chamber.t
            while tt + step <= t + 1e-9:  # the grid times as the plant accumulates them
                tt += step
                n += 1
            if not n:
                return
            a = math.exp(-step / self.thermal.case_tau_s)
            b = 1 - a
            case = self.case_c
            steps = self.chamber.run_steps(n, step)
            cases = []
            for _, air in steps:
                case = a * case + b * air
                cases.append(case)
            self.case_c = case
            rows = np.empty((n, 3))
            rows[:, 0::2] = steps  # (t, air) pairs into columns 0 and 2
            rows[:, 1] = cases
            self._append_history(rows)

    def _append_history(self, rows: np.ndarray) -> None:
        """Append rows (t, case, air) to the history, keeping at least HISTORY_S of it."""
        need = self._n + len(rows)
        if need > len(self._hist):
            keep = int(HISTORY_S / self.chamber.p.step_s)
            if self._n > 2 * keep and keep + len(rows) <= len(self._hist):
                self._hist[:keep] = self._hist[self._n - keep:self._n]
                self._n = keep
            else:
                grown = np.empty((max(2 * len(self._hist), need), 3))
                grown[:self._n] = self._hist[:self._n]
                self._hist = grown
        self._hist[self._n:self._n + len(rows)] = rows
        self._n += len(rows)

    def _history(self, times: np.ndarray, column: int, until: np.ndarray | None = None) -> np.ndarray:
        """Interpolate a history column at times (only the stretch of history they span). With `until` (per
        time), the history as it was when it ended at the last grid step at or before until + 1e-9 (as
        `advance(until)` left it): a time after that step has its value, as np.interp holds the last one."""
        times = np.asarray(times, dtype=float)
        if times.size == 0:
            return np.empty(0)
        ht = self._hist[: self._n, 0]
        lo = max(int(np.searchsorted(ht, times.min(), side="right")) - 1, 0)
        hi = min(int(np.searchsorted(ht, times.max(), side="left")) + 1, self._n)
        out = np.interp(times, ht[lo:hi], self._hist[lo:hi, column])
        if until is not None:
            ends = np.asarray(until, dtype=float) + 1e-9
            # Runs of one horizon (a chunk made on demand has one per clock advance it covers): each run's
            # grid step found once, not once per time; the same steps and values as per time.
            cuts = np.flatnonzero(ends[1:] != ends[:-1]) + 1
            if cuts.size < _FEW_RUNS:
                bounds = [0, *cuts.tolist(), ends.size]
                steps = np.searchsorted(ht, ends[bounds[:-1]], side="right") - 1
                for a, b, last in zip(bounds[:-1], bounds[1:], steps.tolist()):
                    after = times[a:b] > ht[last]  # the grid step advance(until) ended at
                    if after.any():
                        out[a:b][after] = self._hist[last, column]
                return out
            last = np.searchsorted(ht, ends, side="right") - 1  # the grid step advance(until) ended at
            after = times > ht[last]
            if after.any():
                out[after] = self._hist[last[after], column]
        return out

    # --- what the IMU sees ------------------------------------------------------------

    def air_at(self, times: np.ndarray) -> np.ndarray:
        with self.lock:
            return self._history(times, 2)

    def imu_temperature_at(self, times: np.ndarray, history_until: np.ndarray | None = None) -> np.ndarray:
        """Die temperature (what the IMU's sensor reads) at times within the history (as it was when it ended
        at `history_until`, per time: `_history`)."""
        with self.lock:
            case = self._history(times, 1, history_until)
            if not self.powered:
                return case
            # case + extra + self_heat * (1 - exp(-since_on / tau)), in place in that order
            heat = np.maximum(np.asarray(times, dtype=float) - self.t_on, 0.0)
            np.negative(heat, out=heat)
            heat /= self.thermal.self_heat_tau_s
            np.exp(heat, out=heat)
            np.subtract(1.0, heat, out=heat)
            heat *= self.thermal.self_heat_c
            case += self.imu_extra_heat_c
            case += heat
            return case

    def imu_inputs(self, times: np.ndarray, history_until: np.ndarray | None = None) -> ImuInputs:
        times = np.asarray(times, dtype=float)
        n = times.size
        up = up_vector(self.orientation)
        rate = self.table.rate_at(times)
        rate_dps = np.empty((n, 3))
        for j in range(3):  # rate * up, a column at a time (an (n, 3) product is a loop of 3 per sample)
            np.multiply(rate, up[j], out=rate_dps[:, j])
        return ImuInputs(
            t_s=times,
            run=np.full(n, self.run, dtype=np.int64),
            t_on_s=times - self.t_on,
            temp_c=self.imu_temperature_at(times, history_until),
            force_g=np.broadcast_to(up, (n, 3)),  # one up vector for every sample: a read-only view
            rate_dps=rate_dps,
        )

    # --- what the operator does -------------------------------------------------------

    def power_off(self) -> None:
        with self.lock:
            self.powered = False

    def power_on(self, t: float) -> None:
        with self.lock:
            self.advance(t)
            self.powered = True
            self.run += 1
            self.t_on = float(t)

    def restore(self, *, orientation: str, air_c: float, setpoint_c: float, powered_since: float, run: int,
                imu_c: float | None = None) -> None:
        """Start as a lab left running (a resumed dry run): the IMU mounted `orientation` and powered since
        `powered_since` in run `run`, the chamber air at `air_c` heading for `setpoint_c`, the IMU's sensor
        reading `imu_c` (its case that less the self-heating built since power-on; None: the case at `air_c`)."""
        up_vector(orientation)
        with self.lock:
            self.chamber.air_c = float(air_c)
            self.chamber.setpoint_c = float(setpoint_c)
            since_on = max(self.chamber.t - float(powered_since), 0.0)
            heat = self.thermal.self_heat_c * (1.0 - math.exp(-since_on / self.thermal.self_heat_tau_s))
            self.case_c = float(air_c) if imu_c is None or not math.isfinite(imu_c) else float(imu_c) - heat
            self._hist[0] = (self.chamber.t, self.case_c, self.chamber.air_c)
            self._n = 1
            self.orientation = orientation
            self.powered = True
            self.t_on = float(powered_since)
            self.run = int(run)

    def remount(self, orientation: str, t: float) -> None:
        """Power down, turn the IMU to another orientation on the table, power up (a new run)."""
        up_vector(orientation)
        with self.lock:
            self.power_off()
            self.orientation = orientation
            self.power_on(t)
