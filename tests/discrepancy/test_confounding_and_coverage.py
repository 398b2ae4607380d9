"""What the data cannot tell apart, and what it cannot show at all."""

from __future__ import annotations

import numpy as np

from labrunner.discrepancy import diagnose

from .campaigns import DRAWS, Hidden, campaign
from .test_hidden_effects import case_seed


def test_g_sensitivity_and_turn_on_bias_are_confounded_when_every_remount_is_a_power_on():
    seed = case_seed("confounded")
    hidden = DRAWS["g_sensitivity"](np.random.default_rng(seed))
    hidden.power_cycle = "orientation"  # power-ons only at the remounts: the design that cannot tell
    frame, _ = campaign([hidden], "sims", seed)

    result = diagnose(frame)

    assert result.verdict == "g_sensitivity"  # fewer parameters for the same fit
    top = result.findings[0]
    assert top.confounded_with == ["turn_on_bias"]
    alternative = next(f for f in result.findings if f.cause == "turn_on_bias")
    assert alternative.status == "alternative"
    assert alternative.confounded_with == ["g_sensitivity"]
    assert set(alternative.channels) >= hidden.channels
    assert alternative.gain.improvement_pct > 0
    # ... and both say which measurement would separate them.
    for f in (top, alternative):
        assert "power-cycle the IMU within an orientation" in f.evidence
    assert any("every orientation change coincides with a power-on" in n for n in result.coverage.notes)


def test_an_accelerometer_squared_input_is_confounded_with_turn_on_bias_in_the_same_design():
    seed = case_seed("confounded accel")
    k2 = float(np.random.default_rng(seed).uniform(1e-3, 3e-3))
    hidden = Hidden("scale_nonlinearity", {"k2_per_dps": {"accel_y": k2}}, {"accel_y"})
    frame, _ = campaign([hidden], "sims", seed)

    result = diagnose(frame)

    assert result.verdict == "scale_nonlinearity"
    top = result.findings[0]
    assert top.channels == ["accel_y"] and abs(top.parameters["k2_per_dps"]["accel_y"] / k2 - 1) < 0.05
    assert top.confounded_with == ["turn_on_bias"]
    assert "power-cycle within an orientation" in top.evidence


def test_without_table_rotation_the_gyro_scale_terms_are_not_identifiable_but_the_rest_is_diagnosed():
    seed = case_seed("no table")
    hidden = DRAWS["g_sensitivity"](np.random.default_rng(seed))
    frame, _ = campaign([hidden], "sims", seed, table=False)
    assert (frame["table_rate_dps"] == 0).all()

    result = diagnose(frame)

    assert result.verdict == "g_sensitivity"
    assert set(result.findings[0].channels) == hidden.channels
    text = "\n".join(result.not_identifiable)
    assert "gyro scale factor and misalignment: no table rotation" in text
    assert "scale_nonlinearity (gyro): no table rotation" in text
    assert "lever_arm: no table rotation" in text
    assert result.coverage.rotating is False


def test_without_a_chamber_column_nothing_is_lost():
    seed = case_seed("no chamber")
    hidden = DRAWS["scale_nonlinearity"](np.random.default_rng(seed))
    frame, _ = campaign([hidden], "sims", seed, chamber_column=False)
    assert frame["chamber_c"].isna().all()

    result = diagnose(frame)

    assert result.verdict == "scale_nonlinearity"
    assert set(result.findings[0].channels) == hidden.channels
    assert result.coverage.chamber_logged is False
    assert not any("chamber" in m for m in result.not_identifiable)


def test_three_orientations_cannot_separate_accelerometer_bias_from_scale_factor():
    seed = case_seed("three orientations")
    rng = np.random.default_rng(seed)
    hidden = DRAWS["scale_nonlinearity"](rng)
    gyro_k2 = {c: k for c, k in hidden.effect["k2_per_dps"].items() if c.startswith("gyro")} or {"gyro_z": 2e-5}
    hidden.effect = {"k2_per_dps": gyro_k2}
    hidden.channels = set(gyro_k2)
    frame, _ = campaign([hidden], "sims", seed, orientations=("x_up", "y_up", "z_up"))

    result = diagnose(frame)

    assert result.verdict == "scale_nonlinearity"
    assert set(result.findings[0].channels) == hidden.channels
    text = "\n".join(result.not_identifiable)
    assert "accelerometer bias vs scale factor/misalignment" in text
    for axis in "xyz":  # one way up only: the squared force is the scale factor
        assert f"scale_nonlinearity on accel_{axis}: the {axis} axis was vertical one way only" in text


def test_one_run_has_no_turn_on_bias_to_test_and_still_finds_a_warm_up():
    seed = case_seed("one run")
    hidden = DRAWS["warmup"](np.random.default_rng(seed))
    frame, _ = campaign([hidden], "sims", seed, orientations=("z_up",))
    assert frame["run"].nunique() == 1

    result = diagnose(frame)

    assert result.verdict == "warmup"
    assert set(result.findings[0].channels) == hidden.channels
    text = "\n".join(result.not_identifiable)
    assert "turn_on_bias: one power-on (run) in the data" in text
    assert "g_sensitivity: a single orientation" in text
    assert {c["cause"]: c["tested_on"] for c in result.candidates}["turn_on_bias"] == []
