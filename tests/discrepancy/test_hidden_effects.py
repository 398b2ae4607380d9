"""Acceptance: a campaign with one effect hidden in it is diagnosed from its rows alone.

For every cause, a simulated campaign with that effect switched on -- parameters drawn at
random within realistic ranges, from a generator seeded per case -- is passed to
`diagnose` as data only. The verdict, the channels, the fitted parameters and a positive
held-out gain are checked; so is the verdict `none` without an effect, and two effects at
once. Each case runs in two styles: this project's own sims output, and campaigns that
look like real logs (1 s rows with ramps, quantised temperature, random-walk drift).
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from labrunner.discrepancy import diagnose
from labrunner.imu.model import CHANNELS, GYRO_CHANNELS

from .campaigns import DRAWS, Hidden, campaign
from .ols_reference import assert_no_worse_than_ols

CAUSES = ("thermal_lag", "hysteresis", "warmup", "turn_on_bias", "g_sensitivity", "scale_nonlinearity",
          "temperature_nonlinearity", "lever_arm")
STYLES = ("sims", "reallog")


def case_seed(*parts: str) -> int:
    """Reproducible, and different for every case."""
    return zlib.crc32("/".join(parts).encode()) % 100_000


def rel(a: float, b: float) -> float:
    return abs(a - b) / abs(b)


# --- per-cause parameter checks (tolerances are stated here) -------------------------------


def check_thermal_lag(p, hidden, config, frame, result):
    assert rel(p["tau_s"], hidden.effect["tau_s"]) < 0.05


def check_hysteresis(p, hidden, config, frame, result):
    for c, w in hidden.effect["width"].items():
        assert rel(p["width"][c], w) < 0.10, c
    if any("hysteresis travel_c" in m for m in result.not_identifiable):
        return  # soaks only: the travel is not identifiable (and the JSON says so)
    assert rel(p["travel_c"], hidden.effect["travel_c"]) < 0.20


def check_warmup(p, hidden, config, frame, result):
    assert rel(p["tau_s"], hidden.effect["tau_s"]) < 0.10
    for c, a in hidden.effect["amplitude"].items():
        assert rel(p["amplitude"][c], a) < 0.10, c


def check_turn_on_bias(p, hidden, config, frame, result):
    # The generator draws one offset per run; compare with the spread it actually drew.
    runs = np.unique(frame["run"].to_numpy())
    drawn = config.imu_model.run_offsets(runs)
    for c in hidden.channels:
        spread = float(np.std(drawn[:, CHANNELS.index(c)], ddof=1))
        assert rel(p["sigma"][c], spread) < 0.30, c
    assert p["runs"] == runs.size


def check_g_sensitivity(p, hidden, config, frame, result):
    got = np.asarray(p["matrix_dps_per_g"])
    want = np.asarray(hidden.effect["matrix_dps_per_g"])
    for c in hidden.channels:
        i = GYRO_CHANNELS.index(c)
        assert np.max(np.abs(got[i] - want[i])) < 0.004, c


def check_scale_nonlinearity(p, hidden, config, frame, result):
    for c, k in hidden.effect["k2_per_dps"].items():
        assert rel(p["k2_per_dps"][c], k) < 0.05, c


def check_temperature_nonlinearity(p, hidden, config, frame, result):
    e = hidden.effect
    for c, a in e["amplitude"].items():
        assert rel(p["amplitude"][c], a) < 0.15, c
    assert abs(p["center_c"] - e["center_c"]) < 2.0
    assert rel(p["width_c"], e["width_c"]) < 0.30


def check_lever_arm(p, hidden, config, frame, result):
    for i, r in enumerate(hidden.effect["r_m"]):
        if r:
            assert rel(p["r_m"][i], r) < 0.05


CHECKS = {name: globals()[f"check_{name}"] for name in CAUSES}


def assert_found(result, hidden: Hidden) -> None:
    finding = next(f for f in result.findings if f.cause == hidden.cause and f.status == "selected")
    assert set(finding.channels) == hidden.channels
    assert finding.gain.improvement_pct > 0
    for c in finding.channels:
        assert finding.gain.heldout_rms_after[c] < finding.gain.heldout_rms_before[c]


@pytest.mark.parametrize("style", STYLES)
@pytest.mark.parametrize("cause", CAUSES)
def test_a_hidden_effect_is_named_with_its_channels_parameters_and_gain(cause, style):
    seed = case_seed(cause, style)
    hidden = DRAWS[cause](np.random.default_rng(seed))
    frame, config = campaign([hidden], style, seed)

    result = diagnose(frame)  # the rows only

    assert result.verdict == cause
    selected = [f for f in result.findings if f.status == "selected"]
    assert [f.cause for f in selected] == [cause]
    assert selected[0].confounded_with == []
    assert_found(result, hidden)
    CHECKS[cause](selected[0].parameters, hidden, config, frame, result)
    assert result.gain.improvement_pct > 0
    assert_no_worse_than_ols(frame, result)


@pytest.mark.parametrize("style", STYLES)
def test_no_extra_effect_gives_verdict_none(style):
    seed = case_seed("none", style)
    frame, _ = campaign([], style, seed, log_ramps=True)
    result = diagnose(frame)
    assert result.verdict == "none"
    assert [f for f in result.findings if f.status != "noise"] == []
    assert all(v == 0.0 for v in result.gain.improvement_by_channel.values())
    assert_no_worse_than_ols(frame, result)
    if style == "reallog":  # the drift is noticed, as noise, on every channel
        assert all(n.drift_evidence > 10 for n in result.noise.values())
        # Within the stretches logged without a gap (under an hour here) the Allan deviation is white
        # noise's: the simulator's white noise matches it within the target, so no noise finding.
        assert result.allan is not None and max(result.allan.mismatch_before.values()) <= 0.2
        assert "noise" not in {f.cause for f in result.findings}


@pytest.mark.parametrize("style", STYLES)
def test_two_effects_at_once_are_both_found(style):
    seed = case_seed("two", style)
    rng = np.random.default_rng(seed)
    first = DRAWS["warmup"](rng)
    second = DRAWS["scale_nonlinearity"](rng)
    frame, _ = campaign([first, second], style, seed)
    result = diagnose(frame)
    selected = {f.cause for f in result.findings if f.status == "selected"}
    assert selected == {"warmup", "scale_nonlinearity"}
    assert result.verdict in selected
    assert_found(result, first)
    assert_found(result, second)
    assert_no_worse_than_ols(frame, result)


@pytest.mark.parametrize("design", [{"power_cycle": "temperature"}, {"power_cycle": "temperature", "log_ramps": True},
                                    {"log_ramps": False}])
def test_campaign_design_alone_does_not_name_a_cause(design):
    """The designs the hidden-effect cases use (power cycles at every temperature, logged ramps or not)
    carry no cause by themselves: without an effect the verdict stays `none`."""
    seed = case_seed("design", *sorted(f"{k}={v}" for k, v in design.items()))
    frame, _ = campaign([], "sims", seed, **design)
    result = diagnose(frame)
    assert result.verdict == "none", [(f.cause, f.channels) for f in result.findings]
