"""The sequencer built in-process on fake instruments and a real store: what each path through the
state machine leaves in the store and does to the instruments."""

from __future__ import annotations

import re

import numpy as np
import pytest
from sqlalchemy import text

from labrunner.clock import VirtualClock
from labrunner.drivers.protocols import Chamber, Imu, Instruments, Operator, RateTable
from labrunner.procedure import parse_procedure
from labrunner.runner.safe_stop import SAFE_STOP_PERSIST_S, SAFE_STOP_RETRY_S
from labrunner.sequencer import CampaignRunner, NoCurrentStep
from labrunner.store import Store

from .fakes import FakeLab

PROC = """\
name: inproc
temperatures: {list_c: [15, 35], order: serpentine}
soak: {tolerance_c: 0.5, stable_window_s: 120, max_wait_s: 3600, on_timeout: continue, sensor: imu, poll_s: 30}
orientations: [x_up, z_down]
remount_c: 23
remount_s: 60
rates: {list_dps: [-50, 50]}
settle_s: 1
record_s: 4
record_poll_s: 2
safety: {chamber_min_c: -40, chamber_max_c: 40, max_rate_dps: 150, imu_max_temp_c: 85}
faults: {policy: pause, max_rerecords: 2}
fit: {run: false}
"""
N_STEPS = 8  # 2 orientations x 2 temperatures x 2 rates
FRAMES = 200  # 4 s at 50 Hz


class Campaign:
    """A procedure, a store in tmp_path and one campaign in it."""

    def __init__(self, tmp_path, proc_text: str = PROC) -> None:
        self.procedure = parse_procedure(proc_text, "inproc.yaml")
        self.store = Store.create(tmp_path / "c.db")
        self.cid = self.store.new_campaign(
            name=self.procedure.name, procedure_text=self.procedure.text, procedure_path=None,
            procedure_sha256=self.procedure.sha256, lab_config={}, mode="sim", sim_config={}, clock_t0=0.0,
            plan=self.procedure.steps())

    def runner(self, lab: FakeLab, **kwargs) -> CampaignRunner:
        return CampaignRunner(self.procedure, lab, self.store, self.cid, **kwargs)

    def events(self):
        return self.store.events_frame(self.cid)

    def messages(self) -> list[str]:
        return list(self.events().message)

    def steps(self):
        return self.store.steps_frame(self.cid).set_index("idx")

    def record_blocks_per_step(self) -> dict[int, int]:
        with self.store.engine.connect() as conn:
            rows = conn.execute(text("SELECT step_idx, COUNT(*) FROM sample_blocks WHERE kind='record' AND "
                                     "campaign_id=:c GROUP BY step_idx"), {"c": self.cid}).fetchall()
        return {int(i): int(n) for i, n in rows}


@pytest.fixture
def campaign(tmp_path):
    c = Campaign(tmp_path)
    yield c
    c.store.close()


def at_step(runner_ref: list[CampaignRunner], k: int, action) -> callable:
    """A progress callback that calls `action(runner)` once, when `k` steps are recorded."""
    fired = []

    def progress(runner: CampaignRunner) -> None:
        if not fired and runner.done_steps() == k:
            fired.append(runner.t)
            action(runner)

    progress.fired = fired  # type: ignore[attr-defined]
    return progress


def transitions(c: Campaign) -> list[str]:
    ev = c.events()
    return list(ev[ev.kind == "transition"].message)


def test_fakes_implement_the_instrument_protocols():
    lab = FakeLab()
    assert isinstance(lab.chamber, Chamber) and isinstance(lab.table, RateTable) and isinstance(lab.imu, Imu)
    assert callable(lab.operator.remount)
    instruments: Instruments = lab  # the bundle type the runner takes
    operator: Operator = lab.operator
    assert instruments.clock.virtual and operator is lab.operator


