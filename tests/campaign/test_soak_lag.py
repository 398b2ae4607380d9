"""The predictive soak with a sensing element lagging the temperature sensor (`soak.predict_lag_s`, issue 16).

The element's predicted mean offset from the reading over the horizon against its closed form on a clean
exponential approach, the criterion waiting for it, and the parameters' validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labrunner.procedure import Soak, parse_procedure
from labrunner.runner.soak import SoakWindow
from labrunner.runner.soak_predict import ApproachFit, fit_approach
from labrunner.yaml_config import ConfigError

POLL = 15.0
RECORD_S = 60.0


def element_offset_closed_form(a: float, tau: float, lag: float, t0: float, horizon: float) -> float:
    """Mean over [0, horizon] of reading - element for a reading a exp(-t / tau) and an element following
    it through a first-order lag, started at t0 k x lag x rate behind it (d = A exp(-t/tau) + B exp(-(t-t0)/lag)):
    k = tau / (tau - lag), its steady offset, for tau >= 2 lag (then B = 0), else 2."""
    k = tau / (tau - lag) if tau >= 2 * lag else 2.0
    amp = -a * lag / (tau - lag)
    b = a * math.exp(-t0 / tau) * (lag / (tau - lag) - k * lag / tau)
    mean_a = amp * tau * (1.0 - math.exp(-horizon / tau)) / horizon
    mean_b = b * math.exp(t0 / lag) * lag * (1.0 - math.exp(-horizon / lag)) / horizon
    return mean_a + mean_b


@pytest.mark.parametrize("tau, lag", [(600.0, 240.0), (450.0, 600.0), (300.0, 300.5)])
def test_the_element_offset_matches_its_closed_form(tau, lag):
    t = np.arange(0.0, 601.0, POLL)
    a_now = 2.0  # what the reading still has to go at the newest reading (t = 600)
    y = 20.0 + a_now * np.exp(-(t - t[-1]) / tau)
    fit = fit_approach(t, y, RECORD_S, 7200.0, "single", lag_s=lag)
    assert isinstance(fit, ApproachFit)
    want = abs(element_offset_closed_form(a_now, tau, lag, -600.0, RECORD_S))
    assert fit.lag_c == pytest.approx(want, rel=2e-3)
    assert fit.lag_s == lag and fit.lag_bound_c >= fit.lag_c
    # Without a lag the fit predicts no offset and the bound is the drift's alone.
    plain = fit_approach(t, y, RECORD_S, 7200.0, "single")
    assert isinstance(plain, ApproachFit) and plain.lag_c == 0.0 and plain.lag_bound_c == 0.0


def test_a_soak_with_a_known_lag_waits_for_the_element():
    soak = Soak(criterion="predictive", tolerance_c=0.1, predict_tolerance_c=0.3, poll_s=POLL, predict_window_s=600)
    lagged = soak.model_copy(update={"predict_lag_s": 240.0, "predict_lag_tolerance_c": 0.5})

    def ends_after(s: Soak) -> tuple[float, SoakWindow]:
        w = SoakWindow(s, 20.0, horizon_s=RECORD_S)
        for k in range(400):
            t = k * POLL
            w.add(t, 20.0, 20.0 + 5.0 * math.exp(-t / 600.0))
            if w.stable():
                return t, w
        raise AssertionError("never stable")

    t_plain, w_plain = ends_after(soak)
    t_lag, w_lag = ends_after(lagged)
    assert w_plain.prediction is not None and w_lag.prediction is not None
    assert t_lag > t_plain
    # The reading's approach at the decision, and the element's offset it implies (closed form).
    a_plain = 5.0 * math.exp(-t_plain / 600.0)
    a_lag = 5.0 * math.exp(-t_lag / 600.0)
    assert abs(element_offset_closed_form(a_plain, 600.0, 240.0, -600.0, RECORD_S)) > 0.5
    assert abs(element_offset_closed_form(a_lag, 600.0, 240.0, -600.0, RECORD_S)) <= 0.5
    assert w_lag.prediction.lag_bound_c <= 0.5
    detail = w_lag.prediction.detail()
    assert detail["lag_s"] == 240.0 and 0 < detail["predicted_lag_bound_c"] <= 0.5  # type: ignore[operator]
    assert "element" in w_lag.prediction.describe()


@pytest.mark.parametrize("soak_yaml, words", [
    ("{predict_lag_s: 240}", "apply to criterion: predictive"),
    ("{criterion: predictive, predict_lag_s: 0.1}", "soak.predict_lag_s"),
    ("{criterion: predictive, predict_lag_tolerance_c: 20}", "soak.predict_lag_tolerance_c"),
    ("{criterion: predictive, predict_lag_s: -5}", "predict_lag_s"),
])
def test_lag_parameters_are_validated_with_a_located_message(soak_yaml, words):
    text = (f"name: p\ntemperatures: {{list_c: [20]}}\nsoak: {soak_yaml}\norientations: [z_up]\n"
            "rates: {list_dps: [0]}\n")
    with pytest.raises(ConfigError) as exc:
        parse_procedure(text, "p.yaml")
    assert words in str(exc.value) and "p.yaml:3" in str(exc.value)
