"""Calibrating per hysteresis branch (labrunner.calibration.branch_fit, issue 11 item 6): the branch state
under jitter and quantisation, the per-branch fit's held-out gain on log-like data with a hidden hysteresis
and its absence without one, and the exported branch (model JSON, `labrunner compensate`, the C header
compiled with gcc)."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pandas as pd
import pytest

from labrunner.calibration import compensate
from labrunner.calibration.apply import compensate_data, read_model
from labrunner.calibration.branch_fit import BranchModel, BranchState, estimate_state
from labrunner.calibration.export import save_model, write_c_header
from labrunner.calibration.fit import FitOptions, fit_campaign
from labrunner.domain import CHANNELS
from labrunner.errors import UserError
from tests.discrepancy.log_like import log_like  # the diagnosis's log-like logs (not the simulator's)

OUT = ["ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps"]
HYSTERESIS = {"accel_y": 1.0e-3, "gyro_z": 0.08}  # as the diagnosis's log-like hysteresis test hides
POLY_ONLY = {"rbf_variants": (), "rbf_export": ""}


def _path(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A true temperature path at 1 Hz (soaks joined by 0.3-0.6 C/min ramps, up and down) and its direction
    latched: +1 after heating, -1 after cooling, 0 before the first ramp."""
    levels = [23.0, 40.0, 10.0, 30.0, -5.0, 15.0, 50.0, 20.0]
    temp, direction = [np.full(1800, levels[0])], [np.zeros(1800)]
    for a, b in zip(levels[:-1], levels[1:], strict=True):
        rate = rng.uniform(0.3, 0.6) / 60.0
        n = int(abs(b - a) / rate)
        temp += [np.linspace(a, b, n), np.full(3600, b)]
        direction += [np.full(n + 3600, np.sign(b - a))]
    return np.concatenate(temp), np.concatenate(direction)


@pytest.mark.parametrize("jitter", [0.0, 0.01, 0.05])
def test_the_branch_state_follows_heating_and_cooling_under_jitter_and_quantisation(jitter):
    rng = np.random.default_rng(3)
    true, direction = _path(rng)
    logged = np.round((true + rng.normal(0.0, jitter, true.size)) / 0.0625) * 0.0625 if jitter else \
        np.round(true / 0.0625) * 0.0625
    t = np.arange(true.size, dtype=float)
    frame = pd.DataFrame({"t_s": t, "run": 1, "imu_temp_c": logged})
    state = estimate_state(frame)
    s = state.states(t, logged, np.ones(t.size, dtype=int))
    # No chatter: the state changes at the first ramp and at each reversal of the path (7 ramps, two in a row
    # heating: 6 changes), and agrees with the true direction except while a ramp starts (the filter needs a
    # minute or two to see it).
    assert int(np.sum(np.diff(s) != 0)) == 6
    assert np.mean(s == direction) > 0.97
    assert 10.0 <= state.filter_tau_s <= 600.0 and 0.05 / 60 < state.threshold_c_per_s < 0.2 / 60


@pytest.fixture(scope="module")
def hysteresis_fit():
    frame, _ = log_like(5, 48, hysteresis=HYSTERESIS, jitter_c=0.03)
    return frame, fit_campaign(frame, FitOptions(branch_fit=True, **POLY_ONLY))


def test_a_hidden_hysteresis_is_fitted_per_branch_and_gains_on_held_out_records(hysteresis_fit):
    frame, result = hysteresis_fit
    report = result.branch
    assert report is not None and report.used
    assert set(HYSTERESIS) <= set(report.used_channels), report.sentence()
    for c, w in HYSTERESIS.items():
        assert report.widths[c] == pytest.approx(w, rel=0.2), c
        # Judged on records held out of the width's and the polynomial's fit: a large gain on every split.
        assert report.comparison.ratio[c] < 0.75, c
        assert all(sp[c]["branch"] < sp[c]["plain"] for sp in report.comparison.heldout.values()), c
    assert set(report.comparison.heldout) == {"time_blocks", "between_temperatures"}
    model = result.branch_model
    assert model is not None
    assert all((w != 0.0) == (c in report.used_channels) for c, w in zip(CHANNELS, model.widths, strict=True))
    # The exported models carry it, and the fit's own evaluation (refitted per split on the corrected rows)
    # ran on the per-branch fit.
    assert result.model_dicts()["polynomial"]["branch_state"]["width"]["gyro_z"] == pytest.approx(
        report.widths["gyro_z"])
    assert result.to_dict()["branch"]["used_channels"] == list(report.used_channels)
    assert any("hysteresis per branch" in n and "used for" in n for n in result.notes)
    assert result.evaluation and not result.evaluation[0].skipped


