"""`labrunner check --lab LAB.yaml --ping`: talk to each instrument of a lab without moving anything.

Each instrument's driver (from the lab configuration, through the registry) connects and is
asked only what can be read: the chamber its identity, setpoint range, temperature and setpoint;
the rate table its identity, limits (where its language has them), velocity and status; the IMU
streams for a second and gravity is checked from its accelerometer (|a| close to 1 g, which
axis points up, with `runner.mount_check`'s judgement). No setpoint is written and the table is
never jogged or stopped. Every instrument is tried even when an earlier one fails; each problem
is one line naming the instrument and its address.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from labrunner.clock import Clock, ScaledClock, WallClock
from labrunner.drivers.errors import InstrumentError
from labrunner.lab import LabConfig, build_drivers
from labrunner.runner.mount_check import MountVerdict, axis_words, judge, read_accel

log = logging.getLogger(__name__)

READ_S = 1.0  # a second of IMU frames
MAX_TILT_DEG = 10.0  # the up axis within this of gravity (runner.mount_check's default)
GRAVITY_TOLERANCE_G = 0.1


@dataclass
class InstrumentPing:
    kind: str
    driver: str
    address: str = "?"
    lines: list[str] = field(default_factory=list)  # what it answered
    problem: str | None = None  # the first thing that failed (one line)

    @property
    def ok(self) -> bool:
        return self.problem is None


@dataclass
class PingReport:
    instruments: list[InstrumentPing]
    gravity: MountVerdict | None = None  # None: the IMU gave no frames to judge
    gravity_problem: str | None = None

    @property
    def ok(self) -> bool:
        return all(i.ok for i in self.instruments) and self.gravity_problem is None

    def lines(self) -> list[str]:
        out = []
        for inst in self.instruments:
            state = "ok" if inst.ok else "FAILED"
            out.append(f"{inst.kind:8s} {state}: driver {inst.driver} at {inst.address}")
            out += [f"           {line}" for line in inst.lines]
            if inst.problem:
                out.append(f"           {inst.problem}")
        if self.gravity is not None:
            g = self.gravity
            verdict = "ok" if self.gravity_problem is None else "FAILED"
            out.append(f"gravity  {verdict}: {g.measured_words()} from {g.frames} frames")
        if self.gravity_problem:
            out.append(f"           {self.gravity_problem}")
        return out


def _try(inst: InstrumentPing, what: str, ask: Callable[[], Any]) -> Any:
    """Ask one thing; an instrument error (or a driver's own ValueError) becomes the instrument's problem."""
    if inst.problem is not None:
        return None
    try:
        return ask()
    except (InstrumentError, OSError, ValueError) as exc:
        inst.problem = f"{what}: {exc}"
        log.info("ping %s: %s", inst.kind, inst.problem)
        return None


def _gravity(accel: Any, max_tilt_deg: float, tolerance_g: float) -> tuple[MountVerdict | None, str | None]:
    # Judged against the orientation nearest the measured force: the ping asks which axis is up.
    verdict = judge(accel, "z_up", max_angle_deg=180.0, gravity_tolerance_g=math.inf)
    if not verdict.frames:
        return None, "gravity: no IMU frames in a second (is it powered and streaming?)"
    if verdict.measured is None or verdict.magnitude_g is None or verdict.off_measured_deg is None:
        return verdict, f"gravity: {verdict.measured_words()}"
    verdict = judge(accel, verdict.measured, max_angle_deg=max_tilt_deg, gravity_tolerance_g=tolerance_g)
    if verdict.ok:
        return verdict, None
    problems = []
    assert verdict.magnitude_g is not None and verdict.off_measured_deg is not None
    if abs(verdict.magnitude_g - 1.0) > tolerance_g:
        problems.append(f"|a| = {verdict.magnitude_g:.3f} g, not 1 g within {tolerance_g:g} g (moving, or a "
                        "scale problem)")
    if verdict.off_measured_deg > max_tilt_deg:
        problems.append(f"{axis_words(verdict.measured or '')} is {verdict.off_measured_deg:.1f}° from vertical, "
                        f"more than {max_tilt_deg:g}° (tilted mount)")
    return verdict, "gravity: " + "; ".join(problems)


def ping_lab(config: LabConfig, *, read_s: float = READ_S, max_tilt_deg: float = MAX_TILT_DEG,
             gravity_tolerance_g: float = GRAVITY_TOLERANCE_G, clock: Clock | None = None) -> PingReport:
    """Connect to each instrument, read what can be read without moving anything, check gravity."""
    clock = clock or (WallClock() if config.clock.speed == 1.0 else ScaledClock(config.clock.speed))
    # The rate limit only guards jogs, and the ping never jogs.
    chamber, table, imu = build_drivers(config, clock, max_rate_dps=1.0)
    pings = {kind: InstrumentPing(kind, config.instrument(kind).driver.name) for kind in ("chamber", "table", "imu")}
    for kind, driver in (("chamber", chamber), ("table", table), ("imu", imu)):
        pings[kind].address = str(getattr(driver, "address", "?"))
    report = PingReport(list(pings.values()))
    try:
        c = pings["chamber"]
        _try(c, "connect", chamber.connect)
        ident = _try(c, "identity", chamber.identity)
        if ident is not None:
            c.lines.append(_identity_words(ident))
        lo_hi = _try(c, "setpoint range", chamber.setpoint_range)
        pv = _try(c, "temperature", chamber.read_temperature)
        sp = _try(c, "setpoint", chamber.read_setpoint)
        if c.ok:
            c.lines.append(f"setpoint range {lo_hi[0]:g}..{lo_hi[1]:g} C, air {pv:.2f} C, setpoint {sp:g} C")

        t = pings["table"]
        _try(t, "connect", table.connect)
        ident = _try(t, "identity", table.identity)
        if ident is not None:
            t.lines.append(_identity_words(ident))
        limits = getattr(table, "limits", None)
        if limits is not None:
            lim = _try(t, "limits", limits)
            if lim is not None:
                t.lines.append(f"limits {lim[0]:g} deg/s, {lim[1]:g} deg/s^2")
        v = _try(t, "velocity", table.velocity)
        st = _try(t, "status", table.status)
        if t.ok:
            t.lines.append(f"velocity {v:+.4f} deg/s, status {st.mode}{' settled' if st.settled else ''}"
                           f"{' fault ' + st.fault if st.fault else ''}")

        i = pings["imu"]
        _try(i, "connect", imu.connect)
        accel = _try(i, f"{read_s:g} s of frames", lambda: read_accel(imu, clock.sleep, read_s, timeout_s=2.0))
        if accel is not None:
            i.lines.append(f"{len(accel)} frames in {read_s:g} s (expected {round(read_s * imu.rate_hz)} at "
                           f"{imu.rate_hz:g} Hz)")
            report.gravity, report.gravity_problem = _gravity(accel, max_tilt_deg, gravity_tolerance_g)
    finally:
        for driver in (imu, table, chamber):
            try:
                driver.close()
            except Exception as exc:  # closing a broken link must not hide what the ping found
                log.debug("closing %s: %s", type(driver).__name__, exc)
    return report


def _identity_words(ident: Any) -> str:
    extra = ", ".join(f"{k} {v}" for k, v in sorted(ident.extra.items()))
    serial = f" serial {ident.serial}" if ident.serial else ""
    return f"identity {ident.vendor} {ident.model}{serial}" + (f" ({extra})" if extra else "")


__all__ = ["InstrumentPing", "PingReport", "ping_lab"]
