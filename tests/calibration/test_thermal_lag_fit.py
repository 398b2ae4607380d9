"""Calibrating with the thermal lag (labrunner.calibration.thermal_lag_fit): the lag-corrected temperature,
the exported filter (model JSON, `labrunner compensate`, the C header compiled with gcc) and the fit's
choice between the lag-corrected and the plain model."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pandas as pd
import pytest

from labrunner.calibration import compensate
from labrunner.calibration.apply import compensate_data, read_model
from labrunner.calibration.export import save_model, write_c_header
from labrunner.calibration.fit import FitOptions, fit_campaign
from labrunner.calibration.thermal_lag_fit import TemperatureFilter, lag_corrected_temperature
from labrunner.errors import UserError
from labrunner.imu.recursions import first_order_lag

from calib_campaigns import make_campaign

OUT = ["ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps"]


@pytest.fixture(scope="module")
def small_fit():
    return fit_campaign(make_campaign(seed=5, temperatures_c=(-10.0, 10.0, 30.0, 50.0), average_s=1.0),
                        FitOptions(evaluate=False, rbf_variants=("hybrid",)))


def test_the_lag_corrected_temperature_lags_a_ramp_by_rate_times_tau_and_restarts_per_run():
    t = np.arange(0.0, 7200.0, 1.0)
    temp = 10.0 + 0.5 / 60.0 * t  # 0.5 C/min
    run = np.where(t < 3600.0, 1, 2)
    shuffled = np.random.default_rng(0).permutation(t.size)  # rows in any order: filtered in time order per run
    out = np.empty(t.size)
    out[shuffled] = lag_corrected_temperature(t[shuffled], temp[shuffled], run[shuffled], 240.0)
    # Settled on the ramp: behind by r * tau = 2 C; each run's filter starts at its first temperature.
    assert out[3000] == pytest.approx(temp[3000] - 2.0, abs=1e-4)
    assert out[3600] == pytest.approx(temp[3600], abs=1e-9) and out[0] == temp[0]
    assert out[7000] == pytest.approx(temp[7000] - 2.0, abs=1e-4)


def _ramp_frame(period_s: float, n: int, rng: np.random.Generator) -> pd.DataFrame:
    t = np.arange(n) * period_s
    temp = 20.0 + 10.0 * np.sin(t / 900.0) + 0.02 * t / 60.0  # heating and cooling
    y = np.column_stack([rng.normal(0, 0.01, n), rng.normal(0, 0.01, n), 1 + rng.normal(0, 0.01, n),
                         rng.normal(0, 0.5, (n, 3))])
    return pd.DataFrame({"t_s": t, "run": 1, "orientation": "z_up", "imu_temp_c": temp, "table_rate_dps": 0.0,
                         **{c: y[:, j] for j, c in enumerate(OUT)}})


MAIN_C = r"""
#include <stdio.h>
#include "cal.h"
int main(void) {
    double v[8];
    int first = 1;
    lr_temp_filter f;
    while (scanf("%lf %lf %lf %lf %lf %lf %lf %lf", &v[0], &v[1], &v[2], &v[3], &v[4], &v[5], &v[6], &v[7])
           == 8) {
        lr_real y[6], up[6], ur[6], temp;
        int k, fp, fr;
        for (k = 0; k < 6; ++k) y[k] = (lr_real)v[k];
        if (first) { lr_temp_filter_init(&f, (lr_real)v[6]); temp = f.y; first = 0; }
        else if (v[7] > 0) temp = lr_temp_filter_update_dt(&f, (lr_real)v[6], (lr_real)v[7]);
        else temp = lr_temp_filter_update(&f, (lr_real)v[6]);
        fp = lr_poly_compensate(y, temp, up);
        fr = lr_rbf_compensate(y, temp, ur);
        printf("%.17g ", (double)temp);
        for (k = 0; k < 6; ++k) printf("%.17g ", (double)up[k]);
        for (k = 0; k < 6; ++k) printf("%.17g ", (double)ur[k]);
        printf("%d %d\n", fp, fr);
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not available")
@pytest.mark.parametrize("irregular", [False, True])
def test_the_c_header_filter_matches_python_compensate_on_a_temperature_ramp(small_fit, tmp_path, irregular):
    filt = TemperatureFilter(tau_s=240.0, sample_period_s=1.0)
    frame = _ramp_frame(1.0, 6000, np.random.default_rng(1))
    dt = np.zeros(len(frame))
    if irregular:  # rows at irregular times: the firmware calls the update with each interval
        frame["t_s"] = np.cumsum(np.random.default_rng(2).uniform(0.2, 3.0, len(frame)))
        dt[1:] = np.diff(frame["t_s"].to_numpy())
    write_c_header(tmp_path / "cal.h", small_fit.polynomial, small_fit.rbf, temperature_filter=filt)
    save_model(small_fit.polynomial, tmp_path / "polynomial.json", temperature_filter=filt)
    save_model(small_fit.rbf, tmp_path / "rbf.json", temperature_filter=filt)
    (tmp_path / "main.c").write_text(MAIN_C)
    y = frame[OUT].to_numpy()
    text = "\n".join(" ".join(repr(float(v)) for v in (*r, tc, d))
                     for r, tc, d in zip(y, frame.imu_temp_c, dt, strict=True)) + "\n"
    poly = compensate_data(read_model(tmp_path / "polynomial.json"), frame).frame
    rbf = compensate_data(read_model(tmp_path / "rbf.json"), frame).frame
    want_temp = first_order_lag(frame.t_s.to_numpy(), frame.imu_temp_c.to_numpy(), 240.0)
    assert np.abs(want_temp - frame.imu_temp_c.to_numpy()).max() > 0.5  # the lag matters here
    # compensate's temperature is the filter's: the same model at the filtered temperature.
    assert np.allclose(poly[[c + "_comp" for c in OUT]].to_numpy(),
                       compensate(small_fit.polynomial, y, want_temp).values, atol=1e-12)
    for flags, tol_temp, tol_out in (("-DLR_USE_DOUBLE", 1e-9, 1e-9), ("", 2e-4, 2e-5)):
        exe = tmp_path / f"cal{flags or '_float'}"
        subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", *([flags] if flags else []),
                        "-o", str(exe), str(tmp_path / "main.c"), "-lm"], check=True)
        out = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=True).stdout
        arr = np.array([[float(x) for x in line.split()] for line in out.strip().splitlines()])
        assert arr.shape == (len(frame), 15)
        assert np.abs(arr[:, 0] - want_temp).max() < tol_temp, flags
        assert np.abs(arr[:, 1:7] - poly[[c + "_comp" for c in OUT]].to_numpy()).max() < tol_out * 10, flags
        assert np.abs(arr[:, 7:13] - rbf[[c + "_comp" for c in OUT]].to_numpy()).max() < tol_out * 10, flags
        assert np.array_equal(arr[:, 13].astype(bool), poly.extrapolated.to_numpy().astype(bool)) or flags == ""