def test_a_campaign_runs_to_done_with_every_step_recorded_once(campaign):
    lab = FakeLab()
    runner = campaign.runner(lab)
    assert runner.run() == "done"
    assert campaign.store.campaign(campaign.cid).status == "done"
    steps = campaign.steps()
    assert (steps.status == "done").all() and (steps.attempts == 1).all() and (steps.n_samples == FRAMES).all()
    assert campaign.record_blocks_per_step() == {k: 1 for k in range(N_STEPS)}
    recorded = [m for m in campaign.messages() if " recorded: " in m]
    assert [int(m.split()[1]) for m in recorded] == list(range(N_STEPS))
    tr = transitions(campaign)
    assert tr[0] == "idle -> preflight" and tr[-2:] == ["recording -> fitting", "fitting -> done"]
    assert tr.count("rate_settling -> recording") == N_STEPS and "recording -> mounting" in tr
    # Each soak lasted its stable window (120 s) after the chamber reached the setpoint.
    ev = campaign.events()
    soak_start = ev[ev.message == "ramping -> soaking"].t_s.to_numpy()
    soaked = ev[ev.message.str.startswith("soaked at ")].t_s.to_numpy()
    assert len(soaked) == 4 and np.all(soaked - soak_start >= 120.0)
    # The instruments did what the procedure says: two remounts at the remount temperature, the
    # serpentine temperatures, each step's rate, and the lab parked at the end.
    assert [o for _, o, _ in lab.operator.remounts] == ["x_up", "z_down"]
    setpoints = [args[0] for _, args in lab.chamber.called("set_setpoint")]
    assert setpoints == [23.0, 15.0, 35.0, 23.0, 35.0, 15.0, 23.0]
    assert [args[0] for _, args in lab.table.called("jog")] == [s.rate_dps for s in runner.plan]
    assert lab.table.rate == 0.0 and lab.chamber.setpoint == 23.0
    # The samples are the fakes' frames: gravity along the mounted axis, the table's rate on gyro z.
    frame = campaign.store.samples_frame(campaign.cid)
    assert len(frame) == N_STEPS * FRAMES
    assert np.allclose(frame.gz_dps, frame.table_rate_dps)
    x_up = frame[frame.orientation == "x_up"]
    assert np.allclose(x_up.ax_g, 1.0) and np.allclose(x_up.az_g, 0.0)
    # Monitor rows were kept while ramping and soaking with the IMU mounted.
    assert len(campaign.store.samples_frame(campaign.cid, include_monitor=True)) > len(frame)
    assert runner.stats.steps_recorded == N_STEPS and runner.stats.samples == N_STEPS * FRAMES
    with pytest.raises(NoCurrentStep, match="no current step"):
        _ = runner.step


def test_chamber_overshooting_its_safety_limit_trips_to_safe_stop(campaign):
    lab = FakeLab()

    def stick_heater(runner: CampaignRunner) -> None:
        lab.chamber.stuck_heater_c = 60.0  # on the way to 35 C the air keeps heating past the 40 C limit

    progress = at_step([], 2, stick_heater)
    runner = campaign.runner(lab, progress=progress)
    assert runner.run() == "aborted"
    assert campaign.store.campaign(campaign.cid).status == "aborted"
    ev = campaign.events()
    trips = ev[ev.kind == "interlock"]
    assert len(trips) == 1
    reason = trips.message.iloc[0]
    m = re.fullmatch(r"chamber at (\d+\.\d) C, outside the safety limits -40\.0\.\.40\.0 C", reason)
    assert m and 40.0 < float(m.group(1)) < 60.0
    assert runner.last_error == f"interlock: {reason}"
    tr = transitions(campaign)
    assert tr[-2:] == ["ramping -> safe_stop", "safe_stop -> aborted"]  # it never came within 0.5 C of 35 C
    assert "lab in safe state: table stopped, chamber to 23.0 C" in campaign.messages()
    t_trip = float(trips.t_s.iloc[0])
    # After the trip: the table was stopped and the chamber parked at the remount temperature.
    assert any(t >= t_trip for t, _ in lab.table.called("stop")) and lab.table.rate == 0.0
    assert lab.chamber.called("set_setpoint")[-1][1] == (23.0,) and lab.chamber.setpoint == 23.0
    assert (campaign.steps().status == "done").sum() == 2
    # Repaired, a second runner resumes the campaign to the end.
    lab2 = FakeLab(VirtualClock(start=lab.clock.now() + 600.0))
    assert campaign.runner(lab2).run() == "done"
    assert campaign.record_blocks_per_step() == {k: 1 for k in range(N_STEPS)}


