"""Resume in place: a campaign interrupted with the IMU still mounted as the next step plans and the chamber
near that step's setpoint goes on without a remount or a ramp to room temperature; otherwise it remounts as
before. In-process on fakes (a second runner is the resumed session), and a kill -9 of `labrunner run --sim`
followed by `labrunner resume`."""

from __future__ import annotations

import signal

import numpy as np
import pytest
from sqlalchemy import text

from labrunner.runner.last_state import last_mount, last_readings, last_setpoint
from labrunner.store import Store

from .conftest import cli, crashing_cli
from .fakes import FakeLab
from .test_runner_inprocess import N_STEPS, PROC, Campaign, at_step


@pytest.fixture
def campaign(tmp_path):
    c = Campaign(tmp_path)
    yield c
    c.store.close()


def _interrupted(c: Campaign, after_steps: int) -> FakeLab:
    """Run until `after_steps` steps are recorded, then pause (the session ends; the lab is left as it is)."""
    lab = FakeLab()
    first = c.runner(lab)
    first.progress = at_step([first], after_steps, lambda r: r.request_pause("test: interrupted"))
    assert first.run() == "paused"
    assert c.store.next_step(c.cid) == after_steps
    return lab


def _session_events(c: Campaign):
    ev = c.events()
    start = ev[ev.message.str.startswith("campaign resumed")].index[-1]
    return ev.loc[start:]


def test_the_store_tells_how_the_lab_was_left(campaign):
    assert last_mount(campaign.store, campaign.cid) is None and last_readings(campaign.store, campaign.cid) == (None,
                                                                                                               None)
    _interrupted(campaign, 3)  # steps 0-2 recorded: x_up at 15 C, then x_up at 35 C
    mount = last_mount(campaign.store, campaign.cid)
    assert mount is not None and (mount.orientation, mount.run) == ("x_up", 1) and mount.t_s > 0
    chamber, imu = last_readings(campaign.store, campaign.cid)
    assert chamber == pytest.approx(35.0, abs=0.01) and imu == pytest.approx(35.0, abs=0.01)
    assert last_setpoint(campaign.store, campaign.cid, remount_c=23.0) == 35.0


def test_interrupted_with_the_imu_mounted_and_the_chamber_at_its_setpoint_resumes_in_place(campaign):
    lab = _interrupted(campaign, 3)
    remounts_before = len(lab.operator.remounts)
    setpoints_before = len(lab.chamber.called("set_setpoint"))
    restarts_before = len(lab.imu.called("restart_stream"))
    resumed = campaign.runner(lab)
    assert resumed.run() == "done"
    ev = _session_events(campaign)
    in_place = ev[ev.message.str.startswith("resumed in place: ")]
    assert len(in_place) == 1
    assert in_place.message.iloc[0] == (
        "resumed in place: IMU x axis up, 0.0° off, 1.000 g, as planned (x_up); chamber 35.00 C within 2 C of "
        "35 C; step 3 (x_up, 35 C) without a remount or a ramp to room temperature (run 1)")
    transitions = list(ev[ev.kind == "transition"].message)
    assert transitions[:3] == ["idle -> preflight", "preflight -> ramping", "ramping -> soaking"]
    # Nothing went to room temperature and no one was asked before step 3 was recorded.
    step3 = ev[ev.message.str.startswith("step 3 recorded")].index[0]
    assert not ev.loc[:step3].message.str.startswith("remount: ").any()
    session_setpoints = [a[0] for _, a in lab.chamber.called("set_setpoint")[setpoints_before:]]
    assert session_setpoints == [35.0, 23.0, 35.0, 15.0, 23.0]  # 23 C only for z_down's remount and the park
    # The orientation after it is remounted as usual: z_down, once.
    assert [o for _, o, _ in lab.operator.remounts[remounts_before:]] == ["z_down"]
    assert len(lab.imu.called("restart_stream")) == restarts_before + 1
    # Every step exactly once, and the IMU's run went on (it was never powered off).
    assert campaign.record_blocks_per_step() == {k: 1 for k in range(N_STEPS)}
    frame = campaign.store.samples_frame(campaign.cid)
    assert frame.groupby("orientation").run.unique().map(list).to_dict() == {"x_up": [1], "z_down": [2]}


