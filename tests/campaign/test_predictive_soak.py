"""The predictive soak criterion (soak.criterion: predictive) against plants whose time constants are
known: it ends earlier than the spread criterion, the IMU temperature over the record that follows
stays within the tolerance, a noisy or jittery sensor does not end it early, a fit that gives no
prediction falls back to the spread criterion, and the sequencer logs the decision."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from labrunner.clock import VirtualClock
from labrunner.procedure import Soak, parse_procedure
from labrunner.runner.soak import SoakWindow
from labrunner.runner.soak_predict import ApproachFit, NoFit, fit_approach
from labrunner.yaml_config import ConfigError

from .fakes import FakeImu, FakeLab
from .test_runner_inprocess import Campaign

SETPOINT = 35.0
START = 15.0
TAU = 600.0
RECORD_S = 60.0
POLL = 30.0
STRICT = Soak(tolerance_c=0.1, stable_window_s=600, max_wait_s=5 * 3600, sensor="imu", poll_s=POLL)
PREDICTIVE = STRICT.model_copy(update={"criterion": "predictive", "predict_window_s": 600.0})


def first_order(t: float, tau: float = TAU) -> float:
    return SETPOINT + (START - SETPOINT) * math.exp(-t / tau)


def two_constants(t: float) -> float:
    # The case follows the air (600 s) and the die's self-heating after power-on adds +1.5 C (200 s).
    return SETPOINT + (START - SETPOINT) * math.exp(-t / TAU) + 1.5 * (1.0 - math.exp(-t / 200.0))


def soak_end(soak: Soak, plant, sensor=lambda t, true: true, horizon_s: float = RECORD_S) -> tuple[float, SoakWindow]:
    """Poll the plant every POLL s from t = 0 (the chamber at its setpoint) until the window says stable."""
    w = SoakWindow(soak, SETPOINT, horizon_s=horizon_s)
    t = 0.0
    while t <= soak.max_wait_s:
        w.add(t, SETPOINT, sensor(t, plant(t)))
        if w.stable():
            return t, w
        t += POLL
    raise AssertionError("the soak never ended")


def drift_over_record(plant, t_end: float, record_s: float = RECORD_S) -> float:
    """How far the true IMU temperature moves over the record that starts when the soak ends."""
    ts = np.linspace(t_end, t_end + record_s, 61)
    ys = np.array([plant(t) for t in ts])
    return float(ys.max() - ys.min())


def test_predictive_ends_earlier_than_spread_and_the_record_stays_within_tolerance():
    t_strict, _ = soak_end(STRICT, first_order)
    t_pred, w = soak_end(PREDICTIVE, first_order)
    # Spread <= 0.1 C over 600 s: 20 C * exp(-t/tau) * (e - 1) <= 0.1 -> t = 3504 s; the prediction bounds the
    # change over one 60 s record by the current rate times 60 s (no decelerating approach changes more):
    # 20 C * exp(-t/tau) * 60 / tau <= 0.1 -> t = 1797 s.
    assert t_strict == pytest.approx(3510, abs=POLL)
    assert t_pred == pytest.approx(1800, abs=POLL)
    assert w.fallback is None and isinstance(w.prediction, ApproachFit)
    assert w.prediction.tau_s == pytest.approx(TAU, rel=1e-3)
    assert w.prediction.span_s == pytest.approx(600.0)
    assert drift_over_record(first_order, t_pred) <= PREDICTIVE.tolerance_c
    rate = (SETPOINT - START) * math.exp(-t_pred / TAU) / TAU
    assert w.prediction.drift_c == pytest.approx(rate * RECORD_S, rel=1e-3)
    assert w.prediction.drift_c >= drift_over_record(first_order, t_pred)


@pytest.mark.parametrize("horizon_s", [60.0, 600.0, 2600.0])
def test_the_horizon_is_the_duration_the_temperature_must_hold(horizon_s):
    soak = PREDICTIVE.model_copy(update={"predict_horizon_s": horizon_s})
    t_pred, w = soak_end(soak, first_order, horizon_s=RECORD_S)  # the soak's own horizon wins over the record
    assert w.horizon_s == horizon_s
    assert drift_over_record(first_order, t_pred, horizon_s) <= soak.tolerance_c
    # Not needlessly late either: one poll earlier the drift over the horizon was still too large, for the
    # bound (each component's rate times the horizon, up to its amplitude, against the exponential's own).
    conservative = min(horizon_s / TAU, 1.0) / -math.expm1(-horizon_s / TAU)
    assert drift_over_record(first_order, t_pred - POLL, horizon_s) * conservative > soak.tolerance_c * 0.9


def test_two_time_constants_after_power_on_are_fitted_by_the_double_model():
    # Early on both components show: the double model resolves them, the single one cannot.
    t = np.arange(21) * POLL
    y = [two_constants(v) for v in t]
    double = fit_approach(t, y, RECORD_S, 7200.0, "double")
    assert isinstance(double, ApproachFit) and sorted(double.taus_s) == pytest.approx([200.0, TAU], rel=1e-2)
    single = fit_approach(t, y, RECORD_S, 7200.0, "single")
    assert isinstance(single, ApproachFit) and single.rms_c > 100 * double.rms_c
    # Over the soak: the double model ends it earlier than the spread, and the record holds.
    soak = PREDICTIVE.model_copy(update={"predict_model": "double"})
    t_pred, w = soak_end(soak, two_constants)
    t_strict, _ = soak_end(STRICT, two_constants)
    assert t_pred < t_strict - 1000
    assert w.fallback is None and w.prediction is not None
    assert w.prediction.tau_s == pytest.approx(TAU, rel=0.05)
    assert drift_over_record(two_constants, t_pred) <= soak.tolerance_c


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("kind", ["noise", "jitter"])
def test_a_noisy_or_jittery_sensor_does_not_end_the_soak_early(seed, kind):
    rng = np.random.default_rng(seed)

    def sensor(t: float, true: float) -> float:
        if kind == "noise":  # white noise of 0.05 C on a 1/16 C quantised reading
            return round((true + rng.normal(0.0, 0.05)) * 16) / 16
        # a jittery sensor: mostly right, now and then 0.3 C off
        return true + (rng.choice([-0.3, 0.3]) if rng.random() < 0.15 else 0.0)

    t_pred, w = soak_end(PREDICTIVE, first_order, sensor)
    # Whatever ended it (the prediction, or the spread after a fallback), the true temperature holds.
    assert drift_over_record(first_order, t_pred) <= PREDICTIVE.tolerance_c
    if w.fallback is None:
        assert w.prediction is not None and w.prediction.drift_bound_c <= PREDICTIVE.tolerance_c
        assert w.prediction.drift_sigma_c > 0.0  # the noise widened the bound


def test_a_fit_without_an_approach_falls_back_to_the_spread_criterion():
    # The IMU drifts linearly (a heater fault, no equilibrium in sight): no time constant within the bound.
    w = SoakWindow(PREDICTIVE, SETPOINT, horizon_s=RECORD_S)
    for k in range(21):
        w.add(k * POLL, SETPOINT, 30.0 + 0.0005 * k * POLL)
    assert not w.stable()
    assert w.fallback is not None and "time constant" in w.fallback and w.prediction is None
    # From then on the spread decides, and it would say stable once the spread is below the tolerance.
    for k in range(21, 42):
        w.add(k * POLL, SETPOINT, 30.3)
    assert w.stable() and w.fallback is not None


def test_the_chamber_off_its_setpoint_is_not_stable_whatever_the_fit():
    w = SoakWindow(PREDICTIVE, SETPOINT, horizon_s=RECORD_S)
    for k in range(21):
        w.add(k * POLL, SETPOINT + (0.6 if k == 20 else 0.0), SETPOINT)
    assert not w.stable() and w.fallback is None


def test_the_chamber_back_near_its_setpoint_adds_its_offset_to_the_bound():
    # The controller's overshoot: a past excursion the IMU shows no sign of does not hold the soak, the
    # offset still there is in the bound (it moves the IMU by up to offset * (1 - exp(-horizon / tau))).
    w = SoakWindow(PREDICTIVE, SETPOINT, horizon_s=RECORD_S)
    for k in range(21):
        w.add(k * POLL, SETPOINT + (0.4 if k == 10 else 0.05 if k == 20 else 0.0), first_order(1800 + k * POLL))
    assert w.stable() and w.prediction is not None
    assert w.prediction.chamber_drift_c == pytest.approx(0.05 * -math.expm1(-RECORD_S / w.prediction.tau_s))
    assert w.prediction.drift_bound_c <= PREDICTIVE.tolerance_c


def test_fit_approach_reports_why_it_gives_no_prediction():
    assert isinstance(fit_approach([0, 30, 60], [1.0, 2.0, 3.0], 60.0, 7200.0), NoFit)
    t = np.arange(21) * POLL
    assert "bound" in fit_approach(t, 20 + 0.001 * t, 60.0, 7200.0).reason  # type: ignore[union-attr]


@pytest.mark.parametrize("soak_yaml, words", [
    ("{criterion: predictive, sensor: chamber}", "criterion predictive fits the IMU temperature"),
    ("{criterion: predictive, poll_s: 100, predict_window_s: 600}", "at least 8 polls"),
    ("{criterion: predictive, predict_window_s: 1}", "soak.predict_window_s"),
    ("{criterion: predictive, predict_tau_max_s: 1e9}", "soak.predict_tau_max_s"),
    ("{criterion: guess}", "criterion"),
])
def test_predictive_parameters_are_validated_with_a_located_message(soak_yaml, words):
    text = (f"name: p\ntemperatures: {{list_c: [20]}}\nsoak: {soak_yaml}\norientations: [z_up]\n"
            "rates: {list_dps: [0]}\n")
    with pytest.raises(ConfigError) as exc:
        parse_procedure(text, "p.yaml")
    assert words in str(exc.value) and "p.yaml:3" in str(exc.value)


class LaggingImu(FakeImu):
    """The fake IMU whose temperature follows the chamber air with a first-order lag of `tau_s`."""

    tau_s = TAU

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._t_last = self.clock.now()
        self._temp = self.chamber.air_c()

    def _temp_c(self) -> float:
        now = self.clock.now()
        air = self.chamber.air_c()
        self._temp = air + (self._temp - air) * math.exp(-(now - self._t_last) / self.tau_s)
        self._t_last = now
        return self._temp


PROC = """\
name: lagged
temperatures: {list_c: [15, 35], order: ascending}
soak: {tolerance_c: 0.1, stable_window_s: 600, max_wait_s: 18000, on_timeout: abort, sensor: imu, poll_s: 30,
       criterion: CRITERION}
