"""Six-position calibration (Eq. 2-3) at one temperature."""

from __future__ import annotations

import numpy as np

from labrunner.calibration.records import segment_records, temperature_steps
from labrunner.calibration.six_position import calibrate_steps, six_position
from labrunner.imu.model import ORIENTATIONS, UP_VECTORS, default_imu_model

from calib_campaigns import make_campaign


def test_least_squares_is_eq3_for_one_record_per_orientation():
    """With one record per orientation and equal weights the fit is E = Y U' (U U')^-1."""
    frame = make_campaign(seed=5, temperatures_c=(15.0,), rates_dps=(0.0,), record_s=10.0, table=False)
    rec = segment_records(frame)
    assert len(rec) == 6
    cal = six_position(rec, "accel")
    u = np.vstack([UP_VECTORS[rec.orientation].T, np.ones(6)])  # U (4 x 6), K = 1 g
    y = rec.mean[:, :3].T  # measurement matrix (3 x 6)
    e = y @ u.T @ np.linalg.inv(u @ u.T)  # [I + S | b]
    assert np.allclose(cal.scale, e[:, :3] - np.eye(3), atol=1e-12)
    assert np.allclose(cal.bias, e[:, 3], atol=1e-12)
    assert cal.orientations == list(ORIENTATIONS)


def test_gyro_uses_every_rate_and_recovers_truth_within_uncertainty():
    model = default_imu_model()
    frame = make_campaign(seed=6, temperatures_c=(15.0,), record_s=20.0, average_s=1.0)
    rec = segment_records(frame)
    steps = temperature_steps(rec)
    cal = calibrate_steps(rec, steps)
    assert len(cal["gyro"]) == 1
    g = cal["gyro"][0]
    assert g.n_records == len(rec) == 48  # 6 orientations x 8 rate steps
    # One temperature: the records are within ~0.2 C, so compare at their own temperatures
    t = g.temp_c
    zb = (g.bias - model.gyro.bias_at(np.array([t]))[0]) / g.bias_std
    zs = (g.scale - model.gyro.scale_at(np.array([t]))[0]) / g.scale_std
    assert np.all(np.abs(np.concatenate([zb, zs.ravel()])) < 4), (zb, zs)
    assert np.all(g.scale_std < 2e-4) and np.all(g.bias_std < 5e-3)
