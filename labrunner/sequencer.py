"""The campaign sequencer: a `transitions` state machine that drives the lab through a procedure.

States: idle -> preflight -> mounting -> ramping -> soaking -> rate_settling ->
recording -> (rate_settling | ramping | mounting | fitting) ... -> done, plus paused,
safe_stop -> aborted, and failed. Each state has a handler that does that state's
work through the instrument interfaces (`drivers.protocols`) and fires the next
transition; every transition is an event row with its time.

Resuming is running the same machine again: it starts at idle and fires real
transitions (preflight, mounting for the first step not yet recorded, ...), so
every callback runs and nothing is entered by assignment.

Pause requests (first Ctrl-C, `labrunner` control table) take effect at the next
safe point: between polls while ramping or soaking, after a record step is
committed. Abort requests (second Ctrl-C, `labrunner abort`) bring the lab to its
safe state: table stopped, chamber to the remount (ambient) temperature.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from transitions import Machine

from labrunner.drivers.errors import InstrumentError, LimitError
from labrunner.drivers.protocols import ImuRecord
from labrunner.drivers.protocols import Instruments as Lab
from labrunner.procedure import Procedure, Step
from labrunner.runner.safe_stop import safe_stop
from labrunner.store import SampleBlock, Store

STATES = ["idle", "preflight", "mounting", "ramping", "soaking", "rate_settling", "recording", "fitting", "done",
          "paused", "safe_stop", "aborted", "failed"]
ACTIVE = ["preflight", "mounting", "ramping", "soaking", "rate_settling", "recording", "fitting"]
TERMINAL = {"done", "paused", "aborted", "failed"}
TRANSITIONS = [
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
    {"trigger": "abort", "source": ACTIVE + ["paused", "idle"], "dest": "safe_stop"},
    {"trigger": "stopped_safely", "source": "safe_stop", "dest": "aborted"},
    {"trigger": "fail", "source": ACTIVE + ["safe_stop", "idle"], "dest": "failed"},
]

Progress = Callable[["CampaignRunner"], None]


class _Stop(Exception):
    """Leaves a state handler because a pause or abort took over."""


@dataclass
class Control:
    """Requests reaching the runner: from signal handlers (same process) or the store (another one)."""

    pause: bool = False
    abort: bool = False
    reason: str = ""


@dataclass
class RunStats:
    steps_recorded: int = 0
    steps_rerecorded: int = 0
    faults: int = 0
    recoveries: int = 0
    samples: int = 0
    started_wall: float = field(default_factory=time.time)


class CampaignRunner:
    """Runs (or resumes) one campaign of a store on a lab."""

    def __init__(self, procedure: Procedure, lab: Lab, store: Store, campaign_id: int, *,
                 progress: Progress | None = None, fit_out_dir: Any = None,
                 crash_hook: Callable[[str], None] | None = None, auto_resume_s: float | None = None,
                 max_auto_resumes: int = 200) -> None:
        self.procedure = procedure
        self.p = procedure.model
        self.lab = lab
        self.store = store
        self.cid = campaign_id
        self.plan: list[Step] = procedure.steps()
        self.progress = progress
        self.fit_out_dir = fit_out_dir
        self.crash_hook = crash_hook  # tests: called at named points to simulate a kill there
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
        self._last_heartbeat = 0.0
        self._last_request_check = 0.0
        # Dry runs with injected faults: after a pause caused by a fault, resume after this much
        # clock time, as the operator would, through real transitions (paused -> preflight).
        self.auto_resume_s = auto_resume_s
        self.max_auto_resumes = max_auto_resumes
        self.auto_resumes = 0
        self._paused_by_fault = False
        self._retrying: dict[str, str] = {}  # instrument -> last retried error, until it answers again
        self.fault_injector: Any = None
        for inst in (lab.chamber, lab.table):
            if hasattr(inst, "on_retry"):
                inst.on_retry = self._on_retry
        if hasattr(lab.imu, "on_event"):
            lab.imu.on_event = self._on_imu_event
        self.machine = Machine(model=self, states=STATES, transitions=TRANSITIONS, initial="idle",
                               auto_transitions=False, after_state_change="_log_transition", send_event=True)

    # --- time, events, requests ------------------------------------------------------------

    @property
    def t(self) -> float:
        """Campaign time, s."""
        return self.lab.clock.now() - self.t_zero

    def _log_transition(self, event_data: Any = None) -> None:
        src = event_data.transition.source if event_data is not None else "?"
        self.store.event(self.cid, self.t, "transition", f"{src} -> {self.state}", state=self.state, step_idx=self.k)
        self._report()

    def event(self, kind: str, message: str, **detail: Any) -> None:
        self.store.event(self.cid, self.t, kind, message, state=self.state, step_idx=self.k, detail=detail or None)

    def _report(self) -> None:
        if self.progress:
            self.progress(self)

    def request_pause(self, reason: str = "pause requested") -> None:
        self.control.pause = True
        self.control.reason = reason

    def request_abort(self, reason: str = "abort requested") -> None:
        self.control.abort = True
        self.control.reason = reason

    def _on_retry(self, attempt: int, exc: InstrumentError) -> None:
        self.stats.faults += 1
        self._retrying[exc.instrument] = str(exc)
        self.event("fault", f"retry {attempt}: {exc}", instrument=exc.instrument)

    def _on_imu_event(self, kind: str, message: str) -> None:
        # Called from the IMU reader thread; the store is safe to use from there.
        if kind == "imu_link_lost":
            self.stats.faults += 1
            self.event("fault", message)
        else:
            self.stats.recoveries += 1
            self.event("recovery", message)

    def _note_recoveries(self) -> None:
        for instrument in list(self._retrying):
            self._retrying.pop(instrument)
            self.stats.recoveries += 1
            self.event("recovery", f"{instrument} answers again")

    def _check_requests(self, *, allow_pause: bool = True) -> None:
        """At a safe point: act on pause/abort requests (from signals, or from the store)."""
        if self._retrying:
            self._note_recoveries()
        now = time.monotonic()
        if now - self._last_request_check > 0.5:
            self._last_request_check = now
            req = self.store.pending_request(self.cid)
            if req == "abort":
                self.request_abort("abort requested by labrunner abort")
            elif req == "pause":
                self.request_pause("pause requested by labrunner")
            if now - self._last_heartbeat > 2.0:
                self._last_heartbeat = now
                self.store.heartbeat(self.cid, self.lab.clock.now())
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
        clock = self.lab.clock
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

    # --- the loop ------------------------------------------------------------------------------

    def run(self) -> str:
        """Run until done, paused, aborted or failed; returns the final state."""
        self.store.set_status(self.cid, "running", clock_last=self.lab.clock.now(), pid=os.getpid())
        self.event("info", f"campaign {'resumed' if self.k not in (None, 0) else 'started'} at step {self.k}",
                   mode=self.store.campaign(self.cid).mode)
        self.start()
        while True:
            if self.state in TERMINAL:
                if self.state == "paused" and self.control.abort:
                    self.abort()  # a second Ctrl-C (or labrunner abort) right after the pause took effect
                    continue
                if (self.state == "paused" and self._paused_by_fault and self.auto_resume_s is not None
                        and self.auto_resumes < self.max_auto_resumes):
                    self.lab.clock.sleep(self.auto_resume_s)
                    self.auto_resumes += 1
                    self._paused_by_fault = False
                    self.event("recovery", f"resuming after a fault pause (auto-resume {self.auto_resumes})")
                    self.resume()
                    continue
                break
            handler = getattr(self, f"_do_{self.state}")
            try:
                handler()
            except _Stop:
                continue
            except LimitError as exc:
                self._fault(exc, hard=True)
            except InstrumentError as exc:
                self._fault(exc)
            except Exception as exc:  # a bug or an unforeseen failure: leave the lab safe, keep the data
                self.last_error = f"{type(exc).__name__}: {exc}"
                self.event("fault", f"unexpected error in {self.state}: {self.last_error}")
                if self.state in ACTIVE:
                    self.abort()
                else:
                    self.fail()
        final = {"done": "done", "paused": "paused", "aborted": "aborted", "failed": "failed"}[self.state]
        self.store.set_status(self.cid, final, clock_last=self.lab.clock.now(), pid=None)
        self.store.request(self.cid, None)
        self._report()
        return final

    def _fault(self, exc: InstrumentError, hard: bool = False) -> None:
        """An instrument failed after its bounded retries: apply the procedure's fault policy."""
        self.stats.faults += 1
        self.last_error = str(exc)
        self.event("fault", str(exc), instrument=exc.instrument, address=exc.address, state=self.state)
        if self.state == "safe_stop":
            self.fail()
        elif hard or self.p.faults.policy == "abort":
            self.abort()
        else:
            self._paused_by_fault = True
            self.pause()

    # --- state handlers --------------------------------------------------------------------------

    def _do_preflight(self) -> None:
        lab = self.lab
        for inst in (lab.chamber, lab.table, lab.imu):
            inst.connect()
        ident = lab.chamber.identity()
        lo, hi = lab.chamber.setpoint_range()
        temps = self.p.temperatures.values() + [self.p.remount_c]
        outside = [t for t in temps if not lo <= t <= hi]
        if outside:
            raise LimitError(lab.chamber.name, lab.chamber.address, f"procedure temperature {outside[0]} C is outside "
                             f"the controller's setpoint range {lo}..{hi} C")
        self.event("info", f"chamber {ident.vendor} {ident.model} answers; setpoint range {lo}..{hi} C",
                   identity=ident.__dict__)
        tid = lab.table.identity()
        limits = getattr(lab.table, "limits", None)
        if limits is not None:
            max_rate, accel = limits()
            fastest = max(abs(r) for r in self.p.rates.values())
            if fastest > max_rate:
                raise LimitError(lab.table.name, lab.table.address, f"procedure rate {fastest} deg/s exceeds the "
                                 f"table's maximum {max_rate} deg/s")
            self.event("info", f"rate table {tid.vendor} {tid.model} answers; max {max_rate} deg/s, {accel} deg/s^2",
                       identity=tid.__dict__)
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
        self._interlocks(imu_temp=sample.temp_c)
        self._check_requests()
        if self.k is None:
            self.all_recorded()
        elif self.mounted_orientation == self.plan[self.k].orientation:
            self.resume_mounted()  # resumed in the same session: the IMU is still mounted and powered
        else:
            self.preflight_ok()

    def _do_mounting(self) -> None:
        step = self.plan[self.k]  # type: ignore[index]
        lab = self.lab
        lab.table.stop()
        # The operator opens the chamber: bring it near room temperature first.
        lab.chamber.set_setpoint(self.p.remount_c)
        if not self._wait_chamber(self.p.remount_c, max(2.0, self.p.soak.tolerance_c), self.p.soak.max_wait_s,
                                  "remount") and not self._soak_timeout("remount"):
            return
        prompt = self.procedure.prompt_for(step.orientation)
        self.event("operator", f"remount: {prompt}", orientation=step.orientation)
        self._report()
        lab.operator.remount(step.orientation, prompt)
        self.run_no += 1
        self.mounted_orientation = step.orientation
        lab.imu.restart_stream()
        self.event("operator", f"IMU mounted {step.orientation}, powered on (run {self.run_no})",
                   orientation=step.orientation, run=self.run_no)
        self.mounted()

    def _do_ramping(self) -> None:
        step = self.plan[self.k]  # type: ignore[index]
        self.lab.chamber.set_setpoint(step.temperature_c)
        self.event("info", f"setpoint {step.temperature_c} C", setpoint_c=step.temperature_c)
        self._soak_started = self.t
        ok = self._wait_chamber(step.temperature_c, self.p.soak.tolerance_c, self.p.soak.max_wait_s, "ramp")
        if not ok and not self._soak_timeout("ramp"):
            return
        self.at_setpoint()

    def _do_soaking(self) -> None:
        step = self.plan[self.k]  # type: ignore[index]
        s = self.p.soak
        window: list[tuple[float, float, float]] = []  # (t, chamber, imu)
        deadline = getattr(self, "_soak_started", self.t) + s.max_wait_s
        while True:
            pv = self.lab.chamber.read_temperature()
            sample = self.lab.imu.latest()
            imu_t = sample.temp_c if sample is not None else float("nan")
            self._interlocks(chamber_c=pv, imu_temp=imu_t)
            window.append((self.t, pv, imu_t))
            if self._stable(window, step.temperature_c):
                self.event("info", f"soaked at {step.temperature_c} C: chamber {pv:.2f} C, IMU {imu_t:.2f} C",
                           chamber_c=pv, imu_temp_c=imu_t)
                self.soaked()
                return
            if self.t >= deadline:
                if not self._soak_timeout("soak"):
                    return
                self.soaked()
                return
            self._check_requests()
            self._monitor(s.poll_s)

    def _stable(self, history: list[tuple[float, float, float]], setpoint: float) -> bool:
        """Stable when the readings of the last stable_window_s (and the history covers that long) hold."""
        s = self.p.soak
        if not history or history[-1][0] - history[0][0] < s.stable_window_s - 1e-6:
            return False
        start = history[-1][0] - s.stable_window_s - 1e-6
        window = [w for w in history if w[0] >= start]
        chamber = np.array([w[1] for w in window])
        if np.any(np.abs(chamber - setpoint) > s.tolerance_c):
            return False
        if s.sensor == "imu":
            imu = np.array([w[2] for w in window])
            return bool(np.all(np.isfinite(imu)) and imu.max() - imu.min() <= s.tolerance_c)
        return True

    def _soak_timeout(self, what: str) -> bool:
        """The chamber did not stabilise in time: apply soak.on_timeout. True means carry on."""
        policy = self.p.soak.on_timeout
        step = self.plan[self.k]  # type: ignore[index]
        target = self.p.remount_c if what == "remount" else step.temperature_c
        msg = (f"{what} at {target} C did not stabilise within soak.max_wait_s "
               f"({self.p.soak.max_wait_s:.0f} s); on_timeout: {policy}")
        self.event("warning" if policy == "continue" else "fault", msg)
        if policy == "continue":
            return True
        self.last_error = msg
        if policy == "pause":
            self._paused_by_fault = True
            self.pause()
        else:
            self.abort()
        return False

    def _wait_chamber(self, target: float, tolerance: float, max_wait: float, what: str) -> bool:
        """Poll the chamber until it is within tolerance of target; False on timeout."""
        t_end = self.t + max_wait
        while True:
            pv = self.lab.chamber.read_temperature()
            self._interlocks(chamber_c=pv)
            if abs(pv - target) <= tolerance:
                return True
            if self.t >= t_end:
                return False
            self._check_requests()
            self._monitor(self.p.soak.poll_s)

    def _monitor(self, seconds: float) -> None:
        """Let time pass while ramping/soaking; keep 1 s means of the IMU as a monitor block."""
        imu = self.lab.imu
        if not self.p.monitor.enabled or self.mounted_orientation is None:
            self._wait(seconds)
            return
        start = imu.begin_record()
        t0 = self.t
        chamber = [(t0, self.lab.chamber.read_temperature())]
        self._wait(seconds)
        n = int(round(seconds * imu.rate_hz))
        rec = imu.end_record(start, n, timeout_s=self._grace(seconds))
        chamber.append((self.t, self.lab.chamber.read_temperature()))
        if len(rec) == 0:
            return
        avg = max(1, int(round(self.p.monitor.average_s * imu.rate_hz)))
        offs = rec.counter - (start + 1)
        bins = offs // avg
        uniq, inv, counts = np.unique(bins, return_inverse=True, return_counts=True)

        def means(a: np.ndarray) -> np.ndarray:
            out = np.zeros((uniq.size,) + a.shape[1:])
            np.add.at(out, inv, a)
            return out / counts.reshape((-1,) + (1,) * (a.ndim - 1))

        t_rows = means((t0 + (offs + 1) / imu.rate_hz).astype(float))
        block = SampleBlock(kind="monitor", step_idx=None, run=self.run_no, orientation=self.mounted_orientation,
                            t0_s=float(t_rows[0]), rate_hz=1.0 / self.p.monitor.average_s,
                            counter=np.rint((t_rows - t_rows[0]) / self.p.monitor.average_s).astype(np.int64),
                            accel_g=means(rec.accel_g), gyro_dps=means(rec.gyro_dps), temp_c=means(rec.temp_c),
                            chamber=np.array(chamber), table=np.array([(t0, 0.0)]))
        self.store.save_monitor(self.cid, block)

    def _do_rate_settling(self) -> None:
        step = self.plan[self.k]  # type: ignore[index]
        table = self.lab.table
        table.jog(step.rate_dps)
        t_end = self.t + 120.0
        while True:
            st = table.status()
            if st.fault:
                raise InstrumentError(table.name, table.address, f"table reports fault {st.fault}", command="STA")
            if st.settled:
                break
            if self.t > t_end:
                raise InstrumentError(table.name, table.address, f"did not settle at {step.rate_dps} deg/s within 120 s")
            self._wait(0.5)
        self._wait(self.p.settle_s)
        self.settled()

    def _grace(self, seconds: float) -> float:
        clock = self.lab.clock
        return 0.5 if clock.virtual else clock.wall_seconds(seconds) + 5.0

    def _do_recording(self) -> None:
        step = self.plan[self.k]  # type: ignore[index]
        lab = self.lab
        imu = lab.imu
        n = self.procedure.frames_per_record
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
            rate = lab.table.velocity()
            table.append((self.t, rate))
            self._interlocks(chamber_c=chamber[-1][1], rate_dps=rate)
            if abs(rate - step.rate_dps) > max(1e-3 * abs(step.rate_dps), 0.05):
                # The table left its rate (a drive fault): this record is not what the step asks for.
                raise InstrumentError(lab.table.name, lab.table.address, f"table at {rate:+.4f} deg/s while "
                                      f"recording at {step.rate_dps:+g} deg/s; the step will be recorded again")
        rec = imu.end_record(start, n, timeout_s=self._grace(self.p.record_s))
        if self.crash_hook:
            self.crash_hook("record")
        if rec.dropped > self.p.faults.max_dropped_frames:
            self._record_again(step, rec)
            return
        if len(rec):
            self._interlocks(imu_temp=float(rec.temp_c.max()))
        block = SampleBlock(kind="record", step_idx=step.index, run=self.run_no, orientation=step.orientation,
                            t0_s=t_first + (rec.counter[0] - (start + 1)) / imu.rate_hz if len(rec) else t_first,
                            rate_hz=imu.rate_hz, counter=rec.counter, accel_g=rec.accel_g, gyro_dps=rec.gyro_dps,
                            temp_c=rec.temp_c, chamber=np.array(chamber), table=np.array(table), lsb=rec.lsb)
        hook = (lambda: self.crash_hook("commit")) if self.crash_hook else None
        self.store.commit_record(
            self.cid, block, dropped=rec.dropped, corrupt=rec.corrupt, t_end=self.t,
            event_message=f"step {step.index} recorded: {step.orientation} {step.temperature_c} C {step.rate_dps:+g} "
                          f"deg/s, {len(rec)} samples", detail={"dropped": rec.dropped, "corrupt": rec.corrupt},
            _crash_hook=hook)
        self.stats.steps_recorded += 1
        self.stats.samples += len(rec)
        self._advance()

    def _record_again(self, step: Step, rec: ImuRecord) -> None:
        attempts = int(self.store.steps_frame(self.cid).set_index("idx").loc[step.index, "attempts"])
        msg = (f"step {step.index}: {rec.dropped} of {rec.expected} frames lost (allowed "
               f"{self.p.faults.max_dropped_frames}); recording again")
        if attempts > self.p.faults.max_rerecords:
            err = InstrumentError(self.lab.imu.name, self.lab.imu.address,
                                  f"step {step.index}: frames lost in {attempts} attempts ({rec.dropped} of "
                                  f"{rec.expected} in the last)")
            raise err
        self.event("fault", msg, dropped=rec.dropped, corrupt=rec.corrupt, attempt=attempts)
        self.stats.steps_rerecorded += 1
        self.record_again()

    def _advance(self) -> None:
        """After a committed record: pause point, then on to the next step."""
        prev = self.plan[self.k]  # type: ignore[index]
        self.k = self.store.next_step(self.cid)
        self._report()
        self._check_requests()
        if self.k is None:
            self.lab.table.stop()
            self.all_recorded()
            return
        nxt = self.plan[self.k]
        if nxt.orientation != self.mounted_orientation:
            self.next_orientation()
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
        except InstrumentError as exc:
            self.event("warning", f"could not park the lab before fitting: {exc}")
        if self.p.fit.run:
            from labrunner.campaign_fit import fit_and_store

            try:
                self.fit_summary = fit_and_store(self.store, self.cid, self.p.fit, self.fit_out_dir)
                self.fit_ok = True
                self.event("info", "fit stored", out_dir=str(self.fit_out_dir) if self.fit_out_dir else None)
            except Exception as exc:  # the data are safe; a fit can be run again with `labrunner fit`
                self.event("warning", f"fit failed: {type(exc).__name__}: {exc}")
                self.fit_summary = f"fit failed: {exc} (run `labrunner fit` on the database to retry)"
        self.fitted()

    def _do_safe_stop(self) -> None:
        """Table stopped, chamber to the remount temperature; keep trying for a while, the lab must be safe."""
        result = safe_stop(self.lab.table, self.lab.chamber, self.p.remount_c, self.lab.clock,
                           on_retry=lambda problems: self.event(
                               "fault", "safe state not reached yet, trying again: " + "; ".join(problems)))
        if not result.reached:
            self.event("fault", "safe state NOT reached: " + "; ".join(result.problems))
            self.last_error = "; ".join(result.problems)
            self.fail()
            return
        self.event("info", f"lab in safe state: table stopped, chamber to {self.p.remount_c} C")
        self.stopped_safely()

    def on_enter_paused(self, *_: Any) -> None:
        try:
            self.lab.table.stop()
        except Exception as exc:
            self.event("warning", f"could not stop the table on pause: {exc}")

    # --- interlocks ----------------------------------------------------------------------------------

    def _interlocks(self, *, chamber_c: float | None = None, rate_dps: float | None = None,
                    imu_temp: float | None = None) -> None:
        s = self.p.safety
        trip = None
        if chamber_c is not None and not (s.chamber_min_c <= chamber_c <= s.chamber_max_c):
            trip = f"chamber at {chamber_c:.1f} C, outside the safety limits {s.chamber_min_c}..{s.chamber_max_c} C"
        elif rate_dps is not None and abs(rate_dps) > s.max_rate_dps * 1.01:
            trip = f"table at {rate_dps:.2f} deg/s, above the limit {s.max_rate_dps} deg/s"
        elif imu_temp is not None and math.isfinite(imu_temp) and imu_temp > s.imu_max_temp_c:
            trip = f"IMU at {imu_temp:.1f} C, above its rating {s.imu_max_temp_c} C"
        if trip:
            self.last_error = f"interlock: {trip}"
            self.event("interlock", trip)
            self.abort()
            raise _Stop

    # --- progress ------------------------------------------------------------------------------------

    def done_steps(self) -> int:
        return len(self.plan) if self.k is None else self.k

    def current_step(self) -> Step | None:
        return None if self.k is None else self.plan[self.k]

