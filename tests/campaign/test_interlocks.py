"""Interlocks: signal, limit, reason, and the rule for when a trip clears."""

import math

import pytest

from labrunner.procedure import Safety
from labrunner.runner.interlocks import Above, Interlocks, OutsideBand, Readings

SAFETY = Safety(chamber_min_c=-40, chamber_max_c=85, max_rate_dps=300, imu_max_temp_c=85)


def test_the_procedures_safety_section_gives_three_interlocks_in_order():
    locks = Interlocks.from_safety(SAFETY)
    assert [(i.name, i.signal) for i in locks.interlocks] == [
        ("chamber", "chamber_c"), ("table rate", "rate_dps"), ("IMU temperature", "imu_temp_c")]
    assert locks.check(Readings(chamber_c=23.0, rate_dps=-300.0, imu_temp_c=40.0)) is None


@pytest.mark.parametrize("readings, reason", [
    (Readings(chamber_c=85.04), "chamber at 85.0 C, outside the safety limits -40.0..85.0 C"),
    (Readings(chamber_c=-41.0), "chamber at -41.0 C, outside the safety limits -40.0..85.0 C"),
    (Readings(chamber_c=math.nan), "chamber at nan C, outside the safety limits -40.0..85.0 C"),
    (Readings(rate_dps=-303.5), "table at -303.50 deg/s, above the limit 300.0 deg/s"),
    (Readings(imu_temp_c=85.2), "IMU at 85.2 C, above its rating 85.0 C"),
])
def test_a_reading_outside_its_limit_trips_with_its_reason(readings, reason):
    trip = Interlocks.from_safety(SAFETY).check(readings)
    assert trip is not None and trip.reason == reason


def test_the_table_may_exceed_its_limit_by_its_rate_accuracy_and_a_missing_imu_reading_is_no_trip():
    locks = Interlocks.from_safety(SAFETY)
    assert locks.check(Readings(rate_dps=302.9)) is None  # within 1 %
    assert locks.check(Readings(imu_temp_c=math.nan)) is None  # no IMU sample yet
    assert locks.tripped == []


def test_the_first_interlock_in_order_gives_the_reason():
    trip = Interlocks.from_safety(SAFETY).check(Readings(chamber_c=90.0, rate_dps=400.0, imu_temp_c=90.0))
    assert trip is not None and trip.interlock == "chamber"


def test_a_trip_holds_until_the_reading_is_back_inside_by_the_margin():
    locks = Interlocks([Above("IMU temperature", "imu_temp_c", "IMU at {value:.1f} C, above {limit} C", limit=85.0,
                              clear_margin=2.0)])
    first = locks.check(Readings(imu_temp_c=86.0))
    assert first is not None and first.reason == "IMU at 86.0 C, above 85.0 C"
    # Back under the limit but not under limit - margin: still tripped (the first reason stands).
    assert locks.check(Readings(imu_temp_c=84.0)) == first
    assert locks.check(Readings()) == first  # a reading without the signal clears nothing
    assert locks.check(Readings(imu_temp_c=82.9)) is None and locks.tripped == []
    assert locks.check(Readings(imu_temp_c=85.5)) is not None  # and it can trip again


def test_band_clear_rule_and_describe():
    band = OutsideBand("chamber", "chamber_c", "{value:.0f} not in {low}..{high}", low=0.0, high=10.0,
                       clear_margin=1.0)
    assert band.trips(-0.1) and band.trips(10.1) and not band.trips(0.0) and not band.trips(10.0)
    assert not band.clears(0.5) and band.clears(1.0) and band.clears(9.0) and not band.clears(9.5)
    assert band.describe(12.0) == "12 not in 0.0..10.0"
