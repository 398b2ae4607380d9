"""Composition of a campaign run: lab, store and runner put together, run, and taken apart.

`start_run` and `start_resume` build a `Session` (the store opened, the campaign row written or
found, the lab connected, the runner constructed); `Session.execute` runs it and returns a
`RunResult` (`labrunner.campaign_abort` ends a campaign from outside). `labrunner.api` and the
command line both go through here, so a campaign is composed in one place.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labrunner.errors import UserError
from labrunner.output_paths import check_output
from labrunner.sim_config import has_fault_plan, sim_config_dict
from labrunner.store_address import StoreAddress, store_address

if TYPE_CHECKING:
    from labrunner.lab import Lab, LabConfig
    from labrunner.procedure import Procedure, Step
    from labrunner.runner.pace import PaceEstimator, Schedule
    from labrunner.runner.soak import SoakProgress
    from labrunner.sequencer import CampaignRunner
    from labrunner.store import Store

log = logging.getLogger(__name__)

EXIT_CODES = {"done": 0, "paused": 3, "aborted": 4, "failed": 1}
AUTO_RESUME_S = 900.0  # a rehearsed operator resumes a fault pause after 15 minutes (lab time)


@dataclass(frozen=True)
class Progress:
    """Where a running campaign is, as passed to a `progress` callback after every transition and record,
    and after every poll of the chamber while ramping and soaking."""

    steps_done: int  # recorded, this session's and before it (a resumed campaign starts where it was)
    steps_total: int
    state: str
    step: Step | None  # the step being worked on (None when all are recorded)
    lab_time_s: float
    chamber_c: float | None = None  # the latest chamber reading (None before the first)
    imu_temp_c: float | None = None  # the latest IMU temperature
    setpoint_c: float | None = None  # what the chamber is heading for (the remount temperature while mounting)
    soak: SoakProgress | None = None  # while soaking: spread and offset over the window, time stable
    lab_left_s: float | None = None  # lab time to the last step: the plan's, corrected by the pace so far
    eta_s: float | None = None  # wall seconds to the last step at the measured pace (None: not known yet)


@dataclass(frozen=True)
class RunResult:
    """How a run or resume ended."""

    campaign_id: int
    db: StoreAddress  # str() shows a URL's password masked
    state: str  # done, paused, aborted, failed
    exit_code: int  # the CLI's: 0 done, 3 paused, 4 aborted, 1 failed
    steps_done: int
    steps_total: int
    steps_recorded: int = 0  # in this session
    samples: int = 0  # in this session
    steps_rerecorded: int = 0  # steps recorded more than once, campaign-wide (as `status` counts them)
    steps_rerecorded_session: int = 0  # of those, the ones recorded again in this session
    faults: int = 0
    recoveries: int = 0
    lab_time_s: float = 0.0
    wall_s: float = 0.0
    reason: str | None = None  # why it did not finish (the last error), if it did not
    faults_injected: int | None = None  # dry runs with a fault plan
    faults_by_kind: dict[str, int] = field(default_factory=dict)
    auto_resumes: int = 0
    fit_summary: str | None = None  # the end-of-run fit's summary (markdown), or why it failed
    fit_ok: bool = False
    fit_out: Path | None = None  # where the fitted models were written
    already_done: bool = False  # resume of a complete campaign: nothing was run

    @property
    def ok(self) -> bool:
        return self.state == "done"

    @property
    def resumable(self) -> bool:
        return self.state in ("paused", "aborted", "failed")


ProgressCallback = Callable[[Progress], None]


class Session:
    """One campaign ready to run: its store, lab and runner. Close it (or use `with`)."""

    def __init__(self, store: Store, campaign_id: int, procedure: Procedure, *, mode: str, db: StoreAddress,
                 lab: Lab | None = None, runner: CampaignRunner | None = None, status_before: str = "running",
                 next_step: int | None = 0, lease_note: str | None = None) -> None:
        self.store = store
        self.campaign_id = campaign_id
        self.procedure = procedure
        self.mode = mode  # "sim" or "lab"
        self.db = db
        self.lab = lab
        self.runner = runner
        self.status_before = status_before
        self.next_step = next_step
        self.lease_note = lease_note  # how the lease was taken from a previous holder, if it was

    @property
    def already_done(self) -> bool:
        return self.runner is None

    @property
    def steps_total(self) -> int:
        return len(self.procedure.steps())

    @property
    def steps_done(self) -> int:
        """Steps recorded before this session runs (where a progress bar starts)."""
        return self.runner.done_steps() if self.runner is not None else self.steps_total

    @property
    def planned_samples(self) -> int:
        return self.steps_total * self.procedure.frames_per_record

    @property
    def estimated_lab_s(self) -> float:
        return self.procedure.estimated_duration_s()

    def request_pause(self, reason: str = "pause requested") -> None:
        if self.runner is not None:
            self.runner.request_pause(reason)

    def request_abort(self, reason: str = "abort requested") -> None:
        if self.runner is not None:
            self.runner.request_abort(reason)

    def execute(self, progress: ProgressCallback | None = None, *, handle_signals: bool = False) -> RunResult:
        """Run to done, paused, aborted or failed. With `handle_signals`, Ctrl-C pauses at the next
        safe point, a second Ctrl-C (or SIGTERM) aborts to the safe state (main thread only)."""
        runner = self.runner
        if runner is None:
            total = self.steps_total
            return RunResult(campaign_id=self.campaign_id, db=self.db, state="done", exit_code=0, steps_done=total,
                             steps_total=total, already_done=True)
        if progress is not None:
            view = LiveView(runner)
            runner.progress = lambda r: progress(view(r))
        started = time.time()
        attempts_before = _attempts(self.store, self.campaign_id)
        try:
            with _signals(self, handle_signals):
                final = runner.run()
        finally:
            self._close_lab()
        log.info("campaign %d: %s after %.1f s wall", self.campaign_id, final, time.time() - started)
        return _result(runner, self.db, final, time.time() - runner.stats.started_wall, attempts_before)

    def _close_lab(self) -> None:
        if self.lab is not None:
            self.lab.close()
            self.lab = None

    def close(self) -> None:
        self._close_lab()
        try:
            self.store.release_lease(self.campaign_id)
        except Exception as exc:  # the store failed: the lease goes stale, the same-host rule frees it
            log.warning("campaign %d: lease not released: %s", self.campaign_id, exc)
        self.store.close()

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


_HEADING = ("ramping", "soaking", "rate_settling", "recording")  # the chamber's setpoint is the step's


class LiveView:
    """Makes the `Progress` values of one session from its runner: its latest readings, the soak's
    progress, and the ETA from the pace measured in this session (`labrunner.runner.pace`)."""

    def __init__(self, runner: CampaignRunner) -> None:
        from labrunner.runner.pace import PaceEstimator, Schedule

        self.schedule: Schedule = Schedule.of(runner.procedure.estimated_step_ends_s())
        clock = runner.clock
        # A real or scaled clock runs at a known rate; a virtual one's is what the session shows.
        known = None if clock.virtual else 1.0 / max(clock.wall_seconds(1.0), 1e-12)
        self.pace: PaceEstimator = PaceEstimator(self.schedule.total_s, lab_per_wall=known)
        self._step: int | None = -1  # the step the lab time since `_step_t` counts for
        self._step_t = 0.0

    def __call__(self, runner: CampaignRunner) -> Progress:
        t = runner.t
        if runner.k != self._step:
            self._step, self._step_t = runner.k, t
        eta = self.pace.update(time.monotonic(), t, self.schedule.done_s(runner.k, t - self._step_t))
        step = runner.current_step()
        state = str(runner.state)
        setpoint = runner.p.remount_c if state == "mounting" else (
            step.temperature_c if step is not None and state in _HEADING else None)
        return Progress(steps_done=runner.done_steps(), steps_total=len(runner.plan), state=state, step=step,
                        lab_time_s=t, chamber_c=runner.chamber_c, imu_temp_c=runner.imu_temp_c, setpoint_c=setpoint,
                        soak=runner.soak_progress(), lab_left_s=eta.lab_left_s, eta_s=eta.wall_left_s)


def _attempts(store: Store, campaign_id: int) -> dict[int, int]:
    """Recording attempts per step index, as stored."""
    stp = store.steps_frame(campaign_id)
    return {int(i): int(a) for i, a in zip(stp.idx, stp.attempts)}


def _rerecorded(store: Store, campaign_id: int, before: dict[int, int]) -> tuple[int, int]:
    """Steps recorded more than once, campaign-wide (what `status` shows) and in this session."""
    after = _attempts(store, campaign_id)
    total = sum(1 for a in after.values() if a > 1)
    session = sum(1 for i, a in after.items() if a > 1 and a > max(1, before.get(i, 0)))
    return total, session


def _result(runner: CampaignRunner, db: StoreAddress, final: str, wall_s: float,
            attempts_before: dict[int, int] | None = None) -> RunResult:
    s = runner.stats
    rerecorded, rerecorded_session = _rerecorded(runner.store, runner.cid, attempts_before or {})
    inj = getattr(runner, "fault_injector", None)
    return RunResult(
        campaign_id=runner.cid, db=db, state=final, exit_code=EXIT_CODES[final], steps_done=runner.done_steps(),
        steps_total=len(runner.plan), steps_recorded=s.steps_recorded, samples=s.samples,
        steps_rerecorded=rerecorded, steps_rerecorded_session=rerecorded_session, faults=s.faults,
        recoveries=s.recoveries, lab_time_s=runner.t,
        wall_s=wall_s, reason=runner.last_error if final != "done" else None,
        faults_injected=inj.injected if inj is not None else None,
        faults_by_kind=dict(inj.by_kind) if inj is not None else {}, auto_resumes=runner.auto_resumes,
        fit_summary=runner.fit_summary, fit_ok=runner.fit_ok,
        fit_out=Path(runner.fit_out_dir) if runner.fit_ok and runner.fit_out_dir else None)


@contextmanager
def _signals(session: Session, enabled: bool) -> Iterator[None]:
    """Ctrl-C: pause; Ctrl-C again: abort to the safe state; SIGTERM: abort. Restored afterwards."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return
    hits = {"n": 0}

    def on_sigint(_sig: int, _frame: Any) -> None:
        hits["n"] += 1
        if hits["n"] == 1:
            print("\nlabrunner: pausing at the next safe point (Ctrl-C again to abort to a safe state)",
                  file=sys.stderr, flush=True)
            session.request_pause("Ctrl-C: pause")
        else:
            print("\nlabrunner: aborting: bringing the lab to its safe state", file=sys.stderr, flush=True)
            session.request_abort("Ctrl-C twice: abort")

    previous = signal.signal(signal.SIGINT, on_sigint), signal.signal(
        signal.SIGTERM, lambda *_: session.request_abort("SIGTERM: abort"))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous[0])
        signal.signal(signal.SIGTERM, previous[1])


