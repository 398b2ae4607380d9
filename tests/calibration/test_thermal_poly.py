"""Thermal polynomial: recovery of the simulator's cubic truth within the stated uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.calibration.records import segment_records, temperature_steps
from labrunner.calibration.six_position import calibrate_steps
from labrunner.calibration.thermal_poly import cv_order, fit_joint, fit_two_stage, record_prediction
from labrunner.imu.model import default_imu_model


@pytest.fixture(scope="module")
def recs(cubic_campaign):
    r = segment_records(cubic_campaign)
    steps = temperature_steps(r)
    return r, steps


@pytest.mark.parametrize("triad", ["accel", "gyro"])
def test_joint_fit_recovers_true_coefficients_within_uncertainty(recs, triad):
    records, _ = recs
    truth = getattr(default_imu_model(), triad).coefficients()  # (3, 16), basis (T - 25)^k
    model = fit_joint(records, triad, order=3, t_ref_c=25.0)
    z = (model.coefficients() - truth) / model.coefficient_std()
    assert np.all(np.isfinite(z))
    # Every bias/scale coefficient within 3 sigma but for the odd chance outlier among 48 ...
    assert np.mean(np.abs(z) < 3.0) >= 0.95, np.round(z, 1)
    assert np.all(np.abs(z) < 4.5), np.round(z, 1)
    # ... and the stated uncertainties are honest: neither inflated nor too small.
    assert 0.6 < np.sqrt(np.mean(z ** 2)) < 1.5


def test_two_stage_is_biased_by_orientation_temperature_differences(recs):
    """The paper's two-stage fit folds the up/down temperature difference into the scale estimates."""
    records, steps = recs
    truth = default_imu_model().accel.coefficients()
    two = fit_two_stage(calibrate_steps(records, steps)["accel"], order=3)
    z_two = (two.coefficients() - truth) / two.coefficient_std()
    joint = fit_joint(records, "accel", 3)
    err_two = np.abs(two.coefficients() - truth)
    err_joint = np.abs(joint.coefficients() - truth)
    assert np.abs(z_two).max() > 5  # the two-stage estimate misses by many of its own sigmas
    assert np.median(err_joint[:, 4:]) < np.median(err_two[:, 4:])  # scale/misalignment coefficients


def test_cross_validation_picks_the_true_order(recs):
    records, steps = recs
    for triad in ("accel", "gyro"):
        order, scores = cv_order(records, steps, triad, 5, "joint")
        assert order == 3, scores
        assert scores[2] > 10 * scores[3]  # a quadratic misses the cubic clearly


def test_model_predicts_record_means_to_noise_level(recs):
    records, _ = recs
    model = fit_joint(records, "gyro", 3)
    res = record_prediction(model, records) - records.mean[:, 3:]
    noise = np.nanmedian(records.sem[:, 3:], axis=0)
    assert np.all(np.sqrt(np.mean(res ** 2, axis=0)) < 1.5 * noise)
    assert model.t_min_c == pytest.approx(records.temp_c.min())
    assert model.t_max_c == pytest.approx(records.temp_c.max())
