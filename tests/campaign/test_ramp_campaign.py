"""Ramp campaigns (a `ramp:` section) and the shipped procedures of issue 16: the plan along a ramp,
its validation, the sequencer moving the setpoint with the steps (one soak per orientation), a dry run
whose records the calibration cuts into temperature bins, and paper_campaign_fast / ramp_campaign."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labrunner.calibration.records import segment_records, temperature_steps
from labrunner.clock import VirtualClock
from labrunner.data_source import load_campaign_data
from labrunner.procedure import load_procedure, parse_procedure
from labrunner.ramp_plan import ramp_points
from labrunner.yaml_config import ConfigError

from .conftest import ROOT, cli
from .fakes import FakeLab
from .test_runner_inprocess import Campaign

RAMP = """\
name: ramp
temperatures: {start_c: 15, stop_c: 25, step_c: 5, order: serpentine}
soak: {tolerance_c: 0.5, stable_window_s: 120, max_wait_s: 3600, on_timeout: abort, sensor: imu, poll_s: 30}
ramp: {c_per_min: 0.5, bin_c: 1.0}
orientations: [z_up, z_down]
remount_c: 23
remount_s: 60
rates: {list_dps: [-50, 0, 50]}
settle_s: 2
record_s: 10
record_poll_s: 5
safety: {chamber_min_c: -40, chamber_max_c: 40, max_rate_dps: 150, imu_max_temp_c: 85}
monitor: {enabled: false}
fit: {run: false}
"""


def test_ramp_points_move_at_the_slope_and_repeat_the_schedule():
    pts = ramp_points(15.0, 25.0, 0.5, 1.0, [12.5, 12.0, 12.5])  # 37 s per pass of three rates
    temps = np.array([p.temperature_c for p in pts])
    assert temps[0] == 15.0 and temps[-1] <= 25.0 and 25.0 - temps[-1] < 0.5 * 12.5 / 60 + 1e-9
    assert np.all(np.diff(temps) > 0)
    # Step k starts after the durations of the steps before it, at 0.5 C/min.
    elapsed = np.cumsum([0.0] + [[12.5, 12.0, 12.5][p.rate_index] for p in pts[:-1]])
    assert temps == pytest.approx(15.0 + 0.5 * elapsed / 60.0, abs=1e-3)
    assert [p.rate_index for p in pts[:6]] == [0, 1, 2, 0, 1, 2]
    assert [p.bin_index for p in pts] == [int(np.floor(t - 15.0 + 1e-9)) for t in temps]
    down = ramp_points(25.0, 15.0, 0.5, 1.0, [12.5, 12.0, 12.5])
    assert [p.temperature_c for p in down] == pytest.approx([40.0 - t for t in temps], abs=2e-3)
    assert len(ramp_points(20.0, 20.0, 0.5, 1.0, [10.0, 10.0])) == 2  # no width: one pass


def test_a_ramp_procedure_expands_along_the_ramp_per_orientation():
    p = parse_procedure(RAMP, "ramp.yaml")
    steps = p.steps()
    up = [s for s in steps if s.orientation == "z_up"]
    down = [s for s in steps if s.orientation == "z_down"]
    assert up[0].temperature_c == 15.0 and down[0].temperature_c == 25.0  # serpentine: up, then down
    assert len(up) == len(down) and len(up) > 3 * 10  # the schedule repeated along 10 C at 0.5 C/min
    assert [s.rate_dps for s in up[:6]] == [-50, 0, 50, -50, 0, 50]
    ends = p.estimated_step_ends_s()
    assert len(ends) == len(steps) and np.all(np.diff(ends) > 0)
    # One soak per orientation, not one per temperature: the plan is mostly the ramp itself.
    ramp_s = 10 / 0.5 * 60
    assert p.estimated_duration_s() < 2 * (ramp_s + 3 * 3600)


@pytest.mark.parametrize("ramp, words", [
    ("{c_per_min: 0}", "ramp.c_per_min"), ("{c_per_min: 50}", "ramp.c_per_min"),
    ("{c_per_min: 0.5, bin_c: 100}", "ramp.bin_c"), ("{c_per_min: 0.5, slope: 1}", "slope"),
])
def test_ramp_parameters_are_validated_with_a_located_message(ramp, words):
    text = RAMP.replace("ramp: {c_per_min: 0.5, bin_c: 1.0}", f"ramp: {ramp}")
    with pytest.raises(ConfigError) as exc:
        parse_procedure(text, "ramp.yaml")
    assert words in str(exc.value) and "ramp.yaml:4" in str(exc.value)


def test_the_sequencer_moves_the_setpoint_with_the_steps_and_soaks_once_per_orientation(tmp_path):
    c = Campaign(tmp_path, RAMP)
    try:
        lab = FakeLab(VirtualClock())
        c.runner(lab).run()
        steps = c.steps()
        assert (steps.status == "done").all()
        ev = c.events()
        assert ev.message.str.startswith("soaked at").sum() == 2  # one per orientation
        setpoints = [args[0] for _, args in lab.chamber.called("set_setpoint")]
        plan = list(steps.temperature_c)
        # Every step's planned temperature was set, in plan order (remounts at 23 C in between).
        along = [v for v in setpoints if v != 23.0]
        assert along == [t for i, t in enumerate(plan) if i == 0 or t != plan[i - 1]]
        # The fake IMU is at the chamber's air: each record holds the ramp's temperature at its step.
        assert np.abs(steps.imu_temp_c - steps.temperature_c).max() < 0.5 * 12.5 / 60 + 0.3
    finally:
        c.store.close()


def test_a_ramp_dry_run_gives_records_the_calibration_bins(tmp_path):
    proc = tmp_path / "ramp.yaml"
    proc.write_text(RAMP)
    db = tmp_path / "r.db"
    cli("run", proc, "--sim", "--seed", 4, "--db", db, "--quiet", check=0)
    frame = load_campaign_data(db).frame
    records = segment_records(frame)
    assert len(records) >= 0.9 * len(parse_procedure(proc.read_text(), "ramp.yaml").steps())  # drifting, kept
    bins = temperature_steps(records)
    # Continuous data: 1 C bins along the IMU's range (which lags and self-heats: ~21 ... 28 C), not one
    # cluster of 7 C.
    assert len(bins) >= 5 and np.all(bins.hi_c - bins.lo_c <= 1.0 + 1e-9)
    assert bins.hi_c.max() - bins.lo_c.min() > 5.0 and np.all(np.diff(bins.temp_c) > 0.5)


def test_the_shipped_fast_and_ramp_procedures_check_and_save_lab_time():
    strict = load_procedure(ROOT / "procedures" / "paper_campaign.yaml")
    fast = load_procedure(ROOT / "procedures" / "paper_campaign_fast.yaml")
    ramp = load_procedure(ROOT / "procedures" / "ramp_campaign.yaml")
    assert fast.model.soak.criterion == "predictive" and strict.model.soak.criterion == "spread"
    # The paper's steps, only the soaks judged otherwise.
    assert [(s.orientation, s.temperature_c, s.rate_dps) for s in fast.steps()] == \
        [(s.orientation, s.temperature_c, s.rate_dps) for s in strict.steps()]
    assert fast.estimated_duration_s() < 0.8 * strict.estimated_duration_s()
    assert ramp.model.ramp is not None and ramp.estimated_duration_s() <= 1.5 * 86400
    # Records drift less along the ramp than the calibration's record filter allows (0.1 C/min + 0.05 C).
    assert ramp.model.ramp.c_per_min * ramp.model.record_s / 60 <= 0.1 * ramp.model.record_s / 60 + 0.05
    for name in ("paper_campaign_fast", "ramp_campaign"):
        out = cli("check", name, check=0)
        assert f"procedure '{name}' is valid" in out.stdout


def test_the_soaked_event_of_a_predictive_dry_run_carries_the_decision(tmp_path):
    proc = tmp_path / "p.yaml"
    proc.write_text(RAMP.replace("ramp: {c_per_min: 0.5, bin_c: 1.0}\n", "").replace(
        "poll_s: 30}", "poll_s: 30, criterion: predictive, predict_window_s: 300}").replace("max_wait_s: 3600",
                                                                                           "max_wait_s: 7200"))
    db = tmp_path / "p.db"
    cli("run", proc, "--sim", "--seed", 4, "--db", db, "--quiet", check=0)
    from labrunner.store import Store

    with Store.open_existing(db) as s:
        ev = s.events_frame(1)
    soaked = ev[ev.message.str.startswith("soaked at")]
    assert len(soaked) == 6  # 15, 20, 25 C in two orientations
    details = [json.loads(d) if isinstance(d, str) else d for d in soaked.detail]
    predicted = [d for d in details if d and d.get("criterion") == "predictive"]
    fell_back = ev.message.str.contains("falls back to the spread criterion").sum()
    assert len(predicted) + fell_back == 6 and predicted
    for d in predicted:
        assert d["predicted_drift_bound_c"] <= 0.5 and 10 < d["tau_s"] < 7200 and d["fit_window_s"] >= 7 * 30 - 1
    # On the simulated lab (its IMU lags the air by 600 s and self-heats after power-on) the record after
    # each soak indeed holds: its IMU temperature moves less than the tolerance.
    with Store.open_existing(db) as s:
        steps = s.steps_frame(1)
    frame = load_campaign_data(db).frame
    firsts = steps[steps.idx % 3 == 0]  # each temperature's first rate: the record right after the soak
    assert len(firsts) == 6
    for _, st in firsts.iterrows():
        rows = frame[(frame.t_s >= st.t_start) & (frame.t_s <= st.t_end)]
        assert len(rows) > 400 and rows.imu_temp_c.max() - rows.imu_temp_c.min() <= 0.5