def test_the_chamber_away_from_the_setpoint_remounts_as_before(campaign):
    lab = _interrupted(campaign, 3)
    lab.chamber.set_setpoint(23.0)  # e.g. someone sent the chamber to ambient meanwhile
    lab.clock.sleep(600.0)
    remounts_before = len(lab.operator.remounts)
    assert campaign.runner(lab).run() == "done"
    ev = _session_events(campaign)
    assert not ev.message.str.startswith("resumed in place").any()
    why = ev[ev.message.str.startswith("resume: remounting: ")].message
    assert list(why) == ["resume: remounting: chamber 23.00 C is 12.00 C from the step's 35 C "
                         "(resume.chamber_tolerance_c 2 C)"]
    assert list(ev[ev.kind == "transition"].message)[:2] == ["idle -> preflight", "preflight -> mounting"]
    assert [o for _, o, _ in lab.operator.remounts[remounts_before:]] == ["x_up", "z_down"]
    assert campaign.record_blocks_per_step() == {k: 1 for k in range(N_STEPS)}
    runs = campaign.store.samples_frame(campaign.cid).groupby("orientation").run.unique()
    assert sorted(runs["x_up"]) == [1, 2]  # the remount began a new run


def test_an_imu_turned_meanwhile_remounts_as_before(campaign):
    lab = _interrupted(campaign, 3)
    lab.imu.orientation = "y_down"  # knocked over, or remounted by hand
    assert campaign.runner(lab).run() == "done"
    ev = _session_events(campaign)
    assert not ev.message.str.startswith("resumed in place").any()
    why = ev[ev.message.str.startswith("resume: remounting: ")].message.iloc[0]
    assert "the IMU does not stand as planned (measured: y axis down, 0.0° off, 1.000 g; planned: x_up)" in why
    assert ev.message.str.startswith("remount: Mount the IMU with its x axis pointing up.").any()
    frame = campaign.store.samples_frame(campaign.cid)
    x_up = frame[frame.orientation == "x_up"]
    assert np.allclose(x_up[["ax_g", "ay_g", "az_g"]].to_numpy(), [1, 0, 0])


def test_a_gravity_match_after_another_orientation_was_last_mounted_is_not_in_place(campaign):
    lab = _interrupted(campaign, 4)  # x_up done; the next step is z_down's, not yet mounted
    lab.imu.orientation = "z_down"  # turned by hand, behind the sequencer's back
    assert campaign.runner(lab).run() == "done"
    ev = _session_events(campaign)
    assert not ev.message.str.startswith("resumed in place").any()
    assert ev.message.str.startswith("resume: remounting: the last mount the campaign recorded was x_up").any()


def test_in_place_can_be_switched_off(tmp_path):
    c = Campaign(tmp_path, PROC + "resume: {in_place: false}\n")
    try:
        lab = _interrupted(c, 3)
        before = len(lab.operator.remounts)
        assert c.runner(lab).run() == "done"
        assert not c.events().message.str.startswith("resumed in place").any()
        assert [o for _, o, _ in lab.operator.remounts[before:]] == ["x_up", "z_down"]
    finally:
        c.store.close()


def test_a_campaign_never_mounted_gets_its_first_prompt_whatever_the_imu_shows(campaign):
    lab = FakeLab()
    lab.imu.orientation = "x_up"  # already standing as the first step plans
    first = campaign.runner(lab)
    first.request_pause("test: before anything")
    assert first.run() == "paused"
    assert campaign.runner(lab).run() == "done"
    assert [o for _, o, _ in lab.operator.remounts] == ["x_up", "z_down"]
    assert not campaign.events().message.str.startswith("resumed in place").any()


