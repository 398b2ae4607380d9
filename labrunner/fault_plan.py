"""Faults injected into the simulated lab on a schedule, to rehearse a bad night.

A fault plan is a list of faults, each with a kind and a duration (or a count), at a
campaign time (`at_s`) or a random delay (`after_s`) after the sequencer reaches a step
(`at_step`; it then strikes no later than the start of the next step, so every one lands
inside the campaign). `random_fault_plan` spreads N seeded random faults over a
procedure's steps; `FaultInjector` applies them to a `SimLab` as the campaign passes
them, clears them when they end, and logs every injection as an event row.
The sequencer's answer (retries, reconnects, re-recording, pause and resume) is
logged by the sequencer itself.

The kinds are `labrunner.fault_kinds.FaultKind`; the injector reaches the simulated lab
only through its `FaultTarget` interface (`apply_fault`, `clear_fault`).

A plan's faults fire once per campaign, not once per session: every injection is an event with
the fault in its detail, and a resumed campaign skips the faults its store says fired already
(a fault anchored to the step being resumed fired before the kill, and must not fire again).
"""

from __future__ import annotations

import json
import logging
import random
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import Any

from labrunner.clock import VirtualClock
from labrunner.fault_kinds import INTERLOCK_KINDS as _INTERLOCKS
from labrunner.fault_kinds import FaultKind, FaultTarget, fault_kind
from labrunner.yaml_config import ConfigError

_log = logging.getLogger(__name__)  # `log` is the injector's event sink

KINDS: tuple[str, ...] = tuple(k.value for k in FaultKind)
INTERLOCK_KINDS: tuple[str, ...] = tuple(k for k in KINDS if k in _INTERLOCKS)
# Random plans draw from the faults a lab meets at night; interlock trips are rehearsed on purpose.
RANDOM_KINDS = tuple(k for k in KINDS if k not in INTERLOCK_KINDS)
DURATIONS_S = {  # (low, high) for random plans
    "modbus_timeout": (5, 120), "modbus_outage": (10, 300), "heater_failure": (300, 2400),
    "compressor_failure": (300, 2400), "garbage_pv": (2, 60), "table_fault": (5, 120), "table_silent": (2, 60),
    "table_garbage": (2, 30), "imu_stall": (2, 90), "table_link_drop": (2, 60), "imu_link_drop": (2, 60),
    "heater_stuck": (600, 3600), "table_overspeed": (30, 300), "imu_overheat": (300, 1800),
}
COUNTS = {"modbus_exception": (1, 6), "modbus_busy": (1, 3), "imu_corrupt": (1, 40), "imu_gap": (1, 25)}
MAX_RANDOM_FAULTS = 10_000  # a bad night has dozens; a million would only take minutes to plan


@dataclass
class Fault:
    kind: str
    at_s: float | None = None  # campaign time, or:
    at_step: int | None = None  # ... this long after the sequencer reaches this step
    after_s: float = 0.0
    duration_s: float = 0.0
    count: int = 0

    def __post_init__(self) -> None:
        self.kind = fault_kind(self.kind).value  # a plain str, so plans dump to YAML and JSON as written
        if (self.at_s is None) == (self.at_step is None):
            raise ValueError(f"fault {self.kind}: give at_s (campaign time) or at_step (a step index)")


def _at_s(f: Fault) -> float:
    assert f.at_s is not None, "a timed fault"
    return f.at_s


def _at_step(f: Fault) -> int:
    assert f.at_step is not None, "a fault anchored to a step"
    return f.at_step


def _key(spec: dict[str, Any]) -> tuple[Any, ...]:
    """What identifies a planned fault (its plan entry), as its injection event's detail records it."""
    f = asdict(Fault(**spec))
    return tuple(sorted(f.items()))


def not_fired(faults: Iterable[Fault], fired: Iterable[dict[str, Any]]) -> list[Fault]:
    """The faults of a plan that have not fired yet, given the details of the injection events stored.

    A plan may hold the same fault twice: each injection accounts for one of them."""
    seen = Counter(_key(d) for d in fired)
    ahead = []
    for f in faults:
        k = _key(asdict(f))
        if seen[k] > 0:
            seen[k] -= 1
        else:
            ahead.append(f)
    return ahead


