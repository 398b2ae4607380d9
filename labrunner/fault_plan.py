"""Faults injected into the simulated lab on a schedule, to rehearse a bad night.

A fault plan is a list of faults, each with a kind and a duration (or a count), at a
campaign time (`at_s`) or a random delay (`after_s`) after the sequencer reaches a step
(`at_step`; it then strikes no later than the start of the next step, so every one lands
inside the campaign). `random_fault_plan` spreads N seeded random faults over a
procedure's steps; `FaultInjector` applies them to a `SimLab` as the campaign passes
them, clears them when they end, and logs every injection as an event row.
The sequencer's answer (retries, reconnects, re-recording, pause and resume) is
logged by the sequencer itself.

Kinds:
  modbus_timeout       the chamber controller stops answering for duration_s
  modbus_exception     it answers `count` requests with exception 4 (device failure)
  modbus_busy          ... with exception 6 (busy): transient, retried
  modbus_drop          every Modbus client connection is dropped
  modbus_outage        connections dropped and refused for duration_s
  heater_failure       the heater cannot heat for duration_s (setpoint not reached or held)
  compressor_failure   the compressor cannot cool for duration_s
  garbage_pv           the process value reads a sensor-break pattern for duration_s
  table_fault          the table reports a drive fault (and stops) for duration_s
  table_silent         the table does not reply for duration_s
  table_garbage        the table replies line noise for duration_s
  imu_stall            the IMU sends nothing for duration_s
  imu_corrupt          the next `count` frames are corrupted on the line
  imu_gap              the next `count` frames are never sent (counter gap)
  table_link_drop      the table's serial line disappears for duration_s, then comes back
  imu_link_drop        the IMU's serial line disappears for duration_s, then comes back
  heater_stuck         (interlock) the heater is stuck on for duration_s
  table_overspeed      (interlock) the drive holds 1.6x the commanded rate for duration_s
  imu_overheat         (interlock) the IMU runs 70 C hotter for duration_s
"""

from __future__ import annotations

import random
from dataclasses import asdict, dataclass
from typing import Any

KINDS = ("modbus_timeout", "modbus_exception", "modbus_busy", "modbus_drop", "modbus_outage", "heater_failure",
         "compressor_failure", "garbage_pv", "table_fault", "table_silent", "table_garbage", "imu_stall", "imu_corrupt",
         "imu_gap", "table_link_drop", "imu_link_drop", "heater_stuck", "table_overspeed", "imu_overheat")
INTERLOCK_KINDS = ("heater_stuck", "table_overspeed", "imu_overheat")
# Random plans draw from the faults a lab meets at night; interlock trips are rehearsed on purpose.
RANDOM_KINDS = tuple(k for k in KINDS if k not in INTERLOCK_KINDS)
DURATIONS_S = {  # (low, high) for random plans
    "modbus_timeout": (5, 120), "modbus_outage": (10, 300), "heater_failure": (300, 2400),
    "compressor_failure": (300, 2400), "garbage_pv": (2, 60), "table_fault": (5, 120), "table_silent": (2, 60),
    "table_garbage": (2, 30), "imu_stall": (2, 90), "table_link_drop": (2, 60), "imu_link_drop": (2, 60),
    "heater_stuck": (600, 3600), "table_overspeed": (30, 300), "imu_overheat": (300, 1800),
}
COUNTS = {"modbus_exception": (1, 6), "modbus_busy": (1, 3), "imu_corrupt": (1, 40), "imu_gap": (1, 25)}


@dataclass
class Fault:
    kind: str
    at_s: float | None = None  # campaign time, or:
    at_step: int | None = None  # ... this long after the sequencer reaches this step
    after_s: float = 0.0
    duration_s: float = 0.0
    count: int = 0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown fault kind {self.kind!r}; known: {', '.join(KINDS)}")
        if (self.at_s is None) == (self.at_step is None):
            raise ValueError(f"fault {self.kind}: give at_s (campaign time) or at_step (a step index)")


def random_fault_plan(procedure: Any, n: int, seed: int) -> list[dict[str, Any]]:
    """N faults of random kinds at random moments across the procedure's steps (seeded)."""
    rng = random.Random(f"faults-{seed}-{n}")
    last = max(len(procedure.steps()) - 2, 0)
    plan = []
    for _ in range(n):
        kind = rng.choice(RANDOM_KINDS)
        lo, hi = DURATIONS_S.get(kind, (0, 0))
        clo, chi = COUNTS.get(kind, (0, 0))
        plan.append(asdict(Fault(kind=kind, at_step=rng.randint(0, last), after_s=round(rng.uniform(0.0, 600.0), 1),
                                 duration_s=round(rng.uniform(lo, hi), 1) if hi else 0.0,
                                 count=rng.randint(clo, chi) if chi else 0)))
    return sorted(plan, key=lambda f: (f["at_step"], f["after_s"]))


