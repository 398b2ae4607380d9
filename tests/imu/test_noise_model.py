"""The simulator's noise model against the Allan deviation it is fitted with (issue 11, item 5).

The white noise density of `TriadModel` is one-sided: per-sample sigma = N sqrt(fs / 2), so a 1 s mean
of the samples has RMS N / sqrt(2) and the Allan deviation of such rows is N / sqrt(2 tau) -- the
IEEE angle random walk coefficient is N / sqrt(2), not N. Simulated with known parameters, the
model's noise must show that, and its bias instability the Allan variance `allan_variance` says.
"""

from __future__ import annotations

import allantools
import numpy as np

from labrunner.imu.effects.bias_instability import FLOOR, allan_variance
from labrunner.imu.inputs import ImuInputs
from labrunner.imu.model import default_imu_model


def _still(n: int, rate_hz: float) -> ImuInputs:
    t = np.arange(n) / rate_hz
    return ImuInputs(t_s=t, run=np.ones(n, dtype=np.int64), t_on_s=t, temp_c=np.full(n, 25.0),
                     force_g=np.tile([0.0, 0.0, 1.0], (n, 1)), rate_dps=np.zeros((n, 3)))


def test_white_noise_density_is_one_sided_allan_deviation_n_over_sqrt_2_tau():
    model = default_imu_model()
    rate = 50.0
    inputs = _still(int(8000 * rate), rate)
    out, _ = model.simulate(inputs, rate, np.random.default_rng(3))
    err = out - model.simulate(inputs, rate, None)[0]
    rows = err.reshape(-1, int(rate), 6).mean(axis=1)  # 1 s means, as a logger writes them
    taus = np.array([1.0, 2.0, 4.0, 8.0, 16.0])
    for i, density in enumerate([model.accel.noise_density] * 3 + [model.gyro.noise_density] * 3):
        _, adev, _, _ = allantools.oadev(rows[:, i], rate=1.0, data_type="freq", taus=taus)
        assert np.allclose(adev, density / np.sqrt(2.0 * taus), rtol=0.12), i
        assert abs(adev[0] / density - 1.0) > 0.25  # and not N / sqrt(tau): the factor sqrt(2) is there


def test_bias_instability_shows_its_allan_floor():
    b = 2e-3
    model = default_imu_model().with_effects(bias_instability={"b": {"gyro_x": b}})
    inputs = _still(400_000, 1.0)
    wander, _ = model.deterministic_error(inputs, rng=np.random.default_rng(5))
    wander -= model.deterministic_error(inputs)[0]
    taus = 2.0 ** np.arange(0, 13)
    _, adev, _, _ = allantools.oadev(wander[:, 3], rate=1.0, data_type="freq", taus=taus)
    assert np.allclose(adev, np.sqrt(allan_variance(taus, 1.0)) * b, rtol=0.15)
    mid = (taus >= 8) & (taus <= 2048)
    assert np.allclose(adev[mid], FLOOR * b, rtol=0.15)  # flat: flicker-like over these octaves
    assert np.all(wander[:, [0, 1, 2, 4, 5]] == 0)