def test_a_model_file_without_a_filter_compensates_at_the_logged_temperature(small_fit, tmp_path):
    frame = _ramp_frame(1.0, 500, np.random.default_rng(3))
    save_model(small_fit.polynomial, tmp_path / "p.json")
    out = compensate_data(read_model(tmp_path / "p.json"), frame).frame
    want = compensate(small_fit.polynomial, frame[OUT].to_numpy(), frame.imu_temp_c.to_numpy()).values
    assert np.allclose(out[[c + "_comp" for c in OUT]].to_numpy(), want, atol=1e-12)


def test_a_bad_filter_in_a_model_file_is_one_located_line(small_fit, tmp_path):
    save_model(small_fit.polynomial, tmp_path / "p.json", temperature_filter=TemperatureFilter(240.0, 1.0))
    d = json.loads((tmp_path / "p.json").read_text())
    d["model"]["temperature_filter"]["tau_s"] = -3
    (tmp_path / "p.json").write_text(json.dumps(d))
    with pytest.raises(UserError, match="p.json: the model is incomplete or malformed.*tau_s"):
        read_model(tmp_path / "p.json")


@pytest.mark.parametrize("bad", [0.0, -5.0, float("nan"), "soon", True])
def test_the_fit_option_is_validated(bad):
    with pytest.raises(UserError, match="thermal lag must be"):
        FitOptions(thermal_lag_s=bad)


# --- a hidden lag in generated ramp data -------------------------------------------------------------

ROW_S = 1.0  # rows: means of 50 samples at 50 Hz
RAMP_C_PER_MIN = 0.33
RATES = (-50.0, 0.0, 50.0)  # one 10 s record at each, repeated along the ramp


def _imu(tau_s: float | None):
    from labrunner.imu.model import default_imu_model

    model = default_imu_model(seed=4)
    return model if tau_s is None else model.with_effects(thermal_lag={"tau_s": tau_s})