# --- kill -9 of a real dry run, then `labrunner resume` ---------------------------------------------------------


def _record_blocks(db) -> dict[int, int]:
    with Store.open_existing(db) as store:
        with store.engine.connect() as conn:
            rows = conn.execute(text("SELECT step_idx, COUNT(*) FROM sample_blocks WHERE kind='record' "
                                     "GROUP BY step_idx")).fetchall()
    return {int(i): int(n) for i, n in rows}


def _events(db):
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        return store.events_frame(cid), store.steps_frame(cid), store.campaign(cid).status


def test_killed_mid_orientation_resumes_in_place_with_every_step_once(tmp_path, tiny):
    db = tmp_path / "k.db"
    # Killed (SIGKILL) as the 8th record is about to be stored: x_down is mounted, the chamber at 35 C.
    proc = crashing_cli("record:8", "run", tiny, "--sim", "--db", db, "--quiet")
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    proc = cli("resume", db, "--quiet", check=0)
    ev, steps, status = _events(db)
    assert status == "done" and (steps.status == "done").all()
    assert _record_blocks(db) == {k: 1 for k in range(len(steps))}  # every step exactly once
    session = ev.loc[ev[ev.message.str.startswith("campaign resumed at step 7")].index[0]:]
    in_place = session[session.message.str.startswith("resumed in place: ")]
    assert len(in_place) == 1, list(session.message[:12])
    message = in_place.message.iloc[0]
    assert "as planned (x_down); chamber 35." in message and "step 7 (x_down, 35 C)" in message
    # No remount prompt and no ramp to room temperature before the interrupted orientation goes on.
    first_record = session[session.message.str.startswith("step 7 recorded")].index[0]
    before = session.loc[:first_record]
    assert not before.message.str.startswith("remount: ").any()
    assert not before.message.str.endswith("-> mounting").any()
    assert list(before[before.message.str.startswith("setpoint ")].message) == ["setpoint 35.0 C"]
    # The data of x_down are one run, before and after the kill.
    with Store.open_existing(db) as store:
        frame = store.samples_frame(store.resolve(None))
    assert list(frame[frame.orientation == "x_down"].run.unique()) == [2]
    assert sorted(frame.run.unique()) == [1, 2, 3, 4, 5, 6]


def test_killed_on_the_way_to_a_new_temperature_remounts_as_before(tmp_path, tiny):
    """The next step's chamber setpoint is not reached (killed mid-ramp): resume remounts, as it always did."""
    ref = tmp_path / "ref.db"
    cli("run", tiny, "--sim", "--db", ref, "--quiet", check=0)
    # The monitor stretch at which the ramp from 15 C to 35 C (x_up) is about halfway, counted in the reference
    # run (a dry run is deterministic): the kill lands before it is stored.
    with Store.open_existing(ref) as store:
        cid = store.resolve(None)
        ev = store.events_frame(cid)
        ramp_t = float(ev[ev.message == "setpoint 35.0 C"].t_s.iloc[0])
        monitors = [b for b in store.blocks(cid, kinds=("monitor",))]
    n = next(i for i, b in enumerate(monitors, 1) if b.t0_s > ramp_t and b.chamber[:, 1].mean() > 25.0)
    db = tmp_path / "k.db"
    proc = crashing_cli(f"monitor:{n}", "run", tiny, "--sim", "--db", db, "--quiet")
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    cli("resume", db, "--quiet", check=0)
    ev, steps, status = _events(db)
    assert status == "done" and _record_blocks(db) == {k: 1 for k in range(len(steps))}
    session = ev.loc[ev[ev.message.str.startswith("campaign resumed at step 3")].index[0]:]
    assert not session.message.str.startswith("resumed in place").any()
    why = session[session.message.str.startswith("resume: remounting: chamber ")].message
    assert len(why) == 1 and "from the step's 35 C" in why.iloc[0]
    assert session.message.str.startswith("remount: Mount the IMU with its x axis pointing up.").any()
