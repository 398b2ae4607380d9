"""Soak judgement: when the chamber (and the IMU) count as stable, and what a soak timeout does.

A soak is stable when the readings of the last `stable_window_s` all hold: the chamber within
`tolerance_c` of the setpoint and, with `sensor: imu`, the IMU temperature's spread within
`tolerance_c` too (the IMU lags the air, so a settled chamber alone does not mean a settled IMU).

With `criterion: predictive` the IMU part is judged by extrapolation instead
(`labrunner.runner.soak_predict`): from the soak's start (once it holds `MIN_READINGS` polls), over
at most the last `predict_window_s`, with the chamber within `tolerance_c` over the readings fitted,
the fitted approach of the IMU temperature must predict less than `predict_tolerance_c` (default
`tolerance_c`) of change over the horizon (`predict_horizon_s`, by default the procedure's `record_s`),
confidence bound included. With `predict_lag_s` (the sensing element's lag behind the IMU's temperature
sensor, e.g. the diagnosis's thermal_lag finding) the element's predicted mean offset from the reading
over the horizon must also be within `predict_lag_tolerance_c` (default `predict_tolerance_c`): a record
is tagged with the sensor's temperature, so a soak ended while the reading still moves records an element
that is lag x rate behind it. A fit that gives no prediction switches that soak to the spread criterion
for good (`SoakWindow.fallback`).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

from labrunner.procedure import Soak
from labrunner.runner.soak_predict import MIN_READINGS, ApproachFit, NoFit, fit_approach

log = logging.getLogger(__name__)

_EPS_S = 1e-6  # polls land on whole seconds; do not miss a window by rounding
# A predictive soak ends with the chamber within this many tolerances of its setpoint (its controller's
# overshoot, settling; the rest of that excursion is in the predicted drift's bound).
_CHAMBER_BAND = 5.0


@dataclass(frozen=True)
class SoakReading:
    t_s: float
    chamber_c: float
    imu_c: float  # NaN when the IMU gave no sample


@dataclass(frozen=True)
class SoakProgress:
    """How close a soak is to stable, for a live view: what `SoakWindow.stable` judges, as numbers."""

    setpoint_c: float
    tolerance_c: float
    window_s: float
    sensor: str  # "imu": the IMU's spread counts; "chamber": only the chamber's offset
    chamber_c: float  # the newest readings
    imu_c: float
    chamber_offset_c: float  # the largest |chamber - setpoint| over the last window
    imu_spread_c: float  # max - min of the IMU temperature over the last window (NaN: no IMU reading)
    stable_s: float  # how long every reading has held, up to the window: stable once it reaches window_s
    soaked_s: float  # since the soak's first reading

    @property
    def stable(self) -> bool:
        return self.stable_s >= self.window_s - _EPS_S


def soak_progress(readings: Sequence[SoakReading], soak: Soak, setpoint_c: float,
                  first_t: float | None = None) -> SoakProgress | None:
    """The progress of a soak from its readings in time order (None: no reading yet); `first_t` is
    the soak's first reading when older ones were dropped. Only the last window counts, as for
    `SoakWindow.stable`: `stable_s` reaches the window exactly when that says stable."""
    if not readings:
        return None
    newest = readings[-1]
    first = readings[0].t_s if first_t is None else first_t
    window = [r for r in readings if r.t_s >= newest.t_s - soak.stable_window_s - _EPS_S]
    imu = [r.imu_c for r in window if math.isfinite(r.imu_c)]
    lo = hi = math.nan
    held_from: float | None = None  # the oldest reading from which every newer one holds
    for r in reversed(window):
        if abs(r.chamber_c - setpoint_c) > soak.tolerance_c:
            break
        if soak.sensor == "imu":
            if not math.isfinite(r.imu_c):
                break
            lo, hi = (r.imu_c, r.imu_c) if math.isnan(lo) else (min(lo, r.imu_c), max(hi, r.imu_c))
            if hi - lo > soak.tolerance_c:
                break
        held_from = r.t_s
    if held_from is None:
        stable_s = 0.0
    elif held_from == window[0].t_s:  # the whole window holds: as long as the soak, up to the window
        stable_s = min(newest.t_s - first, soak.stable_window_s)
    else:
        stable_s = newest.t_s - held_from
    return SoakProgress(
        setpoint_c=setpoint_c, tolerance_c=soak.tolerance_c, window_s=soak.stable_window_s, sensor=soak.sensor,
        chamber_c=newest.chamber_c, imu_c=newest.imu_c,
        chamber_offset_c=max(abs(r.chamber_c - setpoint_c) for r in window),
        imu_spread_c=max(imu) - min(imu) if imu else math.nan, stable_s=stable_s, soaked_s=newest.t_s - first)


class SoakWindow:
    """The readings of one soak, judged against its setpoint."""

    def __init__(self, soak: Soak, setpoint_c: float, horizon_s: float | None = None) -> None:
        self.soak = soak
        self.setpoint_c = setpoint_c
        # The predictive criterion's horizon: the soak's own, else the caller's (a record), else a window.
        self.horizon_s = soak.predict_horizon_s or horizon_s or soak.stable_window_s
        self.predictive = soak.criterion == "predictive"
        # What the predicted drift over the horizon is held to; the chamber keeps tolerance_c.
        self.predict_tolerance_c = soak.predict_tolerance_c or soak.tolerance_c
        # What the element's predicted offset from the reading is held to (predict_lag_s only).
        self.predict_lag_s = soak.predict_lag_s or 0.0
        self.predict_lag_tolerance_c = soak.predict_lag_tolerance_c or self.predict_tolerance_c
        self.prediction: ApproachFit | None = None  # the newest fit (predictive criterion)
        self.fallback: str | None = None  # why this soak fell back to the spread criterion
        self._keep_s = max(soak.stable_window_s, soak.predict_window_s if self.predictive else 0.0)
        self._first_t: float | None = None
        self._readings: deque[SoakReading] = deque()

    def add(self, t_s: float, chamber_c: float, imu_c: float) -> None:
        if self._first_t is None:
            self._first_t = t_s
        self._readings.append(SoakReading(t_s, chamber_c, imu_c))
        # Readings older than a window before the newest can never be judged again.
        while self._readings and self._readings[0].t_s < t_s - self._keep_s - _EPS_S:
            self._readings.popleft()

    def covered_s(self) -> float:
        """How long the readings span, from the first of the soak to the newest."""
        if self._first_t is None:
            return 0.0
        return self._readings[-1].t_s - self._first_t

    def _last(self, seconds: float) -> list[SoakReading]:
        newest = self._readings[-1].t_s
        return [r for r in self._readings if r.t_s >= newest - seconds - _EPS_S]

    def stable(self) -> bool:
        """Stable by the soak's criterion: `spread` (below), or `predictive` until a fit fails."""
        if self.predictive and self.fallback is None:
            return self._predicted_stable()
        return self._spread_stable()

    def _predicted_stable(self) -> bool:
        s = self.soak
        if self._first_t is None:
            return False
        # From the soak's start (the chamber reached its tolerance), over at most the last
        # predict_window_s: a fit over a few polls is already a prediction, its (profile) bound wide
        # while the window is short against tau. The chamber's controller overshoots and takes minutes
        # to settle back within a tenth of a degree; the IMU, lagging minutes behind, follows that
        # small excursion smoothly, and what it still has to follow is bounded below (chamber term).
        window = self._last(s.predict_window_s)
        if len(window) < MIN_READINGS:
            return False
        fit = fit_approach([r.t_s for r in window], [r.imu_c for r in window], self.horizon_s,
                           s.predict_tau_max_s, s.predict_model, self.predict_lag_s)
        if isinstance(fit, NoFit):
            if window[-1].t_s - window[0].t_s < s.predict_window_s - s.poll_s - _EPS_S:
                self.prediction = None  # a short window may not resolve the approach yet: wait for more
                return False
            self.fallback = fit.reason
            self.prediction = None
            log.info("predictive soak at %s C falls back to the spread criterion: %s", self.setpoint_c, fit.reason)
            return self._spread_stable()
        # The air still off its setpoint by d moves the IMU by up to d (1 - exp(-horizon / tau)) more.
        off = abs(window[-1].chamber_c - self.setpoint_c)
        fit = replace(fit, chamber_drift_c=off * -math.expm1(-self.horizon_s / fit.tau_s))
        self.prediction = fit
        return (off <= s.tolerance_c * _CHAMBER_BAND and fit.drift_bound_c <= self.predict_tolerance_c
                and fit.lag_bound_c <= self.predict_lag_tolerance_c)

    def _spread_stable(self) -> bool:
        """Stable once the soak has lasted a window and every reading of the last window holds."""
        s = self.soak
        if self._first_t is None or self.covered_s() < s.stable_window_s - _EPS_S:
            return False
        window = self._last(s.stable_window_s)
        if any(abs(r.chamber_c - self.setpoint_c) > s.tolerance_c for r in window):
            return False
        if s.sensor == "imu":
            imu = [r.imu_c for r in window]
            return all(math.isfinite(v) for v in imu) and max(imu) - min(imu) <= s.tolerance_c
        return True

    def progress(self) -> SoakProgress | None:
        """How close the soak is to `stable()`, for the live view (reads only)."""
        return soak_progress(self._readings, self.soak, self.setpoint_c, self._first_t)


TimeoutAction = Literal["continue", "pause", "abort"]


@dataclass(frozen=True)
class SoakTimeout:
    """What soak.on_timeout says when the chamber did not stabilise in time."""

    action: TimeoutAction
    message: str

    @property
    def carry_on(self) -> bool:
        return self.action == "continue"

    @property
    def event_kind(self) -> str:
        # Carrying on is worth a warning; stopping is a fault (it pauses or aborts the campaign).
        return "warning" if self.carry_on else "fault"


def soak_timeout(soak: Soak, what: str, target_c: float) -> SoakTimeout:
    """The verdict for a `what` ("ramp", "soak", "remount") at `target_c` that ran out of time."""
    policy = soak.on_timeout
    msg = (f"{what} at {target_c} C did not stabilise within soak.max_wait_s "
           f"({soak.max_wait_s:.0f} s); on_timeout: {policy}")
    log.info("soak timeout: %s", msg)
    return SoakTimeout(action=policy, message=msg)
