"""The simulated lab's fault interface: every `FaultKind` switched on with `SimLab.apply_fault` shows the
symptom a driver would meet on a real lab, and `clear_fault` takes it away again."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from labrunner.drivers.errors import InstrumentError, InstrumentProtocolError, InstrumentRefused, InstrumentTimeout
from labrunner.drivers.protocols import ImuRecord
from labrunner.fault_kinds import INTERLOCK_KINDS, FaultKind, FaultTarget
from labrunner.fault_plan import KINDS, RANDOM_KINDS
from labrunner.lab import Lab
from tests.sim_lab import connected_lab  # noqa: F401 - the `lab` fixture

K = FaultKind




def _wait_for(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.05)
    return False


def _record(lab: Lab, seconds: float = 10.0, timeout_s: float = 1.0) -> ImuRecord:
    start = lab.imu.begin_record()
    lab.clock.sleep(seconds)
    return lab.imu.end_record(start, int(seconds * 50), timeout_s=timeout_s)


def _fails(action: Callable[[], object], error: type[Exception], match: str) -> Callable[[], None]:
    def check() -> None:
        with pytest.raises(error, match=match):
            action()
    return check


def _air_after(lab: Lab, setpoint_c: float, seconds: float) -> float:
    lab.chamber.set_setpoint(setpoint_c)
    start = lab.chamber.read_temperature()
    lab.clock.sleep(seconds)
    return lab.chamber.read_temperature() - start


# kind -> (apply parameters, check while on, check after clear_fault)
def _symptoms(lab: Lab) -> dict[FaultKind, tuple[dict[str, float], Callable[[], None], Callable[[], None]]]:
    ch, table, imu = lab.chamber, lab.table, lab.imu

    def reads() -> None:
        assert ch.read_setpoint() == pytest.approx(23.0)

    def answers() -> None:
        assert table.status().mode in ("JOG", "STOP")

    def outage_check() -> None:
        ch.close()
        with pytest.raises(InstrumentTimeout, match="cannot connect"):
            ch.connect()

    def heats(on: bool) -> Callable[[], None]:
        def check() -> None:
            moved = _air_after(lab, 40.0, 900.0)
            assert (moved < 1.0) if on else (moved > 5.0), moved
        return check

    def cools(on: bool) -> Callable[[], None]:
        def check() -> None:
            moved = _air_after(lab, 0.0, 900.0)
            assert (moved > -1.0) if on else (moved < -5.0), moved
        return check

    def stuck_heater() -> None:
        assert _air_after(lab, 23.0, 900.0) > 5.0  # heating at the ambient setpoint

    def frames(dropped: int | None = None, corrupt: bool = False, at_least: int = 0) -> Callable[[], None]:
        def check() -> None:
            # 5 real seconds for late frames: once, beside CI's other busy worker, 1 s saw none of a record's.
            rec = _record(lab, timeout_s=5.0)
            assert rec.dropped >= at_least and (dropped is None or rec.dropped == dropped), rec.dropped
            assert (rec.corrupt > 0) == corrupt
        return check

    def table_fault() -> None:
        st = table.status()
        assert st.mode == "FAULT" and st.fault == "E17"
        with pytest.raises(InstrumentRefused, match="TABLE FAULT"):
            table.jog(10.0)

    def overspeed(factor: float) -> Callable[[], None]:
        def check() -> None:
            table.jog(10.0)
            lab.clock.sleep(5.0)
            assert table.velocity() == pytest.approx(10.0 * factor, rel=1e-3)
        return check

    def imu_temp(hot: bool) -> Callable[[], None]:
        def check() -> None:
            lab.clock.sleep(1.0)
            sample = imu.latest()
            assert sample is not None and ((sample.temp_c > 80.0) if hot else (sample.temp_c < 40.0)), sample
        return check

    def link_lost() -> None:
        assert _wait_for(lambda: imu.link_drops >= 1)

    def link_restored() -> None:
        # A dry run reopens the line at the clock's next barrier: a record's sleep brings it back.
        assert _wait_for(lambda: _record(lab, 2.0).dropped == 0)
        assert imu.link_up

    return {
        K.MODBUS_TIMEOUT: ({}, _fails(ch.read_setpoint, InstrumentTimeout, "no valid answer"), reads),
        K.MODBUS_EXCEPTION: ({"count": 10}, _fails(ch.read_setpoint, InstrumentRefused, "Modbus exception 4"), reads),
        K.MODBUS_BUSY: ({"count": 10}, _fails(ch.read_setpoint, InstrumentError, "Modbus exception 6"), reads),
        K.MODBUS_DROP: ({}, reads, reads),  # one-shot: the driver reconnects at once
        K.MODBUS_OUTAGE: ({}, outage_check, lambda: (ch.connect(), reads())),
        K.HEATER_FAILURE: ({}, heats(True), heats(False)),
        K.COMPRESSOR_FAILURE: ({}, cools(True), cools(False)),
        K.GARBAGE_PV: ({}, _fails(ch.read_temperature, InstrumentProtocolError, "not a plausible temperature"),
                       lambda: ch.read_temperature()),
        K.TABLE_FAULT: ({}, table_fault, answers),
        K.TABLE_SILENT: ({}, _fails(table.status, InstrumentTimeout, "no reply"), answers),
        K.TABLE_GARBAGE: ({}, _fails(table.status, InstrumentProtocolError, "garbage reply"), answers),
        K.IMU_STALL: ({"duration_s": 5.0}, frames(at_least=200), frames(dropped=0)),
        K.IMU_CORRUPT: ({"count": 3}, frames(dropped=3, corrupt=True), frames(dropped=0)),
        K.IMU_GAP: ({"count": 4}, frames(dropped=4), frames(dropped=0)),
        K.TABLE_LINK_DROP: ({}, _fails(table.status, InstrumentError, "rate table"), answers),
        K.IMU_LINK_DROP: ({}, link_lost, link_restored),
        K.HEATER_STUCK: ({}, stuck_heater, lambda: None),
        K.TABLE_OVERSPEED: ({}, overspeed(1.6), overspeed(1.0)),
        K.IMU_OVERHEAT: ({}, imu_temp(True), imu_temp(False)),
    }


def test_the_kinds_are_one_vocabulary() -> None:
    assert KINDS == tuple(k.value for k in FaultKind)
    assert set(RANDOM_KINDS) == {k.value for k in FaultKind if k not in INTERLOCK_KINDS}


@pytest.mark.parametrize("kind", list(FaultKind), ids=str)
def test_fault_shows_and_clears(lab: Lab, kind: FaultKind) -> None:
    assert isinstance(lab.sim, FaultTarget)
    symptoms = _symptoms(lab)
    assert set(symptoms) == set(FaultKind)  # every kind has a symptom here
    params, while_on, after_clear = symptoms[kind]
    if kind is K.HEATER_STUCK:
        lab.sim.apply_fault(kind)
        while_on()
        lab.sim.clear_fault(kind)
        assert _air_after(lab, 23.0, 1800.0) < -5.0  # the controller brings it back down
        return
    lab.sim.apply_fault(kind.value, **params)  # by name, as a fault plan stores it
    while_on()
    lab.sim.clear_fault(kind)
    after_clear()


def test_unknown_kind_is_refused(lab: Lab) -> None:
    assert lab.sim is not None
    with pytest.raises(ValueError, match=r"unknown fault kind 'modbus_flood'; known: modbus_timeout, "):
        lab.sim.apply_fault("modbus_flood")
