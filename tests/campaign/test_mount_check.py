"""The operator's remount, checked by gravity: the verdict on accelerometer frames, and what the sequencer
does with it (in-process on fakes, and in a dry run whose simulated operator mounts wrongly)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labrunner.campaign_session import start_run
from labrunner.procedure import parse_procedure
from labrunner.runner.mount_check import in_place, judge
from labrunner.yaml_config import ConfigError

from .fakes import FakeLab
from .test_runner_inprocess import N_STEPS, PROC, Campaign

CHECK = {"max_angle_deg": 10.0, "gravity_tolerance_g": 0.1}


def _tilted(orientation_up: np.ndarray, degrees: float, about: np.ndarray, g: float = 1.0, n: int = 50,
            noise_g: float = 0.0, seed: int = 0) -> np.ndarray:
    """n frames of a specific force `g` along `orientation_up` turned by `degrees` about `about` (Rodrigues)."""
    k = about / np.linalg.norm(about)
    a = math.radians(degrees)
    v = orientation_up * math.cos(a) + np.cross(k, orientation_up) * math.sin(a) + k * np.dot(k, orientation_up) * (
        1 - math.cos(a))
    rng = np.random.default_rng(seed)
    return np.tile(v * g, (n, 1)) + rng.normal(0.0, noise_g, (n, 3))


# --- the verdict ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("degrees, ok", [(0.0, True), (3.0, True), (9.5, True), (10.5, False), (30.0, False)])
def test_the_angle_from_the_planned_up_axis_decides(degrees, ok):
    frames = _tilted(np.array([0.0, -1.0, 0.0]), degrees, np.array([1.0, 0.0, 0.0]), noise_g=0.002)
    v = judge(frames, "y_down", **CHECK)
    assert v.ok is ok
    assert v.off_planned_deg == pytest.approx(degrees, abs=0.3)
    assert v.measured == "y_down" and v.frames == 50
    assert v.describe().startswith("measured: y axis down, ") and v.describe().endswith("; planned: y_down")


def test_a_wrong_axis_is_named_with_its_own_angle():
    frames = _tilted(np.array([1.0, 0.0, 0.0]), 3.0, np.array([0.0, 0.0, 1.0]))
    v = judge(frames, "y_down", **CHECK)
    assert not v.ok and v.measured == "x_up"
    assert v.off_measured_deg == pytest.approx(3.0, abs=1e-6) and v.off_planned_deg > 80
    assert v.describe() == "measured: x axis up, 3.0° off, 1.000 g; planned: y_down"
    # Upside down is 180 degrees from the plan.
    flipped = judge(-frames, "x_up", **CHECK)
    assert not flipped.ok and flipped.measured == "x_down" and flipped.off_planned_deg == pytest.approx(177, abs=1e-6)


@pytest.mark.parametrize("g, ok", [(1.0, True), (1.09, True), (0.85, False), (1.2, False), (0.0, False)])
def test_the_magnitude_must_be_near_one_g(g, ok):
    v = judge(_tilted(np.array([0.0, 0.0, 1.0]), 0.0, np.array([1.0, 0.0, 0.0]), g=g), "z_up", **CHECK)
    assert v.ok is ok
    if g == 0.0:
        assert v.measured is None and "no direction" in v.describe()


def test_no_frames_is_refused_and_says_so():
    v = judge(np.zeros((0, 3)), "z_up", **CHECK)
    assert not v.ok and v.frames == 0 and v.describe() == "measured: no IMU frames; planned: z_up"
    nan = judge(np.full((5, 3), np.nan), "z_up", **CHECK)
    assert not nan.ok and nan.frames == 0


def test_in_place_needs_the_mount_and_the_chamber():
    right = judge(_tilted(np.array([0.0, 0.0, 1.0]), 1.0, np.array([1.0, 0.0, 0.0])), "z_up", **CHECK)
    wrong = judge(_tilted(np.array([1.0, 0.0, 0.0]), 1.0, np.array([0.0, 1.0, 0.0])), "z_up", **CHECK)
    assert in_place(right, 35.4, 35.0, 2.0).ok
    near_miss = in_place(right, 37.5, 35.0, 2.0)
    assert not near_miss.ok and "chamber 37.50 C is 2.50 C from the step's 35 C" in near_miss.reason
    refused = in_place(wrong, 35.0, 35.0, 2.0)
    assert not refused.ok and "measured: x axis up" in refused.reason
    assert not in_place(None, 35.0, 35.0, 2.0).ok
    assert not in_place(right, float("nan"), 35.0, 2.0).ok


@pytest.mark.parametrize("section, message", [
    ("mount_check: {max_angle_deg: 0}", "max_angle_deg"),
    ("mount_check: {max_angle_deg: 60}", "max_angle_deg"),
    ("mount_check: {tries: 0}", "tries"),
    ("mount_check: {read_s: 0.01}", "read_s"),
    ("mount_check: {gravity_tolerance_g: -1}", "gravity_tolerance_g"),
    ("resume: {chamber_tolerance_c: 0}", "chamber_tolerance_c"),
    ("mount_check: {angle: 5}", "angle"),
])
def test_mount_check_parameters_are_validated_with_their_line(section, message):
    with pytest.raises(ConfigError) as err:
        parse_procedure(PROC + section + "\n", "p.yaml")
    text = str(err.value)
    assert message in text and "p.yaml:" in text


# --- the sequencer, in-process on fakes --------------------------------------------------------------------------


@pytest.fixture
def campaign(tmp_path):
    c = Campaign(tmp_path)
    yield c
    c.store.close()


def _records_by_orientation(c: Campaign):
    frame = c.store.samples_frame(c.cid)
    return {o: frame[frame.orientation == o][["ax_g", "ay_g", "az_g"]].to_numpy().mean(axis=0)
            for o in frame.orientation.unique()}


def test_a_correct_mount_passes_and_the_event_says_what_gravity_showed(campaign):
    lab = FakeLab()
    runner = campaign.runner(lab)
    assert runner.run() == "done"
    ev = campaign.events()
    mounted = list(ev[ev.message.str.startswith("IMU mounted ")].message)
    assert mounted == ["IMU mounted x_up, powered on (run 1); gravity: x axis up, 0.0° off, 1.000 g",
                       "IMU mounted z_down, powered on (run 2); gravity: z axis down, 0.0° off, 1.000 g"]
    assert not ev.message.str.startswith("mount refused").any()
    # Preflight checked the first orientation too (the fake IMU stands z_up before the first mount).
    pre = ev[ev.message.str.startswith("preflight mount check: ")].message.iloc[0]
    assert pre == ("preflight mount check: measured: z axis up, 0.0° off, 1.000 g; planned: x_up "
                   "(the remount prompt follows)")
    # The check read a second of frames through the driver after each remount, before recording.
    restarts = [t for t, _ in lab.imu.called("restart_stream")]
    begins = [t for t, _ in lab.imu.called("begin_record")]
    assert all(any(0 <= b - r < 1e-9 for b in begins) for r in restarts)


def test_a_wrong_mount_is_refused_and_the_operator_asked_again(campaign):
    lab = FakeLab()
    lab.operator.mount_wrongly("y_up", None)  # first turned about the wrong axis, then the remount skipped
    runner = campaign.runner(lab)
    assert runner.run() == "done"
    ev = campaign.events()
    refused = ev[ev.message.str.startswith("mount refused")]
    assert list(refused.message) == [
        "mount refused (try 1 of 3): measured: y axis up, 0.0° off, 1.000 g; planned: x_up",
        "mount refused (try 2 of 3): measured: y axis up, 0.0° off, 1.000 g; planned: x_up"]
    assert all(d["measured"] == "y_up" and d["planned"] == "x_up" for d in refused.detail.map(__import__("json").loads))
    # Asked three times for x_up, the retries saying what was measured; then z_down once.
    asked = [(o, p) for _, o, p in lab.operator.remounts]
    assert [o for o, _ in asked] == ["x_up", "x_up", "x_up", "z_down"]
    assert "measured: y axis up" in asked[1][1] and "planned: x_up" in asked[1][1]
    assert "measured" not in asked[0][1] and "measured" not in asked[3][1]
    # Nothing was recorded before the mount was right: every record under a label has its gravity.
    means = _records_by_orientation(campaign)
    assert np.allclose(means["x_up"], [1, 0, 0]) and np.allclose(means["z_down"], [0, 0, -1])
    assert campaign.record_blocks_per_step() == {k: 1 for k in range(N_STEPS)}
    # Only the confirmed mounts are runs.
    assert sorted(campaign.store.samples_frame(campaign.cid).run.unique()) == [1, 2]


def test_after_the_tries_the_campaign_pauses_and_a_resume_mounts_again(campaign):
    lab = FakeLab()
    lab.operator.mount_wrongly(None, None, None)  # three skipped remounts (the IMU stays z_up)
    runner = campaign.runner(lab)
    assert runner.run() == "paused"
    assert runner.last_error.startswith("mount of x_up not confirmed by gravity in 3 tries (measured: z axis up")
    ev = campaign.events()
    assert ev.message.str.startswith("mount refused (try 3 of 3)").sum() == 1
    fault = ev[ev.kind == "fault"]
    assert len(fault) == 1 and "measured: z axis up" in fault.message.iloc[0]
    assert list(ev[ev.kind == "transition"].message)[-1] == "mounting -> paused"
    assert campaign.record_blocks_per_step() == {}  # nothing recorded under the wrong label
    assert runner.auto_resumes == 0 and campaign.store.campaign(campaign.cid).status == "paused"
    # The operator fixes it; a resume (a new session) prompts again and the campaign completes.
    again = campaign.runner(lab)
    assert again.run() == "done"
    assert [o for _, o, _ in lab.operator.remounts] == ["x_up"] * 4 + ["z_down"]
    assert campaign.record_blocks_per_step() == {k: 1 for k in range(N_STEPS)}


def test_the_check_can_be_switched_off(tmp_path):
    c = Campaign(tmp_path, PROC + "mount_check: {enabled: false}\n")
    lab = FakeLab()
    lab.operator.mount_wrongly("y_up")
    try:
        assert c.runner(lab).run() == "done"
        assert not c.events().message.str.contains("mount check|mount refused").any()
        assert len(lab.operator.remounts) == 2  # trusted: the mislabelled data are the lab's choice
    finally:
        c.store.close()


def test_tries_is_the_procedures(tmp_path):
    c = Campaign(tmp_path, PROC + "mount_check: {tries: 1}\n")
    lab = FakeLab()
    lab.operator.mount_wrongly("x_down")
    try:
        runner = c.runner(lab)
        assert runner.run() == "paused"
        assert "in 1 tries (measured: x axis down" in runner.last_error
        assert len(lab.operator.remounts) == 1
    finally:
        c.store.close()


# --- a dry run whose simulated operator mounts wrongly -----------------------------------------------------------

DRY = """\
name: dry-mount
temperatures: {list_c: [23]}
soak: {tolerance_c: 1.0, stable_window_s: 60, max_wait_s: 3600, on_timeout: continue, sensor: chamber, poll_s: 30}
orientations: [x_up, y_down]
remount_s: 60
rates: {list_dps: [0, 20]}
settle_s: 1
record_s: 2
record_poll_s: 1
fit: {run: false}
"""


def _dry_run(tmp_path, operator: dict):
    proc = tmp_path / "dry.yaml"
    proc.write_text(DRY)
    with start_run(proc, db=tmp_path / "dry.db", sim_config={"operator": operator}) as session:
        result = session.execute()
        ev = session.store.events_frame(session.campaign_id)
        frame = session.store.samples_frame(session.campaign_id)
    return result, ev, frame


def test_dry_run_a_wrong_mount_is_refused_and_nothing_recorded_under_its_label(tmp_path):
    result, ev, frame = _dry_run(tmp_path, {"wrong_mounts": 2, "mounts_as": "z_up"})
    assert result.state == "done"
    refused = list(ev[ev.message.str.startswith("mount refused")].message)
    assert len(refused) == 2 and all("measured: z axis up" in m and "planned: x_up" in m for m in refused)
    assert ev.message.str.startswith("IMU mounted x_up, powered on (run 1); gravity: x axis up").sum() == 1
    # The simulated IMU's data under each label show that label's gravity (bias and noise aside).
    for orientation, up in (("x_up", [1, 0, 0]), ("y_down", [0, -1, 0])):
        mean = frame[frame.orientation == orientation][["ax_g", "ay_g", "az_g"]].to_numpy().mean(axis=0)
        assert np.allclose(mean, up, atol=0.05), (orientation, mean)
    assert len(frame) == 4 * 100


def test_dry_run_pauses_after_the_tries(tmp_path):
    result, ev, frame = _dry_run(tmp_path, {"wrong_mounts": 4})  # skipped remounts: the IMU stays x_up
    # The first mount happens to be right (the simulated IMU starts x_up): the skipped ones are y_down's.
    assert result.state == "paused" and result.exit_code == 3
    assert "mount of y_down not confirmed by gravity in 3 tries (measured: x axis up" in result.reason
    assert ev.message.str.startswith("mount refused").sum() == 3
    assert set(frame.orientation) == {"x_up"} and len(frame) == 2 * 100


def test_an_imu_silent_during_the_check_is_an_instrument_fault_not_a_wrong_mount(campaign):
    lab = FakeLab()
    lab.imu.lose_frames([0, 50])  # preflight's check gets its frames; the one after the first remount none
    runner = campaign.runner(lab, auto_resume_s=600.0)
    assert runner.run() == "done"
    ev = campaign.events()
    faults = list(ev[ev.kind == "fault"].message)
    assert faults == ["imu at fake:imu: no IMU frames in 1 s for the mount check of x_up (is it powered and "
                      "connected?)"]
    assert not ev.message.str.startswith("mount refused").any()
    # The fault policy paused it (a fault pause, resumed in a rehearsal); the resume mounted again.
    assert runner.auto_resumes == 1
    assert [o for _, o, _ in lab.operator.remounts] == ["x_up", "x_up", "z_down"]


def test_the_command_line_says_why_it_paused_and_resume_mounts_again(tmp_path):
    from .conftest import cli

    proc_file = tmp_path / "dry.yaml"
    proc_file.write_text(DRY)
    sim = tmp_path / "sim.yaml"
    sim.write_text("operator: {wrong_mounts: 4}\n")  # x_up happens to be right; y_down's three tries skipped
    db = tmp_path / "cli.db"
    run = cli("run", proc_file, "--sim", "--sim-config", sim, "--db", db, "--quiet", check=3)
    assert "reason: mount of y_down not confirmed by gravity in 3 tries (measured: x axis up" in run.stderr
    # Resumed, the simulated operator (a new session) goes wrong again for its first four remounts: paused again.
    again = cli("resume", db, "--quiet", check=3)
    assert "not confirmed by gravity" in again.stderr