# --- composing a lab -------------------------------------------------------------------------------------


def _sim_lab(procedure: Procedure, sim_dict: dict[str, Any], start_t: float, orientation: str | None) -> Lab:
    from labrunner.lab import simulated_lab
    from labrunner.sims.world import SimLabConfig

    try:
        config = SimLabConfig.from_dict(sim_dict)
    except (ValueError, TypeError, OSError) as exc:
        raise UserError(f"sim configuration: {exc}") from None
    return simulated_lab(max_rate_dps=procedure.model.safety.max_rate_dps, sim_config=config, start_t=start_t,
                         orientation=orientation, remount_s=procedure.model.remount_s)


def _resumed_sim_lab(procedure: Procedure, store: Store, cid: int, sim_dict: dict[str, Any], clock_t0: float,
                     start_t: float, next_orientation: str | None) -> Lab:
    """A resumed dry run's simulated lab, started as the last session left it, as far as the store knows
    (`runner.last_state`): the IMU still mounted as the sequencer last mounted it and powered since then
    (same run), the chamber air at its last stored reading, heading for the last setpoint given (the
    remount temperature after a safe stop). A campaign never mounted starts as a new one does, in the
    next step's orientation. Whether the run then goes on in place is the sequencer's check, by gravity
    and the chamber, as on a real lab."""
    from labrunner.runner.last_state import left_state

    left = left_state(store, cid, procedure.model.remount_c)
    if left.mount is None:
        return _sim_lab(procedure, sim_dict, start_t, next_orientation)
    lab = _sim_lab(procedure, sim_dict, start_t, left.mount.orientation)
    assert lab.sim is not None
    air = left.chamber_c if left.chamber_c is not None else lab.sim.config.chamber.ambient_c
    setpoint = left.setpoint_c if left.setpoint_c is not None else air
    lab.sim.restore(orientation=left.mount.orientation, air_c=air, setpoint_c=setpoint,
                    powered_since=clock_t0 + left.mount.t_s, run=left.mount.run, imu_c=left.imu_temp_c)
    log.info("resumed dry run: IMU %s since %.0f s (run %d), chamber %.2f C heading for %.2f C",
             left.mount.orientation, left.mount.t_s, left.mount.run, air, setpoint)
    return lab