def fired_faults(store: Any, campaign_id: int) -> list[dict[str, Any]]:
    """The plan entries of the faults a campaign's store logged as injected (`injected` events)."""
    ev = store.events_frame(campaign_id)
    out = []
    for detail in ev.loc[ev.kind == "injected", "detail"]:
        try:
            d = json.loads(detail) if isinstance(detail, str) else None
            if isinstance(d, dict):
                _key(d)  # a detail that is not a fault is not one of the plan's
                out.append(d)
        except (ValueError, TypeError):
            continue
    return out


def random_fault_plan(procedure: Any, n: int, seed: int) -> list[dict[str, Any]]:
    """N faults of random kinds at random moments across the procedure's steps (seeded)."""
    if not 0 <= n <= MAX_RANDOM_FAULTS:
        raise ConfigError([f"--faults {n}: the number of random faults must be in 0..{MAX_RANDOM_FAULTS}"])
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

    def __init__(self, sim: FaultTarget, faults: list[Fault], t_zero: float,
                 log: Callable[[str, str, dict[str, Any]], None] | None = None,
                 progress: Callable[[], int | None] | None = None) -> None:
        self.sim = sim
        self.timed = sorted((f for f in faults if f.at_s is not None), key=_at_s)
        self.by_step = sorted((f for f in faults if f.at_step is not None), key=lambda f: (_at_step(f), f.after_s))
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
        # A resumed campaign replays only what is still ahead of it and has not fired in an earlier session.
        faults = [f for f in faults if (f.at_s is not None and f.at_s >= t_now)
                  or (f.at_step is not None and k_now is not None and f.at_step >= k_now)]
        faults = not_fired(faults, fired_faults(runner.store, runner.cid))

        def log(kind: str, message: str, detail: dict[str, Any]) -> None:
            # Called on a clock listener: a store failure is left for the sequencer to act on.
            runner.log_event(kind, message, detail, raise_failure=False)

        if lab.sim is None or not isinstance(lab.clock, VirtualClock):
            raise ValueError("a fault plan needs the simulated lab of a dry run (a virtual clock)")
        inj = cls(lab.sim, faults, runner.t_zero, log, progress=lambda: runner.k)
        lab.clock.add_listener(inj.on_time)
        _log.info("fault plan attached: %d fault(s) ahead", inj.pending)
        runner.fault_injector = inj
        return inj

    def on_time(self, clock_now: float) -> None:
        t = clock_now - self.t_zero
        for end, fault in list(self.active):
            if t >= end:
                self.active.remove((end, fault))
                self._clear(fault)
                _log.info("fault cleared at t=%.1f s: %s", t, fault.kind)
        due: list[Fault] = []
        while self.timed and _at_s(self.timed[0]) <= t:
            due.append(self.timed.pop(0))
        k = self.progress() if self.progress else None
        if k is not None:
            self.reached.setdefault(k, t)
            for f in list(self.by_step):
                start = self.reached.get(_at_step(f))
                if (start is not None and t >= start + f.after_s) or k > _at_step(f):
                    self.by_step.remove(f)
                    due.append(f)
        for fault in due:
            _log.info("fault injected at t=%.1f s: %s (duration %.1f s, count %d)", t, fault.kind,
                      fault.duration_s, fault.count)
            self._apply(fault)
            self.injected += 1
            self.by_kind[fault.kind] = self.by_kind.get(fault.kind, 0) + 1
            if fault.duration_s > 0:
                self.active.append((t + fault.duration_s, fault))
            if self.log:
                what = f"{fault.duration_s:.0f} s" if fault.duration_s else f"x{fault.count}" if fault.count else ""
                self.log("injected", f"fault injected: {fault.kind} {what}".rstrip(), asdict(fault))

    def _apply(self, f: Fault) -> None:
        self.sim.apply_fault(FaultKind(f.kind), duration_s=f.duration_s, count=f.count)

    def _clear(self, f: Fault) -> None:
        self.sim.clear_fault(FaultKind(f.kind))
