"""The simulated lab's IMU output is the IMU model's, sample by sample, on a ramp with a thermal lag.

A ramp dry run through the real protocols (chamber, table, IMU frames, driver, store) on an IMU whose
element lags its temperature sensor by 240 s, with a non-cubic step on accel z. What the world fed the
model (true sensor temperature, force, rate, per chunk) is recorded; the model is then run once over the
whole history, without the per-chunk state the stream carries, and compared with what the store holds:
the logged temperature, the record means of every channel (within the white noise) and the element
temperature the fit's lag correction makes from the logged rows. A lag state restarted per chunk or per
record, a time base off between chunks or a temperature logged other than the one that drives the
errors would show here as the direction-dependent accel z error of a ramp (slope x rate x tau, ~4 mg).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from labrunner.calibration.thermal_lag_fit import lag_corrected_temperature
from labrunner.data_source import load_campaign_data
from labrunner.sims.world import SimLabConfig

from .sim_truth import dry_run_with_truth
from .test_ramp_campaign import RAMP

EFFECTS = {"thermal_lag": {"tau_s": 240.0},
           "temperature_nonlinearity": {"amplitude": {"accel_z": 0.004, "gyro_z": 0.08}, "center_c": 20.0,
                                        "width_c": 3.0}}
OUT = ["ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps"]


def test_the_stored_ramp_is_the_model_run_once_over_the_true_inputs(tmp_path, monkeypatch):
    proc, sim, db = tmp_path / "ramp.yaml", tmp_path / "sim.json", tmp_path / "r.db"
    proc.write_text(RAMP.replace("stop_c: 25", "stop_c: 35"))  # 40 min per orientation: 10 tau
    sim.write_text(json.dumps({"seed": 5, "imu_model": {"effects": EFFECTS}}))
    truth = dry_run_with_truth(monkeypatch, proc, sim, db, 5)
    assert np.all(np.diff(truth.t_s) > 0)  # each sample generated once, in time order
    model = SimLabConfig.from_dict(json.loads(sim.read_text())).imu_model
    direct = np.concatenate([truth.force_g, truth.rate_dps], axis=1) + model.deterministic_error(truth)[0]
    element = model.element_temperature(truth)

    frame = load_campaign_data(db).frame
    t = frame.t_s.to_numpy()
    j = np.searchsorted(truth.t_s, t - 1e-6)
    assert np.abs(truth.t_s[j] - t).max() < 1e-6  # every stored sample is one the world generated, at its time
    assert np.abs(frame.imu_temp_c.to_numpy() - truth.temp_c[j]).max() <= 0.0051  # the frame's 0.01 C LSB
    # The ramp's lag is there to be found: on the ramp the element falls behind its sensor towards
    # 0.5 C/min x 240 s = 2 C (the case reaches the slope only ~10 min in: it lags the air by 600 s).
    lag = element[j] - truth.temp_c[j]
    for o, sign in (("z_up", -1.0), ("z_down", 1.0)):
        assert np.max(sign * lag[(frame.orientation == o).to_numpy()]) > 1.2

    # Record means of every channel agree within the noise (5 sigma of a record's mean).
    sigma = model.noise_sigma(50.0)
    resid = frame[OUT].to_numpy() - direct[j]
    cuts = np.flatnonzero(np.diff(t) > 1.0) + 1
    starts, ends = np.r_[0, cuts], np.r_[cuts, t.size]
    assert starts.size > 100
    for a, b in zip(starts, ends, strict=True):
        mean = resid[a:b].mean(axis=0)
        assert np.all(np.abs(mean) < 5 * sigma / np.sqrt(b - a)), (t[a], frame.orientation.iloc[a], mean)

    # The fit's lag correction of the logged rows gives the element the model drove the errors with
    # (after 5 tau from a run's start, where the correction starts settled and the element may not).
    corrected = lag_corrected_temperature(t, frame.imu_temp_c.to_numpy(), frame.run.to_numpy(), 240.0)
    run = frame.run.to_numpy()
    settled = np.concatenate([t[run == r] - t[run == r][0] > 1200.0 for r in np.unique(run)])
    assert settled.sum() > t.size / 3
    assert np.abs(corrected - element[j])[settled].max() < 0.01


@pytest.mark.parametrize("n", [1])
def test_the_comparison_sees_a_lag_restarted_at_every_chunk(tmp_path, monkeypatch, n):
    """The check above is not blind: a stream that forgets its lag state at each chunk fails it."""
    from labrunner.sims import imu_stream

    real_next = imu_stream.ImuStreamSim._next_chunk

    def forgetful(self, t):
        self.state = imu_stream.ModelState()
        return real_next(self, t)

    monkeypatch.setattr(imu_stream.ImuStreamSim, "_next_chunk", forgetful)
    with pytest.raises(AssertionError):
        test_the_stored_ramp_is_the_model_run_once_over_the_true_inputs(tmp_path, monkeypatch)
