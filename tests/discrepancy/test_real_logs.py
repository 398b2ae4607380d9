"""Issue 11: the diagnosis on logs that look like real ones (tests/discrepancy/log_like.py, not the simulator).

Each situation is hidden in generated data the analysis receives only as rows: a jittery, quantised
temperature with real heating/cooling overlap (hysteresis found, or ruled out when absent), a
continuous log with run labels but no power-ons, a per-run offset large enough to matter. On every
one the extended model predicts held-out rows (short and hour-long stretches) no worse than an
ordinary least-squares fit of the same baseline. The noise as a finding: test_noise_finding.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.discrepancy import DiagnoseOptions, Measurements, diagnose

from .log_like import log_like
from .ols_reference import assert_no_worse_than_ols

HYSTERESIS = {"accel_y": 1.0e-3, "gyro_z": 0.08}


@pytest.mark.parametrize("situation", ["plain", "continuous", "hysteresis", "run_offsets"])
def test_extended_model_predicts_no_worse_than_least_squares(situation):
    kwargs = {"plain": {}, "continuous": {"continuous": True}, "hysteresis": {"hysteresis": HYSTERESIS},
              "run_offsets": {"run_offsets": {"accel_x": 5e-4}, "runs_per_orientation": 3}}[situation]
    frame, _ = log_like(11, 24, **kwargs)
    result = diagnose(frame)
    assert_no_worse_than_ols(frame, result)
    assert result.method["holdout_long_segment_s"] >= 3600.0


@pytest.mark.parametrize("jitter", [0.01, 0.05])
def test_hysteresis_under_jitter_and_quantisation_is_found(jitter):
    frame, truth = log_like(5, 24, hysteresis=HYSTERESIS, jitter_c=jitter)
    assert np.unique(np.diff(np.unique(frame["imu_temp_c"]))).min() == pytest.approx(0.0625)
    result = diagnose(frame)
    assert result.verdict == "hysteresis", [(f.cause, f.channels) for f in result.findings]
    finding = next(f for f in result.findings if f.cause == "hysteresis")
    assert set(finding.channels) == set(HYSTERESIS)
    for c, w in HYSTERESIS.items():
        assert abs(finding.parameters["width"][c] - w) / w < 0.25, c
    assert result.coverage.temperature_smoothing_s > 0  # the jitter was seen and smoothed
    assert result.coverage.branch_overlap_c > 20.0  # heating and cooling overlap over most of the range
    assert result.coverage.branch_rows[1] > 10_000  # cooling rows inside the range reached heating
    assert not any("no temperature range was reached both" in m for m in result.not_identifiable)


def test_hysteresis_is_ruled_out_when_absent():
    frame, _ = log_like(6, 24, jitter_c=0.04)
    result = diagnose(frame)
    assert "hysteresis" not in {f.cause for f in result.findings}
    # The claim is checked against the data: it was testable (both branches seen), and not selected.
    assert not any(m.startswith("hysteresis") for m in result.not_identifiable)
    hyst = next(c for c in result.candidates if c["cause"] == "hysteresis")
    assert hyst["tested_on"] and not hyst["selected"]


def test_a_continuous_log_with_run_labels_is_one_recording():
    frame, _ = log_like(8, 6, continuous=True)
    assert frame["run"].nunique() == 6
    meas = Measurements.from_frame(frame)
    assert np.unique(meas.run).size == 1
    assert meas.t_on_s[-1] == pytest.approx(frame["t_s"].iloc[-1] - frame["t_s"].iloc[0])
    result = diagnose(frame)
    notes = " ".join(result.coverage.notes)
    assert "power-ons assumed" in notes and "5 change(s) of run without a gap" in notes
    assert result.coverage.to_json()["power_ons"] == {"count": 1, "source": "assumed",
                                                      "run_changes_without_power_on": 5}


def test_power_on_column_marks_the_power_ons():
    frame, truth = log_like(8, 6, power_on_column=True)
    frame.loc[frame.index[frame["power_on"].to_numpy() == 1][2], "power_on"] = 0  # one run change was no power-on
    meas = Measurements.from_frame(frame)
    assert meas.power_on_source == "column"
    assert np.unique(meas.run).size == len(truth.power_on_rows) - 1
    first = truth.power_on_rows[2]
    assert meas.t_on_s[first] > 0  # time since power-on runs on across that change of run
    result = diagnose(frame)
    assert not any("power-ons assumed" in n for n in result.coverage.notes)


def test_a_per_run_offset_large_enough_to_matter_is_found():
    # A random walk well below the offsets over a run (0.2 ug/sqrt(s): 25 ug in 4 h), as in a good IMU.
    walk = {c: (2e-7 if c.startswith("accel") else 1.5e-5) for c in ("accel_x", "accel_y", "accel_z", "gyro_x",
                                                                      "gyro_y", "gyro_z")}
    frame, truth = log_like(7, 24, run_offsets={"accel_x": 5e-4, "gyro_y": 0.06}, runs_per_orientation=3,
                            rate_random_walk=walk)
    result = diagnose(frame)
    finding = next(f for f in result.findings if f.cause == "turn_on_bias" and f.status == "selected")
    assert set(finding.channels) == {"accel_x", "gyro_y"}
    for c, offsets in truth.run_offsets.items():
        spread = float(np.std(offsets, ddof=1))
        assert abs(finding.parameters["sigma"][c] - spread) / spread < 0.4, c
    assert finding.parameters["runs"] == 9


def test_each_finding_says_how_stable_it_is_and_a_marginal_verdict_says_so():
    frame, _ = log_like(5, 24, hysteresis=HYSTERESIS)
    clear = diagnose(frame)
    finding = next(f for f in clear.findings if f.cause == "hysteresis")
    assert finding.stability is not None and finding.stability.selected_share == 1.0
    assert not clear.verdict_uncertain and clear.to_json()["findings"][0]["stability"]["subsamples"] == 10
    # The same data with the threshold at 78 % of this evidence: still selected on the whole log, but
    # 80 % of the time stretches carry less evidence (hysteresis shows where the temperature turns), so
    # the cause clears it on fewer resamples, and the verdict says so.
    marginal = diagnose(frame, DiagnoseOptions(min_evidence=0.78 * finding.evidence_score))
    top = next(f for f in marginal.findings if f.cause == "hysteresis")
    assert top.stability is not None and top.stability.uncertain
    assert marginal.verdict_uncertain and "hysteresis is selected on only" in marginal.verdict_note


def test_the_hysteresis_claim_names_the_rows_it_is_about():
    from labrunner.discrepancy.coverage import assess

    frame, _ = log_like(9, 6, continuous=True)
    frame["orientation"] = "z_up"  # no remount: the path never goes back through room temperature
    n = len(frame)
    ramp = np.linspace(23.0, 50.0, n) + np.random.default_rng(1).normal(0.0, 0.03, n)  # heating only, jittering
    frame["imu_temp_c"] = np.round(ramp / 0.0625) * 0.0625
    coverage = assess(Measurements.from_frame(frame))
    claim = next(m for m in coverage.not_identifiable if m.startswith("hysteresis: no temperature range"))
    heating, cooling = coverage.branch_rows
    assert heating > 0.9 * n and cooling == 0  # the smoothed path only heats, whatever the sensor's jitter
    assert f"{heating} rows heating, 0 cooling rows" in claim


def test_a_bad_power_on_value_is_named_with_file_line_and_column(tmp_path):
    from labrunner.campaign_csv import CampaignDataError, read_campaign, write_campaign

    frame, _ = log_like(8, 1, power_on_column=True)
    path = tmp_path / "log.csv"
    write_campaign(frame, path)
    assert read_campaign(path)["power_on"].sum() == frame["power_on"].sum()  # the column round-trips
    lines = path.read_text().splitlines()
    cells = lines[5].split(",")
    cells[-1] = "2"
    lines[5] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(CampaignDataError, match=r"log.csv:6: column 'power_on': '2' is not 0 or 1"):
        read_campaign(path)
