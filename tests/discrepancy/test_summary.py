"""The store read in 1 s summaries: the statistics over the raw samples survive the averaging."""

import numpy as np
import pytest

from labrunner.discrepancy.measurements import Measurements
from labrunner.discrepancy.summary import (
    MAX_BINS_PER_BLOCK,
    channel_sample_rms,
    sample_rms,
    summarize_blocks,
    weighted_percentile,
)
from labrunner.store import SampleBlock


def _record(rng, t0, n, rate_hz=50.0, orientation="z_up", table=0.0, run=1, temp=20.0):
    up = {"z_up": np.array([0.0, 0.0, 1.0]), "x_down": np.array([-1.0, 0.0, 0.0])}[orientation]
    accel = up + 0.002 + rng.normal(0.0, 1e-3, (n, 3))
    gyro = up * table + 0.3 + rng.normal(0.0, 0.15, (n, 3))
    return SampleBlock(kind="record", step_idx=0, run=run, orientation=orientation, t0_s=t0, rate_hz=rate_hz,
                       counter=np.arange(n), accel_g=accel, gyro_dps=gyro,
                       temp_c=temp + 0.001 * np.arange(n) / rate_hz, chamber=np.array([[t0, temp]]),
                       table=np.array([[t0, table]]))


def _monitor(rng, t0, n, run=1):
    up = np.array([0.0, 0.0, 1.0])
    return SampleBlock(kind="monitor", step_idx=None, run=run, orientation="z_up", t0_s=t0, rate_hz=1.0,
                       counter=np.arange(n), accel_g=up + rng.normal(0.0, 1.4e-4, (n, 3)),
                       gyro_dps=0.3 + rng.normal(0.0, 0.02, (n, 3)), temp_c=np.linspace(20.0, 30.0, n),
                       chamber=np.zeros((0, 2)), table=np.zeros((0, 2)))


def test_summaries_keep_the_samples_statistics():
    rng = np.random.default_rng(3)
    blocks = [_record(rng, 0.0, 3000), _monitor(rng, 60.0, 300),
              _record(rng, 400.0, 3000, orientation="x_down", table=50.0)]
    frame, summary = summarize_blocks(blocks)
    assert len(frame) == 60 + 300 + 60
    assert summary.total_samples == 6300
    assert np.all(np.diff(frame["t_s"].to_numpy()) > 0)
    raw = np.concatenate([np.concatenate([b.accel_g, b.gyro_dps], axis=1) for b in blocks])
    ref = np.concatenate([np.tile(np.r_[0, 0, 1, 0, 0, 0], (3000, 1)), np.tile(np.r_[0, 0, 1, 0, 0, 0], (300, 1)),
                          np.tile(np.r_[-1, 0, 0, -50, 0, 0], (3000, 1))])
    error = raw - ref
    # Measured minus a model constant within each second: the RMS over the 6300 samples, exactly.
    model = np.array([0.002, 0.002, 0.002, 0.3, 0.3, 0.3])
    meas = Measurements.from_frame(frame, summary)
    rows_resid = meas.error - model
    np.testing.assert_allclose(sample_rms(meas.summary, rows_resid),
                               np.sqrt(np.mean((error - model) ** 2, axis=0)), rtol=1e-9)
    assert channel_sample_rms(meas.summary, rows_resid[:, 3], 3) == pytest.approx(
        float(np.sqrt(np.mean((error[:, 3] - 0.3) ** 2))), rel=1e-9)
    # A 1 s mean of 50 samples weighs 50 samples; a monitor row by its noise against one sample's
    # (the monitor rows here are about 50-sample means: 1e-3 / 1.4e-4 squared ~ 51).
    w = meas.row_weight
    assert np.all(w[summary.averaged] == 50)
    assert np.median(w[~summary.averaged]) == pytest.approx(51.0, rel=0.25)
    # The white-noise density is the raw samples': sigma sqrt(2 dt) ... measured by differences.
    assert meas.summary.raw_density[0] == pytest.approx(1e-3 * np.sqrt(2 * 0.02), rel=0.1)


def test_long_records_get_longer_means():
    rng = np.random.default_rng(4)
    frame, summary = summarize_blocks([_record(rng, 0.0, 30000)])
    assert len(frame) == MAX_BINS_PER_BLOCK
    assert np.all(summary.samples == 500)


def test_weighted_percentile_is_the_percentile_of_the_repeated_values():
    rng = np.random.default_rng(5)
    for _ in range(50):
        v = rng.normal(size=int(rng.integers(1, 40)))
        c = rng.integers(1, 6, size=v.size)
        q = float(rng.uniform(0, 100))
        assert weighted_percentile(v, c, q) == pytest.approx(float(np.percentile(np.repeat(v, c), q)), abs=1e-12)