@pytest.mark.parametrize("slow_noise", [True, False])
def test_without_hysteresis_the_branch_fit_is_not_used(slow_noise):
    """Seed 8's log-like slow noise (flicker and a random walk) gives one channel a chance gain of 7 %, below
    the 15 % the branch must earn; white noise alone gives none."""
    quiet = {} if slow_noise else {"bias_instability": {c: 0.0 for c in CHANNELS},
                                   "rate_random_walk": {c: 0.0 for c in CHANNELS}}
    frame, _ = log_like(8, 48, jitter_c=0.03, **quiet)
    result = fit_campaign(frame, FitOptions(branch_fit=True, evaluate=False, **POLY_ONLY))
    report = result.branch
    assert report is not None and not report.used, report.sentence()
    assert result.branch_model is None and "branch_state" not in result.model_dicts()["polynomial"]
    assert len(report.comparison.heldout) == 2
    if not slow_noise:  # no gain at all: the width fitted on the training part only adds noise
        assert min(report.comparison.ratio.values()) > 0.97, report.comparison.ratio


MAIN_C = r"""
#include <stdio.h>
#include "cal.h"
int main(void) {
    double v[9], run = -1;
    lr_branch b = {0, 0, 0};
    while (scanf("%lf %lf %lf %lf %lf %lf %lf %lf %lf", &v[0], &v[1], &v[2], &v[3], &v[4], &v[5], &v[6], &v[7],
                 &v[8]) == 9) {
        lr_real y[6], yc[6], u[6];
        int k, s;
        for (k = 0; k < 6; ++k) y[k] = (lr_real)v[k];
        if (v[8] != run) { lr_branch_init(&b, (lr_real)v[6]); s = b.s; run = v[8]; }  /* power-on */
        else if (v[7] > 0) s = lr_branch_update_dt(&b, (lr_real)v[6], (lr_real)v[7]);
        else s = lr_branch_update(&b, (lr_real)v[6]);
        lr_branch_correct(y, s, yc);
        lr_poly_compensate(yc, (lr_real)v[6], u);
        printf("%d ", s);
        for (k = 0; k < 6; ++k) printf("%.17g ", (double)u[k]);
        printf("\n");
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc not available")
@pytest.mark.parametrize("irregular", [False, True])
def test_compensate_and_the_c_header_apply_the_same_branch(hysteresis_fit, tmp_path, irregular):
    frame, result = hysteresis_fit
    model = result.branch_model
    assert model is not None
    rows = frame.iloc[:40000].reset_index(drop=True)  # one orientation, two power-ons: heating and cooling
    assert rows.run.nunique() == 2
    dt = np.zeros(len(rows))
    if irregular:  # rows at irregular times: the firmware calls the update with each interval
        rows["t_s"] = np.cumsum(np.random.default_rng(2).uniform(0.5, 1.5, len(rows)))
        dt[1:] = np.diff(rows["t_s"].to_numpy())
    save_model(result.polynomial, tmp_path / "polynomial.json", branch=model)
    write_c_header(tmp_path / "cal.h", result.polynomial, None, branch=model)
    loaded = read_model(tmp_path / "polynomial.json")
    assert loaded.branch == model
    comp = compensate_data(loaded, rows).frame
    s = model.state.states(rows.t_s.to_numpy(), rows.imu_temp_c.to_numpy(), rows.run.to_numpy(),
                           rows.orientation.astype(str).to_numpy())
    assert np.sum(s > 0) > 5000 and np.sum(s < 0) > 5000
    y = rows[OUT].to_numpy()
    want = compensate(result.polynomial, model.correct(y, s), rows.imu_temp_c.to_numpy()).values
    assert np.allclose(comp[[c + "_comp" for c in OUT]].to_numpy(), want, atol=1e-12)
    (tmp_path / "main.c").write_text(MAIN_C)
    text = "\n".join(" ".join(repr(float(v)) for v in (*r, tc, d, run))
                     for r, tc, d, run in zip(y, rows.imu_temp_c, dt, rows.run, strict=True)) + "\n"
    for flags, share in (("-DLR_USE_DOUBLE", 1.0), ("", 0.999)):
        exe = tmp_path / f"cal{flags or '_float'}"
        subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", *([flags] if flags else []),
                        "-o", str(exe), str(tmp_path / "main.c"), "-lm"], check=True)
        out = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=True).stdout
        arr = np.array([[float(x) for x in line.split()] for line in out.strip().splitlines()])
        assert arr.shape == (len(rows), 7)
        same = arr[:, 0] == s  # single precision may decide a row at the threshold differently
        assert np.mean(same) >= share, flags
        assert np.abs(arr[same, 1:] - want[same]).max() < (1e-9 if flags else 2e-4), flags


def test_a_bad_branch_in_a_model_file_is_one_located_line(hysteresis_fit, tmp_path):
    _, result = hysteresis_fit
    model = result.branch_model
    assert model is not None
    save_model(result.polynomial, tmp_path / "p.json", branch=model)
    d = json.loads((tmp_path / "p.json").read_text())
    del d["model"]["branch_state"]["width"]["gyro_x"]
    (tmp_path / "p.json").write_text(json.dumps(d))
    with pytest.raises(UserError, match="p.json: the model is incomplete or malformed.*width must give every"):
        read_model(tmp_path / "p.json")
    d["model"]["branch_state"] = {**BranchModel(BranchState(60.0, 1e-3, 1.0), (0.0,) * 6).to_dict(),
                                  "filter_tau_s": -1}
    (tmp_path / "p.json").write_text(json.dumps(d))
    with pytest.raises(UserError, match="filter_tau_s must be > 0"):
        read_model(tmp_path / "p.json")