def _lab_config(lab: str | Path | LabConfig) -> LabConfig:
    from labrunner.lab import LabConfig, load_lab_config

    if isinstance(lab, LabConfig):
        return lab
    return load_lab_config(lab)[0]


def _runner(procedure: Procedure, lab: Lab, store: Store, cid: int, fit_out: Path, sim_dict: dict[str, Any] | None,
            auto_resume_s: float | None) -> CampaignRunner:
    from labrunner.sequencer import CampaignRunner

    runner = CampaignRunner(procedure, lab, store, cid, fit_out_dir=fit_out, auto_resume_s=auto_resume_s)
    if lab.sim is not None and has_fault_plan(sim_dict):
        # Static plant faults (faults.chamber) are applied by the simulated lab itself.
        from labrunner.fault_plan import FaultInjector

        FaultInjector.attach(runner, lab, sim_dict["faults"])  # type: ignore[index]
    return runner


def fit_dir(db: StoreAddress, given: str | Path | None, campaign_id: int) -> Path:
    """Where the end-of-run fit writes its models: given, or the campaign's own directory next to the
    database (<db>_fit/campaign-<id>/; for a server database <dbname>_fit/ in the current directory),
    so a second campaign in the store keeps the first one's models."""
    return Path(given) if given is not None else db.beside("_fit") / f"campaign-{campaign_id}"


