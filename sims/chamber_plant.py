"""Thermal chamber physics: air temperature under a PI controller with limited heating and cooling.

The air exchanges heat with the room (time constant `loss_tau_s`); the heater can
warm it at up to `heat_rate_c_per_min`, the compressor cool it at up to
`cool_rate_c_per_min`, a capacity that falls as the air nears `min_reachable_c`.
A PI controller with anti-windup drives the outputs, which gives ramps of a few
degrees per minute, a small overshoot and settling within about ten minutes, as
real chambers do. Integrated on a fixed 1 s grid so results do not depend on when
the state is looked at.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class ChamberParams:
    ambient_c: float = 23.0
    heat_rate_c_per_min: float = 4.0
    cool_rate_c_per_min: float = 3.0
    min_reachable_c: float = -70.0
    loss_tau_s: float = 3600.0
    kp_pct_per_c: float = 40.0
    ti_s: float = 150.0
    fluctuation_c: float = 0.03  # standard deviation of the air's small random fluctuation
    fluctuation_tau_s: float = 60.0
    setpoint_min_c: float = -70.0  # the controller's setpoint range (registers 602/603)
    setpoint_max_c: float = 180.0
    step_s: float = 1.0
    # The controller's display settings (Watlow F4 registers 901 and 606): temperatures are served
    # in these units with this many decimals, so a driver must read and convert them.
    controller_units: str = "C"  # "C" or "F"
    controller_decimals: int = 1  # 0..2

    def __post_init__(self) -> None:
        if self.controller_units not in ("C", "F"):
            raise ValueError(f"chamber.controller_units must be 'C' or 'F', got {self.controller_units!r}")
        if isinstance(self.controller_decimals, bool) or self.controller_decimals not in (0, 1, 2):
            raise ValueError(f"chamber.controller_decimals must be 0, 1 or 2, got {self.controller_decimals!r}")


class ChamberPlant:
    """Air temperature, controller outputs and faults; `advance_to(t)` integrates up to t."""

    def __init__(self, params: ChamberParams | None = None, start_t: float = 0.0, seed: int = 0) -> None:
        self.p = params or ChamberParams()
        self.t = float(start_t)
        self.air_c = self.p.ambient_c
        self.setpoint_c = self.p.ambient_c
        self.integral = 0.0
        self.output_pct = 0.0  # + heating, - cooling
        self._fluct = 0.0
        self._rng = np.random.default_rng([seed, 0xC4A3])
        # Faults (issue: overnight reliability): capacities forced to zero.
        self.heater_failed = False
        self.compressor_failed = False
        self.heater_stuck = False  # the heater's relay welded shut: full heat whatever the controller says

    def cooling_capacity(self, air_c: float) -> float:
        """Cooling rate at full output, deg C per second, at an air temperature."""
        if self.compressor_failed:
            return 0.0
        span = self.p.ambient_c - self.p.min_reachable_c
        frac = min(max((air_c - self.p.min_reachable_c) / span, 0.0), 1.5)
        return self.p.cool_rate_c_per_min / 60.0 * frac

    def heating_capacity(self) -> float:
        return 0.0 if self.heater_failed else self.p.heat_rate_c_per_min / 60.0

    def _step(self, dt: float) -> None:
        p = self.p
        err = self.setpoint_c - self.air_c
        u_unsat = p.kp_pct_per_c * (err + self.integral / p.ti_s)
        u = min(max(u_unsat, -100.0), 100.0)
        # Anti-windup: integrate only while unsaturated or when the error unwinds saturation.
        if u == u_unsat or (u_unsat > 100.0 and err < 0) or (u_unsat < -100.0 and err > 0):
            self.integral += err * dt
        self.output_pct = u
        heat = (1.0 if self.heater_stuck else max(u, 0.0) / 100.0) * self.heating_capacity()
        cool = max(-u, 0.0) / 100.0 * self.cooling_capacity(self.air_c)
        loss = (p.ambient_c - self.air_c) / p.loss_tau_s
        base = self.air_c - self._fluct
        base += (heat - cool + loss) * dt
        # Small random fluctuation of the air (mixing, compressor cycling): Ornstein-Uhlenbeck.
        a = math.exp(-dt / p.fluctuation_tau_s)
        self._fluct = a * self._fluct + p.fluctuation_c * math.sqrt(1 - a * a) * float(self._rng.standard_normal())
        self.air_c = base + self._fluct
        self.t += dt

    def advance_to(self, t: float) -> None:
        while self.t + self.p.step_s <= t + 1e-9:
            self._step(self.p.step_s)

    def set_setpoint(self, value_c: float) -> None:
        self.setpoint_c = float(value_c)

    @property
    def heat_output_pct(self) -> float:
        return max(self.output_pct, 0.0)

    @property
    def cool_output_pct(self) -> float:
        return max(-self.output_pct, 0.0)
