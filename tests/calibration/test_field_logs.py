"""Calibration on data unlike the simulator's: static field logs (field_logs.py) and what a fit must do with them.

The fit gets only the rows; the truth stays here. Each test names the outcome a user flashing the model
into a microcontroller needs: steps found on slow ramps, the identifiable combinations fitted (not the
identity), signal passed with the fitted gain, and no worse than PX4's method on held-out hours.
"""

from __future__ import annotations

import numpy as np
import pytest
from field_logs import field_log

from labrunner.calibration.compensation import compensate
from labrunner.calibration.evaluation import time_blocks
from labrunner.calibration.fit import FitOptions, fit_campaign
from labrunner.calibration.records import segment_records
from labrunner.campaign_csv import read_campaign

STEPS = {"accel": (0, 0.05), "gyro": (3, 5.0)}  # channel and step added: 0.05 g, 5 deg/s


@pytest.fixture(scope="module")
def log() -> tuple:
    frame, truth = field_log(seed=0)
    return read_campaign(frame), truth


@pytest.fixture(scope="module")
def held_out_fit(log):
    """Fitted on the rows outside the time_blocks split's held-out hours; those rows returned apart."""
    frame, _ = log
    rec = segment_records(frame)
    held, _why = time_blocks(rec)
    assert held is not None
    test_rows = held[np.maximum(rec.row_record, 0)] & (rec.row_record >= 0)
    train = frame[~test_rows].reset_index(drop=True)
    result = fit_campaign(train, FitOptions(evaluate=False))
    return result, frame[test_rows].reset_index(drop=True)


def test_slow_ramps_give_temperature_steps_and_a_network_temperature_width(held_out_fit):
    result, _ = held_out_fit
    steps = result.data_summary["temperature_steps"]
    assert len(steps) >= 15  # 5..24 C in bins of <= 1 C, not "one temperature only"
    assert not any("one temperature" in n for n in result.notes)
    net = result.models.rbf["hybrid"].networks[0]
    assert net.width[-1] * net.in_scale[-1] >= 0.5  # the temperature width floor: the bins' spacing, not 0
    assert result.polynomial.accel.order == 3 and result.polynomial.gyro.order == 3


def test_no_axis_up_and_down_fits_the_combinations_and_says_for_which_use(held_out_fit):
    result, test = held_out_fit
    assert result.combined and "x_down, y_down, z_down" in result.combined[0] and "Valid for" in result.combined[0]
    text = "\n".join(result.to_dict()["provenance"]["combined"])
    assert "not a separation of bias from scale factor" in text
    # compensated with it, not with the identity: on held-out hours the thermal drift is mostly gone
    y = test[["ax_g", "ay_g", "az_g"]].to_numpy()
    comp = compensate(result.polynomial, test[list(test.columns[6:])].to_numpy(), test["imu_temp_c"].to_numpy())
    assert not np.allclose(comp.values[:, :3], y)
    var_raw = var_comp = 0.0
    for run in np.unique(test["run"]):  # the spread over each power-on's held-out hours (its level aside)
        sel = test["run"].to_numpy() == run
        var_raw += float(np.sum(y[sel].var(axis=0)))
        var_comp += float(np.sum(comp.values[sel, :3].var(axis=0)))
    assert var_comp < 0.3 * var_raw, (var_comp, var_raw)


def _step_gains(model, frame, fitted) -> dict[str, float]:
    y = frame[["ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps"]].to_numpy()
    temp = frame["imu_temp_c"].to_numpy()
    base = compensate(model, y, temp).values
    out = {}
    for triad, (ch, step) in STEPS.items():
        for k in range(ch, ch + 3):
            moved = y.copy()
            moved[:, k] += step
            gain = (compensate(model, moved, temp).values[:, k] - base[:, k]) / step
            tp = getattr(fitted, triad)
            s = tp.scale_at(temp)[:, k - ch, k - ch]
            out[f"{triad}_{'xyz'[k - ch]}"] = float(np.max(np.abs(gain * (1 + s) - 1)))
    return out


def test_steps_added_to_held_out_rows_pass_with_the_fitted_gain(held_out_fit, cubic_campaign, nonlinear_campaign):
    result, test = held_out_fit
    exported = [result.polynomial] + ([result.rbf] if result.rbf is not None else [])
    assert result.rbf is not None and result.rbf.variant == "hybrid"
    for model in exported:
        assert max(_step_gains(model, test, result.polynomial).values()) < 0.01
    # the paper's network (raw outputs in) is kept as the paper's variant, with its gain measured and reported
    paper = result.gains["rbf_paper"]
    assert not paper.passed and paper.max_departure > 0.05
    # and on the rotating campaigns as the simulator makes them (the non-cubic one gives the networks work)
    rng = np.random.default_rng(5)
    for campaign in (cubic_campaign, nonlinear_campaign):
        held = rng.random(len(campaign)) < 0.2
        rot = fit_campaign(campaign[~held].reset_index(drop=True), FitOptions(evaluate=False))
        assert rot.rbf is not None and rot.gains["rbf_hybrid"].passed and rot.gains["polynomial"].passed
        for model in (rot.polynomial, rot.rbf):
            assert max(_step_gains(model, campaign[held], rot.polynomial).values()) < 0.01
    assert sum(n.n_centres for n in rot.rbf.networks) > 0  # the check saw networks that do something


def test_exported_model_no_worse_than_px4_on_held_out_hours(log):
    frame, _ = log
    result = fit_campaign(frame, FitOptions(splits=("time_blocks",)))
    split = result.evaluation[0]
    assert not split.skipped and "h held out" in split.description
    exported = f"rbf_{result.rbf.variant}" if result.rbf is not None else "polynomial"
    ours, px4 = split.samples[exported].rms, split.samples["px4"].rms
    assert np.all(ours <= px4), (ours, px4)
    assert np.all(px4 < split.samples["raw"].rms)  # the reference itself works on these data


def test_fit_command_on_a_field_log_csv(tmp_path, capsys):
    """The user's path: the log as a CSV file (no chamber column values), `labrunner fit --out`."""
    from field_logs import write_field_log

    from labrunner.cli import main

    csv = tmp_path / "log.csv"
    write_field_log(str(csv), seed=1, hours_per_run=8.0)
    out = tmp_path / "fit"
    assert main(["fit", str(csv), "--out", str(out), "--splits", "time_blocks", "--quiet"]) == 0
    summary = capsys.readouterr().out
    assert "**Fitted in combination:** accel:" in summary and "one temperature" not in summary
    assert "| px4 " in summary and "Gain of each model" in summary
    header = (out / "imu_calibration.h").read_text()
    assert "fitted in combination: accel:" in header and "campaign CSV: steps planned unknown" in header
    assert (out / "rbf.json").exists() and "lr_rbf_compensate" in header  # the hybrid passes its gain check
