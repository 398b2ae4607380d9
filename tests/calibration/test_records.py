"""Records and temperature steps inferred from rows (no setpoint column)."""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.calibration.records import segment_records, temperature_steps

from calib_campaigns import make_campaign


def test_raw_samples_give_one_record_per_soak_orientation_and_rate():
    frame = make_campaign(seed=1, temperatures_c=(-20.0, 30.0), rates_dps=(50.0, -50.0, 0.0), record_s=10.0)
    rec = segment_records(frame)
    steps = temperature_steps(rec)
    assert len(rec) == 6 * 2 * 3
    assert len(steps) == 2
    assert np.all(steps.n_records == 18)
    assert np.all(rec.n_rows == 500)  # 10 s at 50 Hz, all rows kept
    assert rec.duration_s == pytest.approx(np.full(len(rec), 10.0))
    # Table rates are recovered per record (the table holds them within 1e-4)
    assert np.allclose(np.sort(np.unique(np.round(rec.rate_dps))), [-50.0, 0.0, 50.0])
    # Reference: +1 g along up, rate about up (negative about an axis pointing down)
    down = rec.orientation == 1  # x_down
    assert np.allclose(rec.reference[down, :3], [-1, 0, 0])
    assert np.allclose(rec.reference[down, 3], -rec.rate_dps[down])


def test_ramps_logged_between_soaks_are_not_records_and_steps_are_still_found():
    frame = make_campaign(seed=2, temperatures_c=(-10.0, 10.0, 30.0), average_s=1.0, log_ramps=True,
                          orientations=("z_up", "z_down"))
    rec = segment_records(frame)
    steps = temperature_steps(rec)
    # Three soaks (and possibly the ambient soak before remounting): ramp stretches are dropped
    assert (rec.row_record < 0).sum() > 0.2 * len(frame)
    main = steps.n_records >= 8
    assert main.sum() == 3
    assert np.all(np.diff(steps.temp_c[main]) > 15)
    # Every record is steady: small temperature span and a single rate
    assert rec.temp_span_c.max() <= 0.5 + 1e-9
    assert np.all(rec.duration_s >= 5.0)


def test_static_campaign_with_ramps_keeps_a_record_per_soak():
    """No table: soak, settle and record rows merge at rate 0; the soak ends are still found."""
    frame = make_campaign(seed=3, temperatures_c=(-10.0, 30.0), average_s=1.0, log_ramps=True, table=False,
                          orientations=("z_up",))
    rec = segment_records(frame)
    steps = temperature_steps(rec)
    assert len(steps) >= 2
    assert {round(t / 10) for t in steps.temp_c} >= {round((-10 + 4) / 10), round((30 + 4) / 10)}


def test_time_gap_splits_records():
    frame = make_campaign(seed=4, temperatures_c=(20.0,), rates_dps=(0.0,), record_s=20.0,
                          orientations=("z_up",), table=False)
    rec = segment_records(frame)
    assert len(rec) == 1
    gap = frame.copy()
    gap.loc[gap.index >= 500, "t_s"] += 30.0
    rec2 = segment_records(gap)
    assert len(rec2) == 2 and rec2.n_rows.tolist() == [500, 500]
