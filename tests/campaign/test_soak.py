"""Soak judgement: the stable window and the soak timeout policy."""

import math

import pytest

from labrunner.procedure import Soak
from labrunner.runner.soak import SoakWindow, soak_timeout

SOAK = Soak(tolerance_c=0.5, stable_window_s=120, max_wait_s=3600, on_timeout="pause", sensor="imu", poll_s=30)


def _feed(window, readings, every_s=30.0):
    verdicts = []
    for i, (chamber, imu) in enumerate(readings):
        window.add(i * every_s, chamber, imu)
        verdicts.append(window.stable())
    return verdicts


def test_stable_only_once_the_soak_has_lasted_a_window():
    w = SoakWindow(SOAK, 15.0)
    # Settled from the first reading, but 120 s must have passed: readings at 0, 30, 60, 90, 120 s.
    assert _feed(w, [(15.0, 15.0)] * 6) == [False, False, False, False, True, True]
    assert w.covered_s() == 150.0


def test_a_chamber_reading_outside_the_tolerance_in_the_window_is_not_stable():
    w = SoakWindow(SOAK, 15.0)
    readings = [(15.0, 15.0)] * 4 + [(15.6, 15.0)] + [(15.0, 15.0)] * 5
    verdicts = _feed(w, readings)
    # The excursion at 120 s spoils every window that holds it (up to 240 s), then it is forgotten.
    assert verdicts == [False] * 9 + [True]


def test_the_imu_spread_counts_with_sensor_imu_and_not_with_sensor_chamber():
    drifting = [(15.0, 14.0 + 0.2 * i) for i in range(8)]  # the chamber is there, the IMU still follows
    assert not any(_feed(SoakWindow(SOAK, 15.0), drifting))
    assert _feed(SoakWindow(SOAK.model_copy(update={"sensor": "chamber"}), 15.0), drifting)[4:] == [True] * 4
    # An IMU that gave no sample (NaN) is not known to be stable.
    assert not _feed(SoakWindow(SOAK, 15.0), [(15.0, math.nan)] * 6)[-1]


def test_the_window_boundary_is_inclusive_of_readings_a_window_old():
    w = SoakWindow(SOAK, 15.0)
    w.add(10.0, 15.0, 15.0)
    w.add(130.0, 15.0, 15.6)
    assert not w.stable()  # 10 s and 130 s are 120 s apart: both in the window, spread 0.6 > 0.5
    w.add(131.0, 15.0, 15.6)
    assert w.stable()  # the 10 s reading is now older than a window


@pytest.mark.parametrize("policy, carry_on, kind", [("continue", True, "warning"), ("pause", False, "fault"),
                                                    ("abort", False, "fault")])
def test_soak_timeout_verdicts(policy, carry_on, kind):
    v = soak_timeout(SOAK.model_copy(update={"on_timeout": policy}), "ramp", 35.0)
    assert v.action == policy and v.carry_on is carry_on and v.event_kind == kind
    assert v.message == f"ramp at 35.0 C did not stabilise within soak.max_wait_s (3600 s); on_timeout: {policy}"