def test_table_overspeed_and_imu_overheat_trip_their_interlocks(tmp_path):
    for name, arm, start in (("speed", lambda lab: setattr(lab.table, "overspeed_dps", 160.0), "table at 160.00"),
                             ("heat", lambda lab: setattr(lab.imu, "self_heating_c", 75.0), "IMU at 90.0")):
        d = tmp_path / name
        d.mkdir()
        c = Campaign(d)
        lab = FakeLab()
        runner = c.runner(lab, progress=at_step([], 1, lambda _r, lab=lab, arm=arm: arm(lab)))
        assert runner.run() == "aborted"
        ev = c.events()
        assert list(ev[ev.kind == "interlock"].message.str[:len(start)]) == [start]
        assert lab.table.called("stop")[-1][0] >= float(ev[ev.kind == "interlock"].t_s.iloc[0])
        assert (c.steps().status == "done").sum() == 1  # the tripped record was not stored
        c.store.close()


@pytest.mark.parametrize("policy, final", [("pause", "paused"), ("abort", "aborted")])
def test_an_instrument_error_pauses_or_aborts_per_the_fault_policy(tmp_path, policy, final):
    c = Campaign(tmp_path, PROC.replace("policy: pause", f"policy: {policy}"))
    lab = FakeLab()
    runner = c.runner(lab, progress=at_step([], 3, lambda _r: lab.table.fail("velocity")))
    assert runner.run() == final
    assert c.store.campaign(c.cid).status == final
    ev = c.events()
    faults = ev[ev.kind == "fault"]
    assert list(faults.message) == ["rate table at fake:table: no reply to velocity (fake failure)"]
    assert int(faults.step_idx.iloc[0]) == 3
    assert runner.last_error == faults.message.iloc[0]
    steps = c.steps()
    assert list(steps.status[:4]) == ["done", "done", "done", "planned"] and steps.attempts[3] == 1
    assert lab.table.rate == 0.0  # stopped on pause, and by the safe stop on abort
    tr = transitions(c)
    if policy == "pause":
        assert tr[-1] == "recording -> paused"
        assert lab.chamber.setpoint == 35.0  # a pause leaves the chamber where it was
    else:
        assert tr[-2:] == ["recording -> safe_stop", "safe_stop -> aborted"]
        assert lab.chamber.setpoint == 23.0


def test_a_fault_pause_auto_resumes_after_the_delay(campaign):
    lab = FakeLab()
    runner = campaign.runner(lab, progress=at_step([], 3, lambda _r: lab.table.fail("velocity")),
                             auto_resume_s=900.0)
    assert runner.run() == "done"
    assert runner.auto_resumes == 1
    ev = campaign.events()
    t_pause = float(ev[ev.message == "recording -> paused"].t_s.iloc[0])
    t_resume = float(ev[ev.message == "paused -> preflight"].t_s.iloc[0])
    assert t_resume - t_pause == pytest.approx(900.0)
    assert "resuming after a fault pause (auto-resume 1)" in campaign.messages()
    assert campaign.record_blocks_per_step() == {k: 1 for k in range(N_STEPS)}
    # Resumed in the same session with the IMU still mounted: no remount for that orientation.
    assert [o for _, o, _ in lab.operator.remounts] == ["x_up", "z_down"]
    assert "preflight -> ramping" in transitions(campaign)


