"""Ramp campaigns end to end with the thermal lag: the steps' temperature-bin tags read back from the store,
and a shortened copy of procedures/ramp_campaign.yaml (its fit section: the lag searched) run as a dry run
on a simulated IMU whose element lags its sensor, fitted at its end and compensated with the files written."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labrunner.calibration.apply import compensate_data, read_model
from labrunner.calibration.compensation import compensate
from labrunner.calibration.thermal_lag_fit import lag_corrected_temperature
from labrunner.data_source import load_campaign_data
from labrunner.procedure import parse_procedure
from labrunner.ramp_plan import stored_bins
from labrunner.store import Store

from .conftest import ROOT, cli
from .test_ramp_campaign import RAMP

OUT = ["ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps"]


def test_the_bin_tag_of_every_step_round_trips_through_the_store(tmp_path):
    proc = tmp_path / "ramp.yaml"
    proc.write_text(RAMP)
    db = tmp_path / "r.db"
    cli("run", proc, "--sim", "--seed", 4, "--db", db, "--quiet", check=0)
    plan = parse_procedure(RAMP, "ramp.yaml").steps()
    with Store.open_existing(db) as s:
        bins = stored_bins(s, 1)
    assert len(bins) == len(plan)
    assert list(bins.bin_index) == [p.temperature_index for p in plan]
    # Each step's setpoint lies in its tagged bin, 1 C wide from the start of its orientation's ramp.
    assert np.all((bins.temperature_c >= bins.bin_lo_c - 1e-9) & (bins.temperature_c <= bins.bin_hi_c + 1e-9))
    assert np.allclose(bins.bin_hi_c - bins.bin_lo_c, 1.0)
    up = bins[bins.orientation == "z_up"]
    down = bins[bins.orientation == "z_down"]
    assert up.bin_lo_c.iloc[0] == 15.0 and down.bin_hi_c.iloc[0] == 25.0  # serpentine: down starts at 25
    assert up.bin_index.is_monotonic_increasing and set(up.bin_index) == set(range(10))
    # The records the fit reads back carry the tag through their step's time span.
    frame = load_campaign_data(db).frame
    tag = np.full(len(frame), -1)
    for b, a, e in zip(bins.bin_index, bins.t_start, bins.t_end, strict=True):
        tag[(frame.t_s >= a) & (frame.t_s <= e)] = b
    assert (tag >= 0).all()


def test_a_soak_campaign_has_no_bin_tags(tmp_path):
    text = RAMP.replace("ramp: {c_per_min: 0.5, bin_c: 1.0}\n", "")
    proc = tmp_path / "soak.yaml"
    proc.write_text(text)
    db = tmp_path / "s.db"
    cli("run", proc, "--sim", "--seed", 4, "--db", db, "--quiet", check=0)
    with Store.open_existing(db) as s:
        assert (stored_bins(s, 1).bin_index == -1).all()


def _short_ramp_campaign() -> str:
    """procedures/ramp_campaign.yaml over 10 ... 22 C with three rates: its fit section as shipped."""
    text = (ROOT / "procedures" / "ramp_campaign.yaml").read_text()
    assert "thermal_lag_auto: true" in text
    text = text.replace("start_c: -25", "start_c: 10").replace("stop_c: 55", "stop_c: 22")
    text = text.replace("triangular: {max_dps: 100, step_dps: 10}", "list_dps: [-50, 0, 50]")
    text = text.replace("rbf: true", "rbf: false")
    return text


@pytest.mark.slow
@pytest.mark.timeout(900)  # the dry run with its 20 min end holds and the lag search: 270 s at load 10
def test_a_shortened_ramp_campaign_dry_run_fits_with_the_lag_and_compensates_as_it_fitted(tmp_path):
    proc = tmp_path / "ramp.yaml"
    proc.write_text(_short_ramp_campaign())
    sim = tmp_path / "sim.json"
    sim.write_text(json.dumps({"seed": 3, "imu_model": {"effects": {"thermal_lag": {"tau_s": 240.0}}}}))
    db, fit_dir = tmp_path / "r.db", tmp_path / "fit"
    cli("run", proc, "--sim", "--sim-config", sim, "--seed", 3, "--db", db, "--fit-out", fit_dir, "--quiet",
        check=0, timeout=900)
    with Store.open_existing(db) as s:
        assert s.campaign(1).status == "done"
    summary = (fit_dir / "summary.md").read_text()
    assert "thermal lag tau" in summary
    model = read_model(fit_dir / "polynomial.json")
    frame = load_campaign_data(db).frame
    out = compensate_data(model, frame).frame
    if model.temperature_filter is not None:  # the lag was used: compensate feeds the model the filtered T
        assert "temp_filter_update" in (fit_dir / "imu_calibration.h").read_text()
        temp = lag_corrected_temperature(frame.t_s.to_numpy(), frame.imu_temp_c.to_numpy(), frame.run.to_numpy(),
                                         model.temperature_filter.tau_s)
        assert 100.0 < model.temperature_filter.tau_s < 600.0
    else:
        temp = frame.imu_temp_c.to_numpy()
    want = compensate(model.model, frame[OUT].to_numpy(), temp).values
    assert np.allclose(out[[c + "_comp" for c in OUT]].to_numpy(), want, atol=1e-12)


def test_the_end_hold_repeats_the_schedule_at_the_far_end_in_its_last_bin():
    from labrunner.ramp_plan import ramp_points

    durations = [12.5, 12.0, 12.5]
    plain = ramp_points(15.0, 25.0, 0.5, 1.0, durations)
    held = ramp_points(15.0, 25.0, 0.5, 1.0, durations, end_hold_s=100.0)
    assert held[:len(plain)] == plain
    extra = held[len(plain):]
    assert len(extra) == 3 * 3  # whole passes of 37 s covering 100 s
    assert {p.temperature_c for p in extra} == {plain[-1].temperature_c}
    assert {p.bin_index for p in extra} == {plain[-1].bin_index}
    assert [p.rate_index for p in extra] == [0, 1, 2] * 3


def test_an_end_hold_lengthens_the_plan_and_is_validated():
    held = parse_procedure(RAMP.replace("bin_c: 1.0}", "bin_c: 1.0, end_hold_s: 600}"), "ramp.yaml")
    plain = parse_procedure(RAMP, "ramp.yaml")
    assert len(held.steps()) > len(plain.steps())
    assert held.estimated_duration_s() - plain.estimated_duration_s() == pytest.approx(2 * 600, abs=2 * 40)
    bad = RAMP.replace("bin_c: 1.0}", "bin_c: 1.0, end_hold_s: -5}")
    with pytest.raises(Exception, match="ramp.end_hold_s"):
        parse_procedure(bad, "ramp.yaml")


SOAKS = RAMP.replace("ramp: {c_per_min: 0.5, bin_c: 1.0}\n", "").replace(
    "temperatures: {start_c: 15, stop_c: 25, step_c: 5, order: serpentine}",
    "temperatures: {list_c: [5, 25, 45], order: serpentine}").replace(
    "tolerance_c: 0.5, stable_window_s: 120, max_wait_s: 3600", "tolerance_c: 0.1, stable_window_s: 600, "
    "max_wait_s: 10800").replace(
    "chamber_max_c: 40", "chamber_max_c: 60")


def test_a_soak_campaigns_records_are_compensated_at_the_soaked_element_temperature(tmp_path, monkeypatch):
    """The held-out soaks of bench_chamber_time: records after unlogged moves and soaks, compensated with a
    model that carries a lag filter. The filter of `compensate` must give the element's temperature the
    simulated IMU had (soaked: its sensor's), not a line bridged across the 20 C moves, which puts the
    first record of every soak ~(20 C / gap) x tau behind, heating and cooling with opposite signs."""
    from labrunner.calibration.apply import ModelFile
    from labrunner.calibration.thermal_lag_fit import TemperatureFilter
    from labrunner.imu.recursions import first_order_lag
    from labrunner.sims.world import SimLabConfig

    from .sim_truth import dry_run_with_truth

    proc, sim, db = tmp_path / "soaks.yaml", tmp_path / "sim.json", tmp_path / "s.db"
    proc.write_text(SOAKS)
    sim.write_text(json.dumps({"seed": 6, "imu_model": {"effects": {"thermal_lag": {"tau_s": 240.0}}}}))
    truth = dry_run_with_truth(monkeypatch, proc, sim, db, 6)
    element = SimLabConfig.from_dict(json.loads(sim.read_text())).imu_model.element_temperature(truth)
    frame = load_campaign_data(db).frame
    t = frame.t_s.to_numpy()
    j = np.searchsorted(truth.t_s, t - 1e-6)
    assert np.abs(truth.t_s[j] - t).max() < 1e-6
    # The temperature `compensate` feeds a model file that carries the filter (apply.ModelFile).
    got = ModelFile(model=None, name="polynomial", path="-",  # type: ignore[arg-type]
                    temperature_filter=TemperatureFilter(240.0, 0.02)).model_temperature(frame)
    bridged = np.concatenate([first_order_lag(t[frame.run == r], frame.imu_temp_c[frame.run == r].to_numpy(),
                                              240.0) for r in np.unique(frame.run)])
    assert np.abs(bridged - element[j]).max() > 1.0  # what a line across the moves gave (1.29 C)
    # The element has not quite caught up at the end of a 0.1 C soak: the sensor itself is off by 0.048 C.
    # The filter restarted after each move is as close (0.052 C), within a 0.01 C LSB.
    sensor_off = np.abs(frame.imu_temp_c.to_numpy() - element[j]).max()
    assert sensor_off < 0.06
    assert np.abs(got - element[j]).max() < sensor_off + 0.01


@pytest.mark.slow
@pytest.mark.timeout(900)  # a dry run, a diagnosis and two fits: past 300 s on the loaded 2-core machine
def test_fit_takes_tau_from_the_diagnosis_json(tmp_path):
    """`fit --thermal-lag from:DIAG.json`: the thermal_lag finding `labrunner diagnose --json` wrote."""
    sim = tmp_path / "sim.json"
    sim.write_text(json.dumps({"seed": 5, "imu_model": {"effects": {"thermal_lag": {"tau_s": 240.0}}}}))
    db, diag, fit = tmp_path / "c.db", tmp_path / "d.json", tmp_path / "f.json"
    cli("run", ROOT / "procedures" / "quick.yaml", "--sim", "--sim-config", sim, "--db", db, "--quiet", check=0)
    cli("diagnose", db, "--json", diag, check=0)
    found = next(f for f in json.loads(diag.read_text())["findings"] if f["cause"] == "thermal_lag")
    p = cli("fit", db, "--no-store", "--no-eval", "--rbf", "", "--thermal-lag", f"from:{diag}", "--json", fit,
            check=0, timeout=600)
    assert f"thermal lag tau = {found['parameters']['tau_s']:.1f} s from the diagnosis {diag}" in p.stderr
    lag = json.loads(fit.read_text())["thermal_lag"]
    assert lag["tau_s"] == pytest.approx(found["parameters"]["tau_s"]) and lag["source"] == "configured"
    # A diagnosis without the finding, a missing file, a file that is not a diagnosis: one line each.
    none = tmp_path / "none.json"
    none.write_text(json.dumps({**json.loads(diag.read_text()), "findings": []}))
    (tmp_path / "x.json").write_text("{not json")
    for arg, msg in ((none, "the diagnosis found no thermal_lag"), (tmp_path / "nope.json", "no such file"),
                     (tmp_path / "x.json", "not JSON")):
        p = cli("fit", db, "--no-store", "--thermal-lag", f"from:{arg}", check=2)
        assert msg in p.stderr and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