def _rows(model, t, temp, orient_index, rate, run, rng) -> pd.DataFrame:
    from labrunner.domain import ORIENTATIONS, UP_VECTORS
    from labrunner.imu.inputs import ImuInputs

    up = UP_VECTORS[orient_index]
    inputs = ImuInputs(t_s=t, run=np.full(t.size, run), t_on_s=t - t[0] + 3600.0, temp_c=temp,
                       force_g=np.tile(up, (t.size, 1)), rate_dps=up[None, :] * rate[:, None])
    err, _ = model.deterministic_error(inputs)
    truth = np.concatenate([inputs.force_g, inputs.rate_dps], axis=1)
    y = truth + err + rng.standard_normal(err.shape) * model.noise_sigma(50.0) / np.sqrt(ROW_S * 50.0)
    return pd.DataFrame({"t_s": t, "run": run, "orientation": ORIENTATIONS[orient_index], "chamber_c": np.nan,
                         "imu_temp_c": np.round(temp + rng.normal(0, 0.005, t.size), 3), "table_rate_dps": rate,
                         **{c: y[:, j] for j, c in enumerate(OUT)}})


def ramp_log(tau_s: float | None, seed: int = 0, lo_c: float = -10.0, hi_c: float = 30.0) -> pd.DataFrame:
    """Six orientations, each one power-on: 20 min soaked at the start, then a ramp at 0.33 C/min (heating,
    then cooling for the next orientation: serpentine) with the rate schedule repeated along it."""
    rng = np.random.default_rng(seed)
    model = _imu(tau_s)
    chunks, t0 = [], 0.0
    for oi in range(6):
        start, stop = (lo_c, hi_c) if oi % 2 == 0 else (hi_c, lo_c)
        dur = 1200.0 + abs(stop - start) / RAMP_C_PER_MIN * 60.0
        t = t0 + np.arange(0.0, dur, ROW_S)
        moved = np.clip((t - t0 - 1200.0) * RAMP_C_PER_MIN / 60.0, 0.0, None)
        temp = start + np.sign(stop - start) * moved
        rate = np.asarray(RATES)[((t - t0) // 10.0).astype(int) % len(RATES)]
        chunks.append(_rows(model, t, temp, oi, rate, oi + 1, rng))
        t0 = t[-1] + 1800.0
    return pd.concat(chunks, ignore_index=True)


def soaked_errors(model_file, tau_s: float, temps=(-5.5, 4.5, 14.5, 24.5)) -> np.ndarray:
    """(records, 6) mean errors of the model file on held-out soaks between the ramp's bins (settled), in one
    power-on: each model's mean error over them (the turn-on bias, which no calibration knows) removed."""
    from labrunner.calibration.records import reference_values

    rng = np.random.default_rng(99)
    model = _imu(tau_s)
    out = []
    for k, temp in enumerate(temps):
        for oi in range(6):
            for rate in RATES:
                t = 1e6 + 1e4 * (k * 18 + oi * 3 + RATES.index(rate)) + np.arange(0.0, 60.0, ROW_S)
                f = _rows(model, t, np.full(t.size, temp), oi, np.full(t.size, rate), 100, rng)
                comp = compensate_data(model_file, f).frame[[c + "_comp" for c in OUT]].to_numpy()
                out.append((comp - reference_values(np.full(t.size, oi), f.table_rate_dps.to_numpy())).mean(axis=0))
    return np.array(out) - np.mean(out, axis=0)


@pytest.fixture(scope="module")
def hidden_lag_fits(tmp_path_factory):
    from labrunner.calibration.outputs import write_outputs

    tau = 300.0  # hidden in the data: the analysis gets the rows only
    frame = ramp_log(tau)
    opt = dict(rbf_variants=(), rbf_export="", splits=("between_temperatures", "random"))
    plain = fit_campaign(frame, FitOptions(**opt))
    auto = fit_campaign(frame, FitOptions(**opt, thermal_lag_s="auto"))
    out = tmp_path_factory.mktemp("lagfit")
    write_outputs(plain, out / "plain")
    write_outputs(auto, out / "auto")
    return tau, plain, auto, out


def test_a_hidden_lag_is_recovered_and_the_lag_corrected_fit_beats_the_plain_one_held_out(hidden_lag_fits):
    tau, plain, auto, out = hidden_lag_fits
    rep = auto.thermal_lag
    assert rep is not None and rep.source == "auto"
    assert rep.tau_s == pytest.approx(tau, rel=0.25), rep.search
    assert rep.used and rep.ratio is not None and rep.ratio < 1.0, rep.to_dict()
    doc = auto.to_dict()
    assert doc["thermal_lag"]["used"] and doc["models"]["polynomial"]["temperature_filter"]["tau_s"] == rep.tau_s
    assert "thermal lag tau" in " ".join(doc["notes"])
    # The exported files carry the filter; held-out soaks (settled: no lag) judge both models.
    lagged_file = read_model(out / "auto" / "polynomial.json")
    assert lagged_file.temperature_filter is not None and lagged_file.temperature_filter.tau_s == rep.tau_s
    assert read_model(out / "plain" / "polynomial.json").temperature_filter is None
    assert "temp_filter_update" in (out / "auto" / "imu_calibration.h").read_text()
    e_plain = soaked_errors(read_model(out / "plain" / "polynomial.json"), tau)
    e_lag = soaked_errors(lagged_file, tau)
    rms = lambda e: np.sqrt(np.mean(e ** 2, axis=0))  # noqa: E731
    acc_p, acc_l = np.sqrt(np.mean(rms(e_plain)[:3] ** 2)), np.sqrt(np.mean(rms(e_lag)[:3] ** 2))
    gyr_p, gyr_l = np.sqrt(np.mean(rms(e_plain)[3:] ** 2)), np.sqrt(np.mean(rms(e_lag)[3:] ** 2))
    assert acc_l < 0.7 * acc_p and gyr_l < 0.7 * gyr_p, (acc_p, acc_l, gyr_p, gyr_l)


def test_without_a_lag_the_search_finds_none_worth_using():
    frame = ramp_log(None, seed=1, lo_c=0.0, hi_c=30.0)
    res = fit_campaign(frame, FitOptions(rbf_variants=(), rbf_export="", splits=("between_temperatures",),
                                         thermal_lag_s="auto"))
    rep = res.thermal_lag
    assert rep is not None
    assert rep.tau_s < 30.0 or not rep.used, rep.to_dict()
    assert res.temperature_filter is None or rep.tau_s < 30.0


def _move_and_soak(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A sensor moved between soaks (1 s rows, the whole history) and which rows a log of records keeps:
    three 60 s records at the end of each soak, nothing while the chamber moves and the IMU settles."""
    t = np.arange(0.0, 6 * 7200.0, 1.0)
    setpoints = np.array([-20.0, -5.0, 10.0, 25.0, 40.0, 55.0])
    k = (t // 7200).astype(int)
    since = t - 7200.0 * k
    prev = np.concatenate(([setpoints[0]], setpoints[:-1]))[k]
    sensor = setpoints[k] + (prev - setpoints[k]) * np.exp(-since / 600.0)  # the case approaches its setpoint
    sensor += rng.normal(0.0, 0.002, t.size)
    logged = since >= 7200.0 - 3 * 70.0
    logged &= (since % 70.0) < 60.0  # 10 s of table settling between the records, unlogged
    return t, sensor, logged


def test_a_log_of_soaked_records_is_not_bridged_by_a_line_across_the_unlogged_moves():
    t, sensor, logged = _move_and_soak(np.random.default_rng(4))
    element = first_order_lag(t, sensor, 240.0)  # what the element did: the filter through the whole history
    got = lag_corrected_temperature(t[logged], sensor[logged], None, 240.0)
    # A line across the 2 h moves puts the first record of every soak ~0.5 C behind its soaked sensor.
    bridged = first_order_lag(t[logged], sensor[logged], 240.0)
    assert np.abs(bridged - element[logged]).max() > 0.3
    assert np.abs(got - element[logged]).max() < 0.01


def test_a_ramp_logged_with_gaps_keeps_its_lag_across_long_gaps_too():
    t = np.arange(0.0, 20000.0, 1.0)
    temp = -10.0 + 0.33 / 60.0 * t
    element = first_order_lag(t, temp, 240.0)
    for gap_s in (7.0, 600.0):  # gaps shorter than tau are bridged; longer ones restart on the ramp's slope
        logged = (t % (10.0 + gap_s)) < 10.0
        got = lag_corrected_temperature(t[logged], temp[logged], None, 240.0)
        late = t[logged] > 2400.0  # the element settled on the slope (10 tau)
        assert np.abs(got - element[logged])[late].max() < 1e-3, gap_s
        assert np.abs(got - (temp[logged] - 0.33 / 60.0 * 240.0))[late].max() < 1e-3, gap_s