orientations: [z_up]
remount_c: 23
remount_s: 60
rates: {list_dps: [-50, 50]}
settle_s: 1
record_s: 30
record_poll_s: 10
safety: {chamber_min_c: -40, chamber_max_c: 40, max_rate_dps: 150, imu_max_temp_c: 85}
monitor: {enabled: false}
fit: {run: false}
"""


def _lagged_run(tmp_path, criterion: str, tau_s: float = TAU):
    (tmp_path / criterion).mkdir()
    c = Campaign(tmp_path / criterion, PROC.replace("CRITERION", criterion))
    lab = FakeLab(VirtualClock())
    lab.chamber.ramp_c_per_s = 10.0  # the air steps: the IMU's approach is the pure first-order lag
    lab.imu = LaggingImu(lab.clock, lab.chamber, lab.table)
    lab.imu.tau_s = tau_s
    lab.operator.imu = lab.imu
    runner = c.runner(lab)
    runner.run()
    return c, lab


def test_the_sequencer_logs_the_predictive_decision_and_saves_lab_time(tmp_path):
    strict, strict_lab = _lagged_run(tmp_path, "spread")
    pred, pred_lab = _lagged_run(tmp_path, "predictive")
    try:
        ev = pred.events()
        soaked = ev[ev.message.str.startswith("soaked at")]
        assert len(soaked) == 2
        for raw, msg in zip(soaked.detail, soaked.message, strict=True):
            detail = json.loads(raw) if isinstance(raw, str) else raw
            assert "predictive: predicted drift" in msg
            assert detail["criterion"] == "predictive" and detail["predicted_drift_bound_c"] <= 0.1
            assert detail["tau_s"] == pytest.approx(TAU, rel=0.02) and detail["fit_window_s"] == pytest.approx(600)
            assert detail["horizon_s"] == 30.0
        assert not ev.message.str.contains("falls back").any()
        assert pred_lab.clock.now() < strict_lab.clock.now() - 1500  # two soaks, each ~ 900+ s shorter
        # The records after each predictive soak: their IMU temperatures agree within the tolerance.
        steps = pred.steps()
        for _, group in steps.groupby("temperature_c"):
            assert group.imu_temp_c.max() - group.imu_temp_c.min() <= 0.1
    finally:
        strict.store.close()
        pred.store.close()


def test_the_sequencer_logs_a_fallback_and_the_spread_decides(tmp_path):
    # A sensor lagging by ~a day: over the fit window the IMU drifts almost linearly, no time constant
    # below predict_tau_max_s: each soak falls back, and the spread (tiny drift) ends it.
    c, _ = _lagged_run(tmp_path, "predictive", tau_s=1e6)
    try:
        ev = c.events()
        fell = ev[ev.message.str.contains("falls back to the spread criterion")]
        assert len(fell) == 2 and (fell.kind == "warning").all()
        assert all("on the bound of the search" in m for m in fell.message)
        soaked = ev[ev.message.str.startswith("soaked at")]
        assert len(soaked) == 2 and not soaked.message.str.contains("predictive").any()
    finally:
        c.store.close()