def test_an_operator_pause_is_not_auto_resumed(campaign):
    lab = FakeLab()
    runner = campaign.runner(lab, progress=at_step([], 2, lambda r: r.request_pause("test pause")),
                             auto_resume_s=900.0)
    assert runner.run() == "paused" and runner.auto_resumes == 0


def test_a_pause_request_stops_at_the_next_safe_point_and_a_second_runner_resumes(campaign):
    lab = FakeLab()
    progress = at_step([], 3, lambda r: r.request_pause("test pause"))
    assert campaign.runner(lab, progress=progress).run() == "paused"
    assert campaign.store.campaign(campaign.cid).status == "paused"
    # The safe point is right after step 2's commit: nothing of step 3 was started.
    assert (campaign.steps().status == "done").sum() == 3
    ev = campaign.events()
    assert ev[ev.kind == "operator"].message.iloc[-1] == "test pause"
    assert transitions(campaign)[-1] == "recording -> paused"
    assert len(lab.table.called("jog")) == 3 and lab.table.rate == 0.0

    lab2 = FakeLab(VirtualClock(start=lab.clock.now() + 60.0))
    runner2 = campaign.runner(lab2)
    assert runner2.k == 3 and runner2.step.index == 3
    assert runner2.run() == "done"
    assert campaign.record_blocks_per_step() == {k: 1 for k in range(N_STEPS)}
    recorded = [int(m.split()[1]) for m in campaign.messages() if " recorded: " in m]
    assert recorded == list(range(N_STEPS))  # no step twice, none skipped
    assert "campaign resumed at step 3" in campaign.messages()
    # The second session remounts (the IMU may have been moved meanwhile) and starts a new run.
    assert [o for _, o, _ in lab2.operator.remounts] == ["x_up", "z_down"]
    assert [args[0] for _, args in lab2.table.called("jog")] == [s.rate_dps for s in runner2.plan[3:]]
    steps = campaign.steps()
    assert list(steps.run) == [1, 1, 1, 2, 3, 3, 3, 3]  # run 2: x_up again for step 3; run 3: z_down
    assert len(campaign.store.samples_frame(campaign.cid)) == N_STEPS * FRAMES


def test_the_safe_stop_keeps_retrying_an_instrument_that_fails_a_few_times(campaign):
    lab = FakeLab()

    def abort_with_a_stubborn_table(runner: CampaignRunner) -> None:
        lab.table.fail("stop", times=3)
        runner.request_abort("test abort")

    progress = at_step([], 2, abort_with_a_stubborn_table)
    assert campaign.runner(lab, progress=progress).run() == "aborted"
    msgs = campaign.messages()
    retries = [m for m in msgs if m.startswith("safe state not reached yet, trying again: ")]
    assert retries == ["safe state not reached yet, trying again: could not stop the table: rate table at "
                       "fake:table: no reply to stop (fake failure)"] * 3
    assert msgs[-2:] == ["lab in safe state: table stopped, chamber to 23.0 C", "safe_stop -> aborted"]
    t_abort = progress.fired[0]
    stops = [t for t, _ in lab.table.called("stop") if t >= t_abort]
    assert len(stops) == 4 and np.allclose(np.diff(stops), SAFE_STOP_RETRY_S)
    assert lab.table.rate == 0.0 and lab.chamber.setpoint == 23.0
    # Remount and ramp setpoints, then parked once: the chamber answered at the first try.
    assert [args[0] for _, args in lab.chamber.called("set_setpoint")] == [23.0, 15.0, 23.0]