def _check_fit_dir(procedure: Procedure, out: Path, db: StoreAddress, inputs: list[Any], force: bool) -> None:
    """Refuse, before anything runs, a fit directory that holds an input or (without `force`) files."""
    if procedure.model.fit.run:
        check_output(out, store=db, inputs=[i for i in inputs if isinstance(i, (str, Path))], force=force,
                     directory=True, option="the fit directory")


# --- run, resume ---------------------------------------------------------------------------------------------


def start_run(procedure: str | Path | Procedure, *, db: str | Path | StoreAddress, lab: str | Path | LabConfig = "sim",
              seed: int | None = None, faults: int = 0, sim_config: str | Path | dict[str, Any] | None = None,
              fit_out: str | Path | None = None, auto_resume: bool = True, force: bool = False) -> Session:
    """A new campaign of `procedure` in `db`, on the simulated lab (`lab="sim"`) or a real one. The
    end-of-run fit's directory must be empty or new unless `force`."""
    from labrunner.lab import lab_config_from_dict, real_lab
    from labrunner.procedure import Procedure, load_procedure
    from labrunner.run_validation import validate_run  # what `labrunner check` refuses, refused here too
    from labrunner.runner.lease import new_token
    from labrunner.store import Store

    db = store_address(db)
    if isinstance(procedure, Procedure):
        proc, proc_path = procedure, None
    else:
        proc, proc_path = load_procedure(procedure), str(Path(procedure).resolve())
    sim = isinstance(lab, str) and lab == "sim"
    sim_dict: dict[str, Any] | None = None
    if sim:
        sim_dict = sim_config_dict(sim_config)
        if seed is not None:
            sim_dict["seed"] = seed
        if faults:
            from labrunner.fault_plan import random_fault_plan

            sim_dict["faults"] = {"random": random_fault_plan(proc, faults, sim_dict.get("seed", 0))}
        validate_run(proc, sim=sim_dict, sim_source=sim_config if isinstance(sim_config, (str, Path)) else None)
        the_lab = _sim_lab(proc, sim_dict, 0.0, proc.steps()[0].orientation)
        lab_dict = the_lab.config.model_dump()
    else:
        if faults:
            raise UserError("--faults injects faults into the simulated lab: use it with --sim")
        config = _lab_config(lab)
        validate_run(proc, lab=config, lab_source=lab if isinstance(lab, (str, Path)) else None)
        lab_dict = config.model_dump()
        the_lab = real_lab(lab_config_from_dict(lab_dict), max_rate_dps=proc.model.safety.max_rate_dps)
    try:
        store = Store.create(db)
    except Exception:
        the_lab.close()
        raise
    try:
        # The id new_campaign will give (reserved: a PostgreSQL sequence is not the largest + 1): the
        # default fit directory is checked before the campaign exists, so a refusal adds nothing to the store.
        planned_id = store.reserve_campaign_id()
        _check_fit_dir(proc, fit_dir(db, fit_out, planned_id), db, [proc_path, sim_config, None if sim else lab],
                       force)
        cid = store.new_campaign(name=proc.name, procedure_text=proc.text, procedure_path=proc_path,
                                 procedure_sha256=proc.sha256, lab_config=lab_dict, mode="sim" if sim else "lab",
                                 sim_config=sim_dict, clock_t0=the_lab.clock.now(), plan=proc.steps(),
                                 lease_token=new_token(), campaign_id=planned_id)
        auto = AUTO_RESUME_S if (sim and has_fault_plan(sim_dict) and auto_resume) else None
        runner = _runner(proc, the_lab, store, cid, fit_dir(db, fit_out, cid), sim_dict, auto)
    except BaseException:
        the_lab.close()
        store.close()
        raise
    log.info("campaign %d '%s' in %s: %d steps (%s)", cid, proc.name, db, len(runner.plan), "sim" if sim else "lab")
    return Session(store, cid, proc, mode="sim" if sim else "lab", db=db, lab=the_lab, runner=runner)


