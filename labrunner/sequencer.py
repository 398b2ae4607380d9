"""The campaign sequencer: a `transitions` state machine that drives the lab through a procedure.

States: idle -> preflight -> mounting -> ramping -> soaking -> rate_settling ->
recording -> (rate_settling | ramping | mounting | fitting) ... -> done, plus paused,
safe_stop -> aborted, and failed. Each state has a handler that does that state's
work through the instrument interfaces (`drivers.protocols`) and fires the next
transition; every transition is an event row with its time.

The runner only sequences. What it judges on the way is asked of small objects in
`labrunner.runner`: the soak window (`soak`), the monitor means (`monitor`), the
interlocks (`interlocks`), the fault policy and auto-resume (`fault_policy`) and the
one safe stop (`safe_stop`).

Resuming is running the same machine again: it starts at idle and fires real
transitions (preflight, mounting for the first step not yet recorded, ...), so
every callback runs and nothing is entered by assignment.

Pause requests (first Ctrl-C, `labrunner` control table) take effect at the next
safe point: between polls while ramping or soaking, after a record step is
committed. Abort requests (second Ctrl-C, `labrunner abort`) bring the lab to its
safe state: table stopped, chamber to the remount (ambient) temperature.

Whatever fails — an instrument past its retries, the store (disk full, lost
connection, read-only file), a bug — `run` does not raise: the lab goes to its
safe state first, and the store is not touched from the moment the sequencer leaves
for the safe stop until the lab is safe (the events meanwhile wait in
`runner.journal`). Then the run's end is recorded; a store failure ends the run
`failed`, and if the store still cannot be written the returned state is `failed`
with `last_error` saying so in one line (the campaign stays marked running, which
`labrunner status` and `resume` read as interrupted once the process is gone).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from transitions import EventData, Machine

from labrunner.clock import Clock
from labrunner.drivers.errors import InstrumentError, LimitError
from labrunner.drivers.protocols import ImuRecord
from labrunner.drivers.protocols import Instruments as Lab
from labrunner.procedure import Procedure, ProcedureModel, Step
from labrunner.runner.control import Control, RunStats, StoreRequests
from labrunner.runner.fault_log import FaultLog
from labrunner.runner.fault_policy import Action, AutoResume, FaultPolicy
from labrunner.runner.interlocks import Interlocks, Readings
from labrunner.runner.journal import Journal
from labrunner.runner.last_state import last_mount
from labrunner.runner.monitor import ImuMonitor
from labrunner.runner.mount_check import InPlace, MountVerdict, in_place, judge, read_accel
from labrunner.runner.preflight import check_chamber, check_table
from labrunner.runner.safe_stop import safe_stop
from labrunner.runner.soak import SoakProgress, SoakWindow, soak_timeout
from labrunner.store import SampleBlock, Store, StoreError

log = logging.getLogger(__name__)

STATES = ["idle", "preflight", "mounting", "ramping", "soaking", "rate_settling", "recording", "fitting", "done",
          "paused", "safe_stop", "aborted", "failed"]
ACTIVE = ["preflight", "mounting", "ramping", "soaking", "rate_settling", "recording", "fitting"]
TERMINAL = {"done", "paused", "aborted", "failed"}
ABORTABLE = ACTIVE + ["paused", "idle"]
TRANSITIONS: list[dict[str, Any]] = [
    {"trigger": "start", "source": "idle", "dest": "preflight"},
    {"trigger": "preflight_ok", "source": "preflight", "dest": "mounting"},
    {"trigger": "resume_mounted", "source": "preflight", "dest": "ramping"},
    {"trigger": "mounted", "source": "mounting", "dest": "ramping"},
    {"trigger": "at_setpoint", "source": "ramping", "dest": "soaking"},
    {"trigger": "soaked", "source": "soaking", "dest": "rate_settling"},
    {"trigger": "settled", "source": "rate_settling", "dest": "recording"},
    {"trigger": "next_rate", "source": "recording", "dest": "rate_settling"},
    {"trigger": "record_again", "source": "recording", "dest": "rate_settling"},
    {"trigger": "next_temperature", "source": "recording", "dest": "ramping"},
    {"trigger": "next_orientation", "source": "recording", "dest": "mounting"},
    {"trigger": "all_recorded", "source": ["recording", "preflight"], "dest": "fitting"},
    {"trigger": "fitted", "source": "fitting", "dest": "done"},
    {"trigger": "pause", "source": ACTIVE, "dest": "paused"},
    {"trigger": "resume", "source": "paused", "dest": "preflight"},
    {"trigger": "abort", "source": ABORTABLE, "dest": "safe_stop"},
    {"trigger": "stopped_safely", "source": "safe_stop", "dest": "aborted"},
    {"trigger": "fail", "source": ACTIVE + ["safe_stop", "idle"], "dest": "failed"},
]
TABLE_SETTLE_S = 120.0  # a table that has not settled at its rate by then has a drive problem

Progress = Callable[["CampaignRunner"], None]
Trigger = Callable[[], bool]


class _Stop(Exception):
    """Leaves a state handler because a pause or abort took over."""


class NoCurrentStep(RuntimeError):
    """A handler asked for the current step when every step is recorded (a sequencing bug)."""


class CampaignRunner:
    """Runs (or resumes) one campaign of a store on a lab."""

    # Bound by `transitions.Machine` (declared, not defined, so the machine can bind them).
    state: str
    start: Trigger
    preflight_ok: Trigger
    resume_mounted: Trigger
    mounted: Trigger
    at_setpoint: Trigger
    soaked: Trigger
    settled: Trigger
    next_rate: Trigger
    record_again: Trigger
    next_temperature: Trigger
    next_orientation: Trigger
    all_recorded: Trigger
    fitted: Trigger
    pause: Trigger
    resume: Trigger
    abort: Trigger
    stopped_safely: Trigger
    fail: Trigger

    def __init__(self, procedure: Procedure, lab: Lab, store: Store, campaign_id: int, *,
                 progress: Progress | None = None, fit_out_dir: str | Path | None = None,
                 auto_resume_s: float | None = None, max_auto_resumes: int = 200) -> None:
        self.procedure = procedure
        self.p: ProcedureModel = procedure.model
        self.lab = lab
        self.clock: Clock = lab.clock
        self.store = store
        self.cid: int = campaign_id
        self.plan: list[Step] = procedure.steps()
        self.progress = progress
        self.fit_out_dir = fit_out_dir
        self.control = Control()
        self.stats = RunStats()
        info = store.campaign(campaign_id)
        self.t_zero = info.clock_t0
        self.run_no = store.max_run(campaign_id)
        self.k: int | None = store.next_step(campaign_id)
        self.mounted_orientation: str | None = None
        self.last_error: str | None = None
        self.fit_summary: str | None = None
        self.fit_ok = False
        self.store_failure: StoreError | None = None  # the store failure that ended the run
        self.lab_safe = False  # the safe stop (or the park before fitting) reached the safe state
        self.journal = Journal(store, campaign_id)
        self.requests = StoreRequests(store, campaign_id, self.clock, self.control)
        self._soak_started: float | None = None  # when the current ramp began: the soak's deadline counts from it
        self.interlocks = Interlocks.from_safety(self.p.safety)
        self.policy = FaultPolicy(self.p.faults)
        self.auto_resume = AutoResume(auto_resume_s, max_auto_resumes)
        self._chamber_reading: tuple[float, float] | None = None  # (clock time, °C) of the last chamber read
        self.monitor = ImuMonitor(lab.imu, lab.chamber, lambda: self.t, self.p.monitor.average_s,
                                  read_chamber=self._read_chamber)
        self.fault_log = FaultLog(self.stats, self.event, self.event_from_thread)
        self.fault_log.attach(lab.chamber, lab.table, lab.imu)
        self.fault_injector: Any = None  # set by labrunner.fault_plan in dry runs with injected faults
        # The latest readings the handlers took, for the live view (read, never acted on): nothing is
        # read from an instrument for a display.
        self.chamber_c: float | None = None
        self.imu_temp_c: float | None = None
        self._soak_window: SoakWindow | None = None
        self.machine = Machine(model=self, states=STATES, transitions=TRANSITIONS, initial="idle",
                               auto_transitions=False, after_state_change="_log_transition", send_event=True)

    # --- what the CLI and the API read ---------------------------------------------------------

    @property
    def auto_resume_s(self) -> float | None:
        return self.auto_resume.delay_s

    @property
    def max_auto_resumes(self) -> int:
        return self.auto_resume.max_resumes

    @property
    def auto_resumes(self) -> int:
        return self.auto_resume.resumes

    @property
    def step(self) -> Step:
        """The step being worked on; every handler before fitting has one."""
        if self.k is None:
            raise NoCurrentStep(f"campaign {self.cid}: no current step in state {self.state} (all steps recorded)")
        return self.plan[self.k]

    def done_steps(self) -> int:
        return len(self.plan) if self.k is None else self.k

    def current_step(self) -> Step | None:
        return None if self.k is None else self.plan[self.k]

    def soak_progress(self) -> SoakProgress | None:
        """How close the soak in progress is to stable (None unless soaking)."""
        window = self._soak_window
        return window.progress() if window is not None and self.state == "soaking" else None

    def _saw(self, chamber_c: float | None = None, imu_c: float | None = None) -> None:
        """Keep the latest readings for the live view."""
        if chamber_c is not None:
            self.chamber_c = chamber_c
        if imu_c is not None and np.isfinite(imu_c):
            self.imu_temp_c = imu_c

    def _read_chamber(self) -> float:
        """The chamber's temperature, read once per moment of clock time.

        A poll and the monitor stretch it opens (or closes) want the reading of one moment: a second
        Modbus request while the clock stands still could only return the same value (a simulated lab
        changes only when its virtual clock advances; on a real clock the time never repeats, so every
        call reads). Halves the chamber requests of a dry run's ramps and soaks."""
        now = self.clock.now()
        cached = self._chamber_reading
        if cached is not None and cached[0] == now:
            return cached[1]
        pv = self.lab.chamber.read_temperature()
        # A read that let the clock move (a retry's backoff) is not a reading of one moment.
        self._chamber_reading = (now, pv) if self.clock.now() == now else None
        return pv

    # --- time, events, requests ------------------------------------------------------------

    @property
    def t(self) -> float:
        """Campaign time, s."""
        return self.clock.now() - self.t_zero

    def _log_transition(self, event_data: EventData | None = None) -> None:
        src = event_data.transition.source if event_data is not None and event_data.transition else "?"
        self.log_event("transition", f"{src} -> {self.state}")
        self._report()

    def event(self, kind: str, message: str, **detail: Any) -> None:
        self.log_event(kind, message, detail or None)

    def event_from_thread(self, kind: str, message: str, **detail: Any) -> None:
        """An event from another thread (the IMU reader): a store failure is left for the sequencer."""
        self.log_event(kind, message, detail or None, raise_failure=False)

    def log_event(self, kind: str, message: str, detail: dict[str, Any] | None = None, *,
                  raise_failure: bool = True) -> None:
        """An event at the current campaign time, state and step (held while the lab is made safe)."""
        self.journal.write(self.t, kind, message, state=self.state, step_idx=self.k, detail=detail,
                           raise_failure=raise_failure)

    def _report(self) -> None:
        if self.progress:
            self.progress(self)

    def request_pause(self, reason: str = "pause requested") -> None:
        self.control.request_pause(reason)

    def request_abort(self, reason: str = "abort requested") -> None:
        self.control.request_abort(reason)

    def _check_requests(self, *, allow_pause: bool = True) -> None:
        """At a safe point: act on pause/abort requests (from signals, or from the store)."""
        self.journal.raise_failure()  # met by another thread meanwhile
        if self.fault_log.retrying:
            self.fault_log.note_recoveries()
        self.requests.poll()
        if self.control.abort:
            self.event("operator", self.control.reason)
            self.abort()
            raise _Stop
        if self.control.pause and allow_pause:
            self.event("operator", self.control.reason)
            self.pause()
            raise _Stop

    def _wait(self, seconds: float) -> None:
        """Let clock time pass, looking at requests at least every real second."""
        clock = self.clock
        if clock.virtual:
            clock.sleep(seconds)
            self._check_requests(allow_pause=False)
            return
        end = clock.now() + seconds
        per_real_second = 1.0 / max(clock.wall_seconds(1.0), 1e-9)  # clock seconds in one real second
        while True:
            remaining = end - clock.now()
            if remaining <= 0:
                return
            clock.sleep(min(remaining, per_real_second))
            self._check_requests(allow_pause=False)

    def _grace(self, seconds: float) -> float:
        """Real seconds to wait for `seconds` of IMU frames to arrive."""
        return 0.5 if self.clock.virtual else self.clock.wall_seconds(seconds) + 5.0

    # --- the loop ------------------------------------------------------------------------------

    def run(self) -> str:
        """Run until done, paused, aborted or failed; returns the final state. Never raises for a
        failure of the instruments or the store (see the module's docstring)."""
        self._guarded(self._begin)
        while True:
            if self.state in TERMINAL and not self._leave_terminal():
                break
            if self.state not in TERMINAL:
                self._guarded(getattr(self, f"_do_{self.state}"))
        return self._finish()

    def _begin(self) -> None:
        self.store.set_status(self.cid, "running", clock_last=self.clock.now(), pid=os.getpid())
        self.event("info", f"campaign {'resumed' if self.k not in (None, 0) else 'started'} at step {self.k}",
                   mode=self.store.campaign(self.cid).mode)
        self.start()

    def _leave_terminal(self) -> bool:
        """At a final state, what still moves the machine: True when it went on."""
        if self.state != "paused":
            return False
        if self.control.abort:
            self._guarded(self.abort)  # a second Ctrl-C (or labrunner abort) right after the pause took effect
            return True
        if self.auto_resume.due():
            self._guarded(self._auto_resume)
            return True
        return False

    def _auto_resume(self) -> None:
        assert self.auto_resume.delay_s is not None
        self.clock.sleep(self.auto_resume.delay_s)
        n = self.auto_resume.take()
        self.event("recovery", f"resuming after a fault pause (auto-resume {n})")
        self.resume()

    def _guarded(self, action: Callable[[], object]) -> None:
        """Run a handler; whatever it raises becomes a decision of the fault policy or a safe stop."""
        try:
            action()
        except _Stop:
            return
        except InstrumentError as exc:
            try:
                self._fault(exc, hard=isinstance(exc, LimitError))
            except Exception as during:  # the fault's event or transition met a failing store
                self._unexpected(during)
        except Exception as exc:
            self._unexpected(exc)

    def _unexpected(self, exc: Exception) -> None:
        """The store failed, or something unforeseen did: bring the lab to its safe state before the store
        is touched again (the journal holds every event until the lab is safe), keep the data."""
        self.journal.hold()
        where = self.state
        if isinstance(exc, StoreError):
            self.store_failure = self.store_failure or exc
            self.last_error = str(exc)
            log.info("store failed in %s: %s; bringing the lab to its safe state", where, exc)
            self.event("fault", f"store failed in {where}: {exc}", database=str(exc.path))
        else:
            self.last_error = f"{type(exc).__name__}: {exc}"
            log.error("unexpected error in %s: %s", where, self.last_error, exc_info=log.isEnabledFor(logging.DEBUG))
            self.event("fault", f"unexpected error in {where}: {self.last_error}")
        if where == "idle":
            self.fail()  # nothing was driven yet: there is nothing to make safe
        elif where in ABORTABLE:
            self.abort()
        elif where == "safe_stop":
            self.fail()

    def _finish(self) -> str:
        """Record how the run ended: what the journal held during the safe stop, then the status. A store
        that cannot take it gives `failed` and a `last_error` that says so."""
        failure = self._record_end()
        if failure is not None and self.state == "paused":
            # The pause cannot be recorded: the store failed, so the lab goes to its safe state as for
            # any store failure, and the run ends failed.
            self._unexpected(failure)
            self._guarded(self._do_safe_stop)
            failure = self._record_end()
        self._report()
        if failure is None:
            return str(self.state)
        outcome = "the lab is in its safe state" if self.lab_safe else "the lab is NOT in its safe state"
        self.last_error = (f"{failure}; {outcome}; the campaign's end ({self.state}) could not be recorded "
                           "(it shows as interrupted: resume it once the database can be written)")
        log.info("campaign %d: %s", self.cid, self.last_error)
        return "failed"

    def _record_end(self) -> StoreError | None:
        failure = self.journal.flush()
        if failure is not None:
            return failure
        try:
            self.store.set_status(self.cid, self.state, clock_last=self.clock.now(), pid=None)
            self.store.request(self.cid, None)
        except StoreError as exc:
            return exc
        return None

    def _act(self, action: Action, *, by_fault: bool = True) -> None:
        """Carry out a pause, abort or fail decided by the fault policy."""
        if action == "fail":
            self.fail()
        elif action == "abort":
            self.abort()
        else:
            if by_fault:
                self.auto_resume.fault_paused()
            self.pause()

    def _fault(self, exc: InstrumentError, hard: bool = False) -> None:
        """An instrument failed after its bounded retries: apply the procedure's fault policy."""
        self.stats.faults += 1
        self.last_error = str(exc)
        self.event("fault", str(exc), instrument=exc.instrument, address=exc.address, state=self.state)
        self._act(self.policy.on_instrument_error(hard=hard, in_safe_stop=self.state == "safe_stop"))

    def _soak_timeout(self, what: str) -> bool:
        """The chamber did not stabilise in time: apply soak.on_timeout. True means carry on."""
        target = self.p.remount_c if what == "remount" else self.step.temperature_c
        verdict = soak_timeout(self.p.soak, what, target)
        self.event(verdict.event_kind, verdict.message)
        if verdict.carry_on:
            return True
        self.last_error = verdict.message
        self._act("pause" if verdict.action == "pause" else "abort")
        return False

    def _interlocks(self, *, chamber_c: float | None = None, rate_dps: float | None = None,
                    imu_temp: float | None = None) -> None:
        """Ask the interlocks about what was just read; a trip goes to the safe stop."""
        trip = self.interlocks.check(Readings(chamber_c=chamber_c, rate_dps=rate_dps, imu_temp_c=imu_temp))
        if trip is not None:
            self.last_error = f"interlock: {trip.reason}"
            self.event("interlock", trip.reason)
            self.abort()
            raise _Stop

    # --- state handlers --------------------------------------------------------------------------

    def _do_preflight(self) -> None:
        lab = self.lab
        for inst in (lab.chamber, lab.table, lab.imu):
            inst.connect()
        identity, message = check_chamber(lab.chamber, self.p.temperatures.values() + [self.p.remount_c])
        self.event("info", message, identity=identity)
        table = check_table(lab.table, self.p.rates.values())
        if table is not None:
            self.event("info", table[1], identity=table[0])
        lab.table.stop()
        self._wait(1.0)
        if lab.imu.latest() is None:
            deadline = time.monotonic() + 5.0
            while lab.imu.latest() is None and time.monotonic() < deadline:
                self._wait(0.5)
        sample = lab.imu.latest()
        if sample is None:
            raise InstrumentError(lab.imu.name, lab.imu.address, "no frames from the IMU (is it powered and is the "
                                  "baud rate right?)")
        self.event("info", f"IMU streams at {lab.imu.address}; temperature {sample.temp_c:.2f} C")
        self._saw(imu_c=sample.temp_c)
        self._interlocks(imu_temp=sample.temp_c)
        self._check_requests()
        if self.k is None:
            self.all_recorded()
            return
        # The same gravity check as after a remount, for the orientation the next step plans.
        verdict = self._check_mount(self.step.orientation)
        if verdict is not None:
            # Before a campaign's first mount a mismatch is news, not a problem: the operator mounts it next.
            self.event("info", f"preflight mount check: {verdict.describe()}"
                       + ("" if verdict.ok else " (the remount prompt follows)"), **verdict.detail())
        if self.mounted_orientation == self.step.orientation and (verdict is None or verdict.ok):
            self.resume_mounted()  # resumed in the same session: the IMU is still mounted and powered
        elif self._resume_in_place(verdict):
            self.resume_mounted()
        else:
            self.mounted_orientation = None
            self.preflight_ok()

    def _check_mount(self, planned: str) -> MountVerdict | None:
        """A second or so of accelerometer frames judged against `planned` (None: the check is off)."""
        check = self.p.mount_check
        if not check.enabled:
            return None
        imu = self.lab.imu
        accel = read_accel(imu, self._wait, check.read_s, self._grace(check.read_s))
        if not len(accel):
            # Silence is the IMU's (or its link's) failure, not the mount's: the fault policy decides.
            raise InstrumentError(imu.name, imu.address, f"no IMU frames in {check.read_s:g} s for the mount check "
                                  f"of {planned} (is it powered and connected?)")
        return judge(accel, planned, max_angle_deg=check.max_angle_deg,
                     gravity_tolerance_g=check.gravity_tolerance_g)

    def _resume_in_place(self, verdict: MountVerdict | None) -> bool:
        """A campaign mounted before (another session, a crash): go on without a remount or a ramp to room
        temperature when the IMU still stands as the next step plans and the chamber is near its setpoint."""
        if not self.p.resume.in_place or self.mounted_orientation is not None:
            return False
        before = last_mount(self.store, self.cid)
        if before is None:
            return False  # never mounted: the operator mounts the first orientation (and gravity checks it)
        step = self.step
        pv = self.lab.chamber.read_temperature()
        self._saw(pv)
        self._interlocks(chamber_c=pv)
        decision = in_place(verdict, pv, step.temperature_c, self.p.resume.chamber_tolerance_c)
        if decision.ok and before.orientation != step.orientation:
            # Gravity agrees, but the sequencer last mounted another orientation: it was turned behind its
            # back (a new run, unrecorded), so it is mounted again, through the prompt.
            decision = InPlace(False, f"the last mount the campaign recorded was {before.orientation}, the next "
                                      f"step plans {step.orientation}")
        if not decision.ok:
            self.event("info", f"resume: remounting: {decision.reason}", orientation=step.orientation)
            return False
        # The IMU was never powered off: the data go on in the run it was in.
        self.run_no = max(self.run_no, before.run)
        self.mounted_orientation = step.orientation
        self.event("info", f"resumed in place: {decision.reason}; step {step.index} ({step.orientation}, "
                           f"{step.temperature_c:g} C) without a remount or a ramp to room temperature (run "
                           f"{self.run_no})", orientation=step.orientation, run=self.run_no, chamber_c=pv)
        return True

    def _do_mounting(self) -> None:
        step = self.step
        lab = self.lab
        lab.table.stop()
        # The operator opens the chamber: bring it near room temperature first.
        lab.chamber.set_setpoint(self.p.remount_c)
        if not self._wait_chamber(self.p.remount_c, max(2.0, self.p.soak.tolerance_c), self.p.soak.max_wait_s) \
                and not self._soak_timeout("remount"):
            return
        self.mounted_orientation = None  # from the prompt on, nothing is mounted until gravity says so
        asked = self.procedure.prompt_for(step.orientation)
        prompt = asked
        tries = self.p.mount_check.tries
        for attempt in range(1, tries + 1):
            self.event("operator", f"remount: {prompt}", orientation=step.orientation, attempt=attempt)
            self._report()
            lab.operator.remount(step.orientation, prompt)
            lab.imu.restart_stream()
            verdict = self._check_mount(step.orientation)
            if verdict is None or verdict.ok:
                break
            self.event("warning", f"mount refused (try {attempt} of {tries}): {verdict.describe()}",
                       **verdict.detail())
            prompt = f"{asked} The IMU does not stand as planned ({verdict.describe()}); mount it again."
        else:
            assert verdict is not None
            self.last_error = (f"mount of {step.orientation} not confirmed by gravity in {tries} tries "
                               f"({verdict.describe()}); pausing: mount the IMU {step.orientation}, then resume")
            self.event("fault", self.last_error, **verdict.detail())
            self._act("pause", by_fault=False)  # a person must look at it: no auto-resume
            return
        self.run_no += 1
        self.mounted_orientation = step.orientation
        checked = f"; gravity: {verdict.measured_words()}" if verdict is not None else ""
        self.event("operator", f"IMU mounted {step.orientation}, powered on (run {self.run_no}){checked}",
                   orientation=step.orientation, run=self.run_no)
        self.mounted()

    def _do_ramping(self) -> None:
        step = self.step
        self.lab.chamber.set_setpoint(step.temperature_c)
        self.event("info", f"setpoint {step.temperature_c} C", setpoint_c=step.temperature_c)
        self._soak_started = self.t
        if not self._wait_chamber(step.temperature_c, self.p.soak.tolerance_c, self.p.soak.max_wait_s) \
                and not self._soak_timeout("ramp"):
            return
        self.at_setpoint()

    def _do_soaking(self) -> None:
        step = self.step
        s = self.p.soak
        window = self._soak_window = SoakWindow(s, step.temperature_c, horizon_s=self.p.record_s)
        started = self._soak_started if self._soak_started is not None else self.t
        deadline = started + s.max_wait_s
        fallback_told = False
        while True:
            pv = self._read_chamber()
            sample = self.lab.imu.latest()
            imu_t = sample.temp_c if sample is not None else float("nan")
            self._interlocks(chamber_c=pv, imu_temp=imu_t)
            window.add(self.t, pv, imu_t)
            self._saw(pv, imu_t)
            self._report()  # the soak's progress, poll by poll
            stable = window.stable()
            if window.fallback is not None and not fallback_told:
                fallback_told = True
                self.event("warning", f"predictive soak at {step.temperature_c} C falls back to the spread "
                                      f"criterion: {window.fallback}", criterion="spread", reason=window.fallback)
            if stable:
                fit = window.prediction if window.fallback is None else None
                how = f" (predictive: {fit.describe()})" if fit is not None else ""
                self.event("info", f"soaked at {step.temperature_c} C: chamber {pv:.2f} C, IMU {imu_t:.2f} C{how}",
                           chamber_c=pv, imu_temp_c=imu_t, **(fit.detail() if fit is not None else {}))
                self.soaked()
                return
            if self.t >= deadline:
                if not self._soak_timeout("soak"):
                    return
                self.soaked()
                return
            self._check_requests()
            self._monitor(s.poll_s)

    def _wait_chamber(self, target: float, tolerance: float, max_wait: float) -> bool:
        """Poll the chamber until it is within tolerance of target; False on timeout."""
        t_end = self.t + max_wait
        while True:
            pv = self._read_chamber()
            self._interlocks(chamber_c=pv)
            self._saw(pv)
            self._report()  # the chamber on its way, poll by poll
            if abs(pv - target) <= tolerance:
                return True
            if self.t >= t_end:
                return False
            self._check_requests()
            self._monitor(self.p.soak.poll_s)

    def _monitor(self, seconds: float) -> None:
        """Let time pass while ramping/soaking; keep 1 s means of the IMU as a monitor block."""
        if not self.p.monitor.enabled or self.mounted_orientation is None:
            self._wait(seconds)
            return
        window = self.monitor.begin()
        self._wait(seconds)
        block = self.monitor.end(window, seconds, timeout_s=self._grace(seconds), run=self.run_no,
                                 orientation=self.mounted_orientation)
        if block is not None:
            self.store.save_monitor(self.cid, block)
            self._saw(float(block.chamber[-1, 1]), float(block.temp_c[-1]))

    def _do_rate_settling(self) -> None:
        step = self.step
        table = self.lab.table
        table.jog(step.rate_dps)
        t_end = self.t + TABLE_SETTLE_S
        while True:
            st = table.status()
            if st.fault:
                raise InstrumentError(table.name, table.address, f"table reports fault {st.fault}", command="STA")
            if st.settled:
                break
            if self.t > t_end:
                raise InstrumentError(table.name, table.address,
                                      f"did not settle at {step.rate_dps} deg/s within {TABLE_SETTLE_S:.0f} s")
            self._wait(0.5)
        self._wait(self.p.settle_s)
        self.settled()

    def _do_recording(self) -> None:
        step = self.step
        lab = self.lab
        imu = lab.imu
        self.store.note_attempt(self.cid, step.index)
        chamber = [(self.t, lab.chamber.read_temperature())]
        table = [(self.t, lab.table.velocity())]
        start = imu.begin_record()
        t_first = self.t + 1.0 / imu.rate_hz
        remaining = self.p.record_s
        while remaining > 1e-9:
            dt = min(self.p.record_poll_s, remaining)
            self._wait(dt)
            remaining -= dt
            chamber.append((self.t, lab.chamber.read_temperature()))
            self._saw(chamber[-1][1])
            rate = lab.table.velocity()
            table.append((self.t, rate))
            self._interlocks(chamber_c=chamber[-1][1], rate_dps=rate)
            if abs(rate - step.rate_dps) > max(1e-3 * abs(step.rate_dps), 0.05):
                # The table left its rate (a drive fault): this record is not what the step asks for.
                raise InstrumentError(lab.table.name, lab.table.address, f"table at {rate:+.4f} deg/s while "
                                      f"recording at {step.rate_dps:+g} deg/s; the step will be recorded again")
        rec = imu.end_record(start, self.procedure.frames_per_record, timeout_s=self._grace(self.p.record_s))
        if rec.dropped > self.p.faults.max_dropped_frames:
            self._record_again(step, rec)
            return
        if len(rec):
            self._interlocks(imu_temp=float(rec.temp_c.max()))
            self._saw(imu_c=float(rec.temp_c[-1]))
        block = SampleBlock(kind="record", step_idx=step.index, run=self.run_no, orientation=step.orientation,
                            t0_s=t_first + (rec.counter[0] - (start + 1)) / imu.rate_hz if len(rec) else t_first,
                            rate_hz=imu.rate_hz, counter=rec.counter, accel_g=rec.accel_g, gyro_dps=rec.gyro_dps,
                            temp_c=rec.temp_c, chamber=np.array(chamber), table=np.array(table), lsb=rec.lsb)
        self.store.commit_record(
            self.cid, block, dropped=rec.dropped, corrupt=rec.corrupt, t_end=self.t,
            event_message=f"step {step.index} recorded: {step.orientation} {step.temperature_c} C {step.rate_dps:+g} "
                          f"deg/s, {len(rec)} samples", detail={"dropped": rec.dropped, "corrupt": rec.corrupt})
        self.stats.steps_recorded += 1
        self.stats.samples += len(rec)
        self._advance()

    def _record_again(self, step: Step, rec: ImuRecord) -> None:
        """Frames were lost: record the step again, or (lost every time) let the fault policy decide."""
        attempts = int(self.store.steps_frame(self.cid).set_index("idx").loc[step.index, "attempts"])
        if self.policy.on_record(rec.dropped, attempts) == "give_up":
            raise InstrumentError(self.lab.imu.name, self.lab.imu.address,
                                  f"step {step.index}: frames lost in {attempts} attempts ({rec.dropped} of "
                                  f"{rec.expected} in the last)")
        self.event("fault", f"step {step.index}: {rec.dropped} of {rec.expected} frames lost (allowed "
                            f"{self.p.faults.max_dropped_frames}); recording again",
                   dropped=rec.dropped, corrupt=rec.corrupt, attempt=attempts)
        self.stats.steps_rerecorded += 1
        self.record_again()

    def _advance(self) -> None:
        """After a committed record: pause point, then on to the next step."""
        prev = self.step
        self.k = self.store.next_step(self.cid)
        self._report()
        self._check_requests()
        if self.k is None:
            self.lab.table.stop()
            self.all_recorded()
            return
        nxt = self.step
        if nxt.orientation != self.mounted_orientation:
            self.next_orientation()
        elif self.p.ramp is not None and nxt.orientation_index == prev.orientation_index:
            # A ramp campaign (labrunner.ramp_plan): the setpoint moves on with the step, no soak.
            self.lab.chamber.set_setpoint(nxt.temperature_c)
            self.next_rate()
        elif nxt.temperature_c != prev.temperature_c or nxt.orientation_index != prev.orientation_index:
            self.lab.table.stop()
            self.next_temperature()
        else:
            self.next_rate()

    def _do_fitting(self) -> None:
        lab = self.lab
        try:
            lab.table.stop()
            lab.chamber.set_setpoint(self.p.remount_c)
            self.lab_safe = True
        except InstrumentError as exc:
            self.event("warning", f"could not park the lab before fitting: {exc}")
        if self.p.fit.run:
            from labrunner.campaign_fit import fit_and_store

            try:
                self.fit_summary = fit_and_store(self.store, self.cid, self.p.fit, self.fit_out_dir)
                self.fit_ok = True
                self.event("info", "fit stored", out_dir=str(self.fit_out_dir) if self.fit_out_dir else None)
            except StoreError:
                raise  # not the fit's failure: the store's, which ends the run (the fit is made again on resume)
            except Exception as exc:  # the data are safe; a fit can be run again with `labrunner fit`
                log.warning("fit failed: %s", exc, exc_info=log.isEnabledFor(logging.DEBUG))
                self.event("warning", f"fit failed: {type(exc).__name__}: {exc}")
                self.fit_summary = f"fit failed: {exc} (run `labrunner fit` on the database to retry)"
        self.fitted()

    def _do_safe_stop(self) -> None:
        """Table stopped, chamber to the remount temperature; keep trying for a while, the lab must be safe."""
        result = safe_stop(self.lab.table, self.lab.chamber, self.p.remount_c, self.clock,
                           on_retry=lambda problems: self.event(
                               "fault", "safe state not reached yet, trying again: " + "; ".join(problems)))
        if not result.reached:
            self.event("fault", "safe state NOT reached: " + "; ".join(result.problems))
            self.last_error = "; ".join(result.problems)
            self.fail()
            return
        self.lab_safe = True
        self.event("info", f"lab in safe state: table stopped, chamber to {self.p.remount_c} C")
        if self.store_failure is not None:
            self.fail()  # safe, but the campaign cannot go on until the store can be written again
        else:
            self.stopped_safely()

    def on_exit_soaking(self, *_: Any) -> None:
        self._soak_window = None  # the next soak's entry must not show this one's progress

    def on_enter_safe_stop(self, *_: Any) -> None:
        # From here until the lab is safe nothing waits on the store: it may be what failed.
        self.journal.hold()

    def on_enter_paused(self, *_: Any) -> None:
        try:
            self.lab.table.stop()
        except Exception as exc:
            self.event("warning", f"could not stop the table on pause: {exc}")