class FaultInjector:
    """Applies a fault plan to a simulated lab as the (virtual) clock passes the faults' times."""

    def __init__(self, sim: Any, faults: list[Fault], t_zero: float, log: Any = None,
                 progress: Any = None) -> None:
        self.sim = sim
        self.timed = sorted((f for f in faults if f.at_s is not None), key=lambda f: f.at_s)  # type: ignore[arg-type]
        self.by_step = sorted((f for f in faults if f.at_step is not None), key=lambda f: (f.at_step, f.after_s))
        self.reached: dict[int, float] = {}  # step -> campaign time it was first seen in progress
        self.active: list[tuple[float, Fault]] = []  # (end campaign time, fault)
        self.t_zero = t_zero
        self.log = log  # (kind, message, detail) -> None
        self.progress = progress  # () -> index of the step in progress (None when all are recorded)
        self.injected = 0
        self.by_kind: dict[str, int] = {}

    @property
    def pending(self) -> int:
        return len(self.timed) + len(self.by_step)

    @classmethod
    def attach(cls, runner: Any, lab: Any, spec: dict[str, Any]) -> FaultInjector:
        """Wire a plan from a sim configuration's `faults` (`random` and/or `schedule` lists) to a run."""
        items = list(spec.get("schedule") or []) + list(spec.get("random") or [])
        faults = [Fault(**f) for f in items]
        t_now, k_now = runner.t, runner.k
        # A resumed campaign replays only what is still ahead of it.
        faults = [f for f in faults if (f.at_s is not None and f.at_s >= t_now)
                  or (f.at_step is not None and k_now is not None and f.at_step >= k_now)]

        def log(kind: str, message: str, detail: dict[str, Any]) -> None:
            runner.store.event(runner.cid, runner.t, kind, message, state=runner.state, step_idx=runner.k,
                               detail=detail)

        inj = cls(lab.sim, faults, runner.t_zero, log, progress=lambda: runner.k)
        lab.clock.add_listener(inj.on_time)
        runner.fault_injector = inj
        return inj

    def on_time(self, clock_now: float) -> None:
        t = clock_now - self.t_zero
        for end, fault in list(self.active):
            if t >= end:
                self.active.remove((end, fault))
                self._clear(fault)
        due: list[Fault] = []
        while self.timed and self.timed[0].at_s <= t:  # type: ignore[operator]
            due.append(self.timed.pop(0))
        k = self.progress() if self.progress else None
        if k is not None:
            self.reached.setdefault(k, t)
            for f in list(self.by_step):
                start = self.reached.get(f.at_step)  # type: ignore[arg-type]
                if (start is not None and t >= start + f.after_s) or k > f.at_step:  # type: ignore[operator]
                    self.by_step.remove(f)
                    due.append(f)
        for fault in due:
            self._apply(fault, clock_now)
            self.injected += 1
            self.by_kind[fault.kind] = self.by_kind.get(fault.kind, 0) + 1
            if fault.duration_s > 0:
                self.active.append((t + fault.duration_s, fault))
            if self.log:
                what = f"{fault.duration_s:.0f} s" if fault.duration_s else f"x{fault.count}" if fault.count else ""
                self.log("injected", f"fault injected: {fault.kind} {what}".rstrip(), asdict(fault))

    # Faults that are a flag on a simulated instrument: set while the fault lasts, cleared after.
    FLAGS: dict[str, tuple[Any, str]] = {
        "modbus_timeout": (lambda sim: sim.chamber.faults, "silent"),
        "garbage_pv": (lambda sim: sim.chamber.faults, "garbage_pv"),
        "heater_failure": (lambda sim: sim.world.chamber, "heater_failed"),
        "compressor_failure": (lambda sim: sim.world.chamber, "compressor_failed"),
        "heater_stuck": (lambda sim: sim.world.chamber, "heater_stuck"),
        "table_silent": (lambda sim: sim.table.faults, "silent"),
        "table_garbage": (lambda sim: sim.table.faults, "garbage"),
    }

    def _apply(self, f: Fault, clock_now: float) -> None:
        sim, k = self.sim, f.kind
        if k in self.FLAGS:
            target, attr = self.FLAGS[k]
            setattr(target(sim), attr, True)
        elif k in ("modbus_exception", "modbus_busy"):
            ch = sim.chamber.faults
            ch.exception_code, ch.exception_count = (4 if k == "modbus_exception" else 6), max(1, f.count)
        elif k == "modbus_drop":
            sim.chamber.drop_connections()
        elif k == "modbus_outage":
            sim.chamber.refuse_connections(True)
        elif k == "table_fault":
            sim.table.faults.fault = "E17 OVERCURRENT"
            with sim.world.lock:
                sim.world.table.command(clock_now, 0.0)  # a faulted drive coasts to rest
        elif k == "imu_stall":
            sim.imu.faults.stall_from, sim.imu.faults.stall_until = clock_now, clock_now + f.duration_s
        elif k == "imu_corrupt":
            sim.imu.faults.corrupt_frames += max(1, f.count)
        elif k == "imu_gap":
            sim.imu.faults.skip_frames += max(1, f.count)
        elif k in ("table_link_drop", "imu_link_drop"):
            port = sim.table_port if k == "table_link_drop" else sim.imu_port
            if hasattr(port, "refusing"):
                port.refusing = True
                port.disconnect()
        elif k == "table_overspeed":
            with sim.world.lock:
                sim.world.table.overspeed = 1.6
                sim.world.table.command(clock_now, sim.world.table.commanded_dps)
        elif k == "imu_overheat":
            sim.world.imu_extra_heat_c = 70.0

    def _clear(self, f: Fault) -> None:
        sim, k = self.sim, f.kind
        if k in self.FLAGS:
            target, attr = self.FLAGS[k]
            setattr(target(sim), attr, False)
        elif k == "modbus_outage":
            sim.chamber.refuse_connections(False)
        elif k == "table_fault":
            sim.table.faults.fault = None
        elif k in ("table_link_drop", "imu_link_drop"):
            port = sim.table_port if k == "table_link_drop" else sim.imu_port
            if hasattr(port, "refusing"):
                port.refusing = False
        elif k == "table_overspeed":
            with sim.world.lock:
                sim.world.table.overspeed = 1.0
        elif k == "imu_overheat":
            sim.world.imu_extra_heat_c = 0.0