def start_resume(db: str | Path | StoreAddress, *, campaign: int | None = None,
                 lab: str | Path | LabConfig | None = None, fit_out: str | Path | None = None, force: bool = False,
                 take_over: bool = False) -> Session:
    """Continue a paused, aborted, failed or killed campaign from its first missing step. A complete
    campaign gives a session with nothing to run (`already_done`).

    The campaign's lease is taken before any instrument is built or connected: another process
    holding it refuses the resume (`runner.lease.LeaseRefused`, naming it); a stale one (no heartbeat
    for `runner.lease.STALE_AFTER_S`) is taken only with `take_over`."""
    from labrunner.lab import lab_config_from_dict, real_lab
    from labrunner.procedure import parse_procedure
    from labrunner.runner.lease import acquire
    from labrunner.store import Store

    db = store_address(db)
    store = Store.open_existing(db)
    the_lab: Lab | None = None
    held: int | None = None  # the campaign whose lease this call took
    try:
        cid = store.resolve(campaign)
        info = store.campaign(cid)
        procedure = parse_procedure(info.procedure_text, f"{db} (campaign {cid} procedure)", stored=True)
        if info.status == "done":
            return Session(store, cid, procedure, mode=info.mode, db=db, status_before="done", next_step=None)
        decision = acquire(store, cid, take_over=take_over)
        held = cid
        lease_note = None
        if decision.previous is not None:
            lease_note = (f"lease of campaign {cid} taken over from {decision.previous}" if decision.reason ==
                          "taken over" else f"lease of campaign {cid} taken: its holder ({decision.previous}) "
                          "is gone from this host, so it counts as stale at once")
        info = store.campaign(cid)  # as the lease found it (another process may have ended it meanwhile)
        if info.status == "done":
            store.release_lease(cid)
            held = None
            return Session(store, cid, procedure, mode=info.mode, db=db, status_before="done", next_step=None)
        if fit_out is not None:  # the default directory is this campaign's own: its fit is written again
            _check_fit_dir(procedure, Path(fit_out), db, [lab], force)
        nxt = store.next_step(cid)
        orientation = procedure.steps()[nxt].orientation if nxt is not None else None
        if info.mode == "sim":
            # The simulated lab starts again a minute after the campaign's last stored moment: after a
            # kill the heartbeat's clock_last and the last event may both lag behind the monitor
            # stretches stored while soaking (a resumed session must not overlap them).
            last = max(info.clock_last, info.clock_t0 + store.last_moment(cid))
            the_lab = _resumed_sim_lab(procedure, store, cid, info.sim_config or {}, info.clock_t0, last + 60.0,
                                       orientation)
        else:
            config = _lab_config(lab) if lab is not None else lab_config_from_dict(info.lab_config,
                                                                                  "stored lab configuration")
            if lab is not None:  # a lab given anew is checked as `run` checks one
                from labrunner.run_validation import validate_run

                validate_run(procedure, lab=config, lab_source=lab if isinstance(lab, (str, Path)) else None)
            the_lab = real_lab(config, max_rate_dps=procedure.model.safety.max_rate_dps)
        faulty = info.mode == "sim" and has_fault_plan(info.sim_config)
        runner = _runner(procedure, the_lab, store, cid, fit_dir(db, fit_out, cid), info.sim_config,
                         AUTO_RESUME_S if faulty else None)
    except BaseException:
        if the_lab is not None:
            the_lab.close()
        try:
            if held is not None:
                store.release_lease(held)
        finally:
            store.close()
        raise
    log.info("resuming campaign %d (%s) at step %s", cid, info.status, nxt)
    return Session(store, cid, procedure, mode=info.mode, db=db, lab=the_lab, runner=runner,
                   status_before=info.status, next_step=nxt, lease_note=lease_note)
