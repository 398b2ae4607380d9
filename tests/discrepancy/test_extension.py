"""The extended model is a sims configuration that reproduces what was measured."""

from __future__ import annotations

import numpy as np

from labrunner.discrepancy import Measurements, check_model, diagnose
from labrunner.imu.model import CHANNELS
from labrunner.sims.campaign import synthesize
from labrunner.sims.world import SimLabConfig

from .campaigns import DRAWS, campaign, plan_for
from .test_hidden_effects import case_seed


def test_the_extended_model_loads_into_the_sims_and_leaves_no_structure(tmp_path):
    seed = case_seed("extend")
    rng = np.random.default_rng(seed)
    hidden = [DRAWS["hysteresis"](rng), DRAWS["turn_on_bias"](rng)]
    # Power-cycled at every temperature: log the ramps, or the branch is lost at each power-on.
    frame, _ = campaign(hidden, "sims", seed, log_ramps=True)
    measured = Measurements.from_frame(frame)

    result = diagnose(frame)
    assert {f.cause for f in result.selected} == {"hysteresis", "turn_on_bias"}
    path = tmp_path / "imu_model.json"
    result.model.save(path)

    # What a dry run would use: the sims load the model from the path.
    config = SimLabConfig.from_dict({"imu_model": str(path), "seed": seed})
    assert set(config.imu_model.effects) >= {"hysteresis", "turn_on_bias"}
    after = check_model(config.imu_model, measured)
    for c in CHANNELS:
        white = result.noise[c].white_rms
        # Measured minus the extended model is the white noise, nothing more ...
        assert after[c] < 1.05 * white, c
    # ... while the baseline left the hidden effects in the affected channels.
    affected = set().union(*(h.channels for h in hidden))
    for c in affected:
        assert result.model_check["baseline"][c] > 1.2 * after[c], c


def test_a_dry_run_with_the_extended_model_reproduces_the_measured_behaviour():
    seed = case_seed("dry run")
    rng = np.random.default_rng(seed)
    hidden = DRAWS["warmup"](rng)
    frame, _ = campaign([hidden], "sims", seed)
    first = diagnose(frame)
    assert first.verdict == "warmup"

    # Simulate the same procedure with the extended model, and diagnose that.
    plan = plan_for([hidden], "sims", np.random.default_rng(seed))
    rerun = synthesize(plan, SimLabConfig(seed=seed + 1, imu_model=first.model))
    second = diagnose(rerun)
    assert second.verdict == "warmup"
    a, b = first.selected[0], second.selected[0]
    assert a.channels == b.channels
    assert abs(b.parameters["tau_s"] / a.parameters["tau_s"] - 1) < 0.1
    for c in a.channels:
        assert abs(b.parameters["amplitude"][c] / a.parameters["amplitude"][c] - 1) < 0.1
    # Same noise, same held-out residual level.
    for c in CHANNELS:
        assert abs(second.gain.heldout_rms_after[c] / first.gain.heldout_rms_after[c] - 1) < 0.15, c
