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

_NORMALS_BLOCK = 4096


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
        self._normals: list[float] = []  # a block of the fluctuation's normals, drawn ahead
        self._next_normal = 0
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
        self.run_steps(1, dt)

    def run_steps(self, n: int, dt: float) -> list[tuple[float, float]]:
        """Integrate `n` steps of `dt`; the (time, air) after each.

        One Python loop over local variables (a dry run integrates ~570 000 steps for the paper
        campaign), with the arithmetic of one step in the order it always had, so the air is the
        same to the bit; the fluctuation's normals are drawn in blocks (numpy's generator gives the
        same sequence as one draw at a time). Faults only change between calls.
        """
        p = self.p
        setpoint, air, integral, fluct, t = self.setpoint_c, self.air_c, self.integral, self._fluct, self.t
        kp, ti, ambient, loss_tau = p.kp_pct_per_c, p.ti_s, p.ambient_c, p.loss_tau_s
        heat_cap = self.heating_capacity()
        stuck = self.heater_stuck
        cool_rate = 0.0 if self.compressor_failed else p.cool_rate_c_per_min / 60.0
        lo, span = p.min_reachable_c, p.ambient_c - p.min_reachable_c
        a = math.exp(-dt / p.fluctuation_tau_s)
        kick = p.fluctuation_c * math.sqrt(1 - a * a)
        u = self.output_pct
        out: list[tuple[float, float]] = []
        append = out.append
        # The block of normals as locals (drawn ahead in blocks, taken one per step).
        normals, k = self._normals, self._next_normal
        # min() and max() of two are written out as the builtins decide them (max(a, b): b if b > a else a;
        # min(a, b): b if b < a else a, NaN and signed zeros included): the same values without the calls.
        for _ in range(n):
            err = setpoint - air
            u_unsat = kp * (err + integral / ti)
            u = -100.0 if -100.0 > u_unsat else u_unsat  # min(max(u_unsat, -100.0), 100.0)
            u = 100.0 if 100.0 < u else u
            # Anti-windup: integrate only while unsaturated or when the error unwinds saturation.
            if u == u_unsat or (u_unsat > 100.0 and err < 0) or (u_unsat < -100.0 and err > 0):
                integral += err * dt
            heat = (1.0 if stuck else (0.0 if 0.0 > u else u) / 100.0) * heat_cap  # max(u, 0.0)
            # cooling_capacity(air): the compressor's rate falls as the air nears min_reachable_c
            reach = (air - lo) / span
            reach = 0.0 if 0.0 > reach else reach  # min(max(reach, 0.0), 1.5)
            reach = 1.5 if 1.5 < reach else reach
            cool = (0.0 if 0.0 > -u else -u) / 100.0 * (cool_rate * reach)  # max(-u, 0.0)
            loss = (ambient - air) / loss_tau
            base = air - fluct
            base += (heat - cool + loss) * dt
            # Small random fluctuation of the air (mixing, compressor cycling): Ornstein-Uhlenbeck.
            if k == len(normals):
                normals = self._normals = self._rng.standard_normal(_NORMALS_BLOCK).tolist()
                k = 0
            fluct = a * fluct + kick * normals[k]
            k += 1
            air = base + fluct
            t += dt
            append((t, air))
        self._next_normal = k
        self.air_c, self.integral, self._fluct, self.t, self.output_pct = air, integral, fluct, t, u
        return out

    def advance_to(self, t: float) -> None:
        n, tt, step = 0, self.t, self.p.step_s
        while tt + step <= t + 1e-9:  # the times run_steps accumulates, compared as they always were
            tt += step
            n += 1
        if n:
            self.run_steps(n, self.p.step_s)

    def set_setpoint(self, value_c: float) -> None:
        self.setpoint_c = float(value_c)

    @property
    def heat_output_pct(self) -> float:
        return max(self.output_pct, 0.0)

    @property
    def cool_output_pct(self) -> float:
        return max(-self.output_pct, 0.0)
