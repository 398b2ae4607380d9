"""Degenerate campaigns: say what cannot be fitted, fit the rest."""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.calibration.compensation import compensate
from labrunner.calibration.fit import FitOptions, fit_campaign
from labrunner.errors import UserError
from labrunner.imu.model import default_imu_model

from calib_campaigns import make_campaign

FAST = FitOptions(rbf_variants=("paper",), rbf_export="paper", splits=("random",))
TEMPS = (-20.0, 0.0, 20.0, 40.0)


def _truth(triad):
    return getattr(default_imu_model(), triad)


def test_missing_one_orientation_still_fits_everything():
    frame = make_campaign(seed=31, temperatures_c=TEMPS, average_s=2.0,
                          orientations=("x_up", "x_down", "y_up", "y_down", "z_up"))
    res = fit_campaign(frame, FAST)
    assert res.not_fitted == []
    acc = res.polynomial.accel
    assert acc.fitted.all() and np.all(np.isfinite(acc.bias_std))
    # z bias and z scale are still separated (z_up vs the horizontal orientations)
    assert abs(acc.bias[2, 0] - _truth("accel").bias[2, 0]) < 5 * acc.bias_std[2, 0] + 1e-5


def test_only_three_orientations_names_the_accelerometer_terms_and_fits_the_gyro():
    frame = make_campaign(seed=32, temperatures_c=TEMPS, average_s=2.0, orientations=("x_up", "y_up", "z_up"))
    res = fit_campaign(frame, FAST)
    text = " ".join(res.not_fitted)
    assert "accel" in text and "bias x" in text and "scale factor z" in text and "cannot be fitted" in text
    acc = res.polynomial.accel
    assert not acc.fitted.any()  # no term is claimed as separately determined ...
    # ... but what the orientations determine is fitted and compensated, not left to the identity: each
    # axis's output in each orientation seen, as a function of temperature
    assert res.combined and "x_up, y_up, z_up" in res.combined[0] and "Valid for" in res.combined[0]
    assert res.to_dict()["models"]["polynomial"]["accel"]["combined"] == res.combined
    rec = res.records
    comp = compensate(res.polynomial, rec.mean, rec.temp_c).values[:, :3]
    raw_err = np.sqrt(np.mean((rec.mean[:, :3] - rec.reference[:, :3]) ** 2))
    err = np.sqrt(np.mean((comp - rec.reference[:, :3]) ** 2))
    assert err < 0.05 * raw_err, (err, raw_err)
    assert np.all(acc.residual_rms < 0.05 * raw_err)
    gyro = res.polynomial.gyro  # one orientation per axis and both rotation senses: fully identifiable
    assert gyro.fitted.all() and "gyro" not in text
    z = (gyro.coefficients() - _truth("gyro").coefficients()) / gyro.coefficient_std()
    assert np.mean(np.abs(z) < 3) > 0.9
    assert res.to_dict()["models"]["polynomial"]["accel"]["not_fitted"]


def test_single_temperature_fits_constants_and_says_so():
    frame = make_campaign(seed=33, temperatures_c=(25.0,), average_s=2.0)
    res = fit_campaign(frame, FitOptions(rbf_variants=("paper",), rbf_export="paper"))
    assert res.polynomial.accel.order == 0 and res.polynomial.gyro.order == 0
    assert any("order 0 at most" in n for n in res.notes)
    assert any("temperature" in s and "skipped" in s for s in res.not_fitted)  # no temperature hold-outs
    t = res.data_summary["temperature_steps"][0]["temp_c"]
    truth = _truth("gyro").bias_at(np.array([t]))[0]
    assert np.allclose(res.polynomial.gyro.bias[:, 0], truth, atol=5 * res.polynomial.gyro.bias_std[:, 0].max())
    assert any("one temperature" in n for n in res.notes)  # the networks cannot learn temperature either


def test_no_table_rotation_fits_gyro_bias_only():
    frame = make_campaign(seed=34, temperatures_c=TEMPS, average_s=2.0, table=False)
    res = fit_campaign(frame, FitOptions(rbf_variants=("paper",), rbf_export="paper",
                                         splits=("random", "between_rates")))
    text = " ".join(res.not_fitted)
    assert "gyro" in text and "no table rotation" in text and "scale factor x" in text
    gyro = res.polynomial.gyro
    assert gyro.fitted[:, 0].all() and not gyro.fitted[:, 1:].any()
    assert np.all(gyro.scale == 0)
    z = (gyro.bias - _truth("gyro").bias) / gyro.bias_std
    assert np.mean(np.abs(z) < 3) > 0.9
    assert res.polynomial.accel.fitted.all()  # the accelerometer is unaffected
    assert any("rate" in s and "skipped" in s for s in res.not_fitted)


def test_no_usable_records_is_a_user_error():
    frame = make_campaign(seed=35, temperatures_c=(20.0,), record_s=3.0, orientations=("z_up",), rates_dps=(10.0,))
    with pytest.raises(UserError, match="no stable records"):
        fit_campaign(frame, FAST)
