"""What measurement would separate two causes the data cannot tell apart."""

from __future__ import annotations

from .terms import Term

_PAIRS: dict[frozenset[str], str] = {
    frozenset({"g_sensitivity", "turn_on_bias"}):
        "every orientation change coincides with a power-on, so per-orientation offsets (g-sensitivity) and "
        "per-run offsets (turn-on bias) fit alike: power-cycle the IMU within an orientation (e.g. at every "
        "temperature), or come back to an orientation after a later power-on",
    frozenset({"scale_nonlinearity", "turn_on_bias"}):
        "the squared input changes only when the IMU is remounted (a power-on), so a squared-force term and "
        "per-run offsets fit alike: power-cycle within an orientation, or for the gyro spin the table at "
        "several rates within one power-on",
    frozenset({"hysteresis", "turn_on_bias"}):
        "each power-on covers one temperature direction, so the heating/cooling branch offset and per-run "
        "offsets fit alike: reverse the temperature direction within one power-on (up and down in the same "
        "run), or power-cycle at every temperature",
    frozenset({"hysteresis", "g_sensitivity"}):
        "each orientation is measured in one temperature direction: measure every orientation both heating "
        "and cooling",
    frozenset({"thermal_lag", "warmup"}):
        "the only temperature changes in the log are the self-heating after power-on, where a lag of the "
        "element and a power-on transient look alike: log the ramps between soaks (a lag follows dT/dt, a "
        "warm-up only the time since power-on)",
    frozenset({"thermal_lag", "hysteresis"}):
        "only soaked data: a slow element still settling after a heating or a cooling approach looks like a "
        "branch offset: log the ramps, or soak longer before recording (a lag decays, hysteresis does not)",
    frozenset({"warmup", "turn_on_bias"}):
        "a slow power-on transient and a per-run offset look alike over short runs: record longer after "
        "each power-on, or power-cycle more often",
    frozenset({"temperature_nonlinearity", "hysteresis"}):
        "the temperature levels were each visited in one direction only: reach every level from both "
        "sides, or add levels",
    frozenset({"temperature_nonlinearity", "thermal_lag"}):
        "log the ramps and add temperature levels: a lag follows dT/dt, a non-cubic temperature law the "
        "temperature itself",
    frozenset({"lever_arm", "scale_nonlinearity"}):
        "spin the table with the IMU in more orientations: a lever arm acts on the horizontal "
        "accelerometer axes only, a squared-input error on the axis that carries the input",
}


def separating_measurement(a: Term, b: Term) -> str:
    key = frozenset({a.name, b.name})
    if key in _PAIRS:
        return _PAIRS[key]
    return f"vary {a.driver.split(' (')[0]} independently of {b.driver.split(' (')[0]}"