def test_a_safe_stop_that_never_succeeds_fails_the_campaign(campaign):
    lab = FakeLab()

    def abort_with_a_dead_table(runner: CampaignRunner) -> None:
        lab.table.fail("stop", times=10_000)
        runner.request_abort("test abort")

    progress = at_step([], 2, abort_with_a_dead_table)
    runner = campaign.runner(lab, progress=progress)
    assert runner.run() == "failed"
    assert campaign.store.campaign(campaign.cid).status == "failed"
    msgs = campaign.messages()
    assert msgs[-2].startswith("safe state NOT reached: could not stop the table")
    assert msgs[-1] == "safe_stop -> failed"
    stops = [t for t, _ in lab.table.called("stop") if t >= progress.fired[0]]
    assert stops[-1] - stops[0] >= SAFE_STOP_PERSIST_S
    assert len(stops) == int(SAFE_STOP_PERSIST_S / SAFE_STOP_RETRY_S) + 1
    assert lab.chamber.setpoint == 23.0  # what could be made safe was


def test_lost_frames_record_the_step_again_then_give_up(tmp_path):
    c = Campaign(tmp_path)
    lab = FakeLab()
    assert c.runner(lab, progress=at_step([], 1, lambda _r: lab.imu.lose_frames([5]))).run() == "done"
    assert f"step 1: 5 of {FRAMES} frames lost (allowed 0); recording again" in c.messages()
    steps = c.steps()
    assert steps.attempts[1] == 2 and (steps.attempts.drop(1) == 1).all() and (steps.n_samples == FRAMES).all()
    c.store.close()

    d = tmp_path / "again"
    d.mkdir()
    c = Campaign(d)
    lab = FakeLab()
    runner = c.runner(lab, progress=at_step([], 1, lambda _r: lab.imu.lose_frames([5, 5, 5])))
    assert runner.run() == "paused"  # max_rerecords 2: the third loss goes to the fault policy
    assert c.messages().count(f"step 1: 5 of {FRAMES} frames lost (allowed 0); recording again") == 2
    assert runner.last_error == f"imu at fake:imu: step 1: frames lost in 3 attempts (5 of {FRAMES} in the last)"
    assert c.steps().status[1] == "planned"
    c.store.close()


@pytest.mark.parametrize("policy, final", [("abort", "aborted"), ("pause", "paused"), ("continue", "done")])
def test_a_chamber_too_slow_to_soak_meets_the_timeout_policy(tmp_path, policy, final):
    c = Campaign(tmp_path, PROC.replace("on_timeout: continue", f"on_timeout: {policy}")
                 .replace("max_wait_s: 3600", "max_wait_s: 600"))
    lab = FakeLab()
    lab.chamber.ramp_c_per_s = 0.01  # 8 C to go at 0.6 C/min: far more than 600 s
    assert c.runner(lab).run() == final
    msg = f"ramp at 15.0 C did not stabilise within soak.max_wait_s (600 s); on_timeout: {policy}"
    ev = c.events()
    kinds = list(ev[ev.message == msg].kind)
    # Carrying on meets the slow chamber at both ramps to 15 C; stopping at the first.
    assert kinds == (["warning", "warning"] if policy == "continue" else ["fault"])
    assert (c.steps().status == "done").sum() == (N_STEPS if policy == "continue" else 0)
    c.store.close()


def test_a_failing_end_of_run_fit_leaves_the_campaign_done_with_its_data(tmp_path):
    # Two orientations cannot give a six-position fit: the data stay, the fit can be run again later.
    c = Campaign(tmp_path, PROC.replace("fit: {run: false}", "fit: {run: true, rbf: false}"))
    runner = c.runner(FakeLab(), fit_out_dir=tmp_path / "fit")
    assert runner.run() == "done"
    ev = c.events()
    warnings = list(ev[ev.kind == "warning"].message)
    assert len(warnings) == 1 and warnings[0].startswith("fit failed: ")
    assert runner.fit_summary.startswith("fit failed: ") and not runner.fit_ok
    assert c.store.fits_frame(c.cid).empty and not (tmp_path / "fit").exists()
    assert len(c.store.samples_frame(c.cid)) == N_STEPS * FRAMES
    c.store.close()
