"""Logging: wire traffic at DEBUG from the drivers talking to the simulated lab, retries and link
losses at INFO/WARNING, and nothing on stderr unless the application asks for it."""

from __future__ import annotations

import io
import logging
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator

import pytest

from labrunner.fault_kinds import FaultKind
from labrunner.lab import Lab, simulated_lab
from labrunner.logs import configure

LOGGERS = ("labrunner", "pymodbus", "transitions", "matplotlib", "PIL")


@pytest.fixture(autouse=True)
def restore_logging() -> Iterator[None]:
    """configure() (also called by in-process CLI tests) rewires loggers: undo it around each test."""
    saved = {n: (list(lg.handlers), lg.level, lg.propagate) for n in LOGGERS for lg in [logging.getLogger(n)]}
    logging.getLogger("labrunner").propagate = True  # caplog listens at the root
    yield
    for name, (handlers, level, propagate) in saved.items():
        lg = logging.getLogger(name)
        lg.handlers[:], lg.level, lg.propagate = handlers, level, propagate


@pytest.fixture
def lab(caplog: pytest.LogCaptureFixture) -> Iterator[Lab]:
    caplog.set_level(logging.DEBUG, logger="labrunner")  # from the connects on
    lab = simulated_lab(max_rate_dps=150.0)
    lab.chamber.connect()
    lab.table.connect()
    lab.imu.connect()
    yield lab
    lab.close()


def _messages(caplog: pytest.LogCaptureFixture, logger: str, level: int | None = None) -> list[str]:
    return [r.getMessage() for r in caplog.get_records("setup") + caplog.records
            if r.name == logger and (level is None or r.levelno == level)]


def _wait_for(condition, timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.05)
    return False


def test_drivers_log_wire_traffic_at_debug(caplog: pytest.LogCaptureFixture, lab: Lab) -> None:
    lab.chamber.set_setpoint(30.0)
    lab.chamber.read_temperature()
    lab.table.jog(10.0)
    lab.table.velocity()
    start = lab.imu.begin_record()
    lab.clock.sleep(10.0)  # 500 frames at 50 Hz
    rec = lab.imu.end_record(start, 500, timeout_s=2.0)
    assert rec.dropped == 0

    modbus = _messages(caplog, "labrunner.drivers.chamber_modbus", logging.DEBUG)
    assert "chamber: write 1 register(s) at 300 <- [300]" in modbus  # setpoint 30.0 C in tenths
    assert "chamber: read 1 register(s) at 300 -> [300]" in modbus  # read back
    assert any(m.startswith("chamber: read 1 register(s) at 100 -> [") for m in modbus)  # the process value
    table = _messages(caplog, "labrunner.drivers.rate_table", logging.DEBUG)
    assert table[:4] == [r"rate table: tx b'JOG+10.0000\r\n'", r"rate table: rx b'OK\r\n'",
                         r"rate table: tx b'PVE\r\n'", table[3]]
    assert table[3].startswith("rate table: rx b'PVE +")
    imu = _messages(caplog, "labrunner.drivers.imu_serial")
    assert any("stream open at" in m for m in imu)
    assert f"imu: record after counter {start}: 500 of 500 frames, 0 corrupt stretch(es)" in imu
    assert len(imu) < 10  # summaries, not one line per frame


def test_retries_resyncs_and_link_losses_are_logged(caplog: pytest.LogCaptureFixture, lab: Lab) -> None:
    assert lab.sim is not None
    lab.sim.apply_fault(FaultKind.MODBUS_BUSY, count=1)
    lab.chamber.read_setpoint()  # busy once, then answered
    retries = _messages(caplog, "labrunner.drivers.retry", logging.INFO)
    assert len(retries) == 1 and retries[0].startswith("retry 1 of 2 in ")
    assert "Modbus exception 6" in retries[0]

    lab.sim.apply_fault(FaultKind.IMU_CORRUPT, count=3)
    start = lab.imu.begin_record()
    lab.clock.sleep(2.0)
    lab.imu.end_record(start, 100, timeout_s=1.0)
    assert any("resynchronised after" in m for m in _messages(caplog, "labrunner.drivers.imu_serial", logging.DEBUG))

    lab.sim.apply_fault(FaultKind.IMU_LINK_DROP, duration_s=1.0)
    assert _wait_for(lambda: any("link lost" in m for m in _messages(
        caplog, "labrunner.drivers.imu_serial", logging.WARNING)))
    lab.sim.clear_fault(FaultKind.IMU_LINK_DROP)
    lab.clock.sleep(2.0)  # on a dry run the lost line is reopened at a clock advance (virtual time), not by the reader
    assert _wait_for(lambda: any("link restored" in m for m in _messages(
        caplog, "labrunner.drivers.imu_serial", logging.INFO)))


def test_default_level_prints_nothing_and_keeps_pymodbus_quiet(lab: Lab) -> None:
    # (the lab fixture's DEBUG level for caplog is replaced by configure's WARNING)
    stream = io.StringIO()
    configure("WARNING", stream=stream)  # what the CLI does without -v
    lab.chamber.set_setpoint(25.0)
    lab.table.jog(5.0)
    start = lab.imu.begin_record()
    lab.clock.sleep(5.0)
    lab.imu.end_record(start, 250, timeout_s=2.0)
    assert stream.getvalue() == ""
    # Refused connections: pymodbus logs an ERROR for each, the driver reports them itself.
    assert lab.sim is not None
    lab.sim.apply_fault(FaultKind.MODBUS_OUTAGE)
    lab.chamber.close()
    with pytest.raises(Exception, match="cannot connect"):
        lab.chamber.connect()
    lab.sim.clear_fault(FaultKind.MODBUS_OUTAGE)
    out = stream.getvalue()
    assert "pymodbus" not in out and "Connection to" not in out, out
    assert "WARNING labrunner.drivers.retry: giving up after 3 attempt(s)" in out


def test_unconfigured_logging_prints_nothing() -> None:
    # A script that uses labrunner without configuring logging: the warnings labrunner logs on retries
    # and lost links must not reach stderr through Python's last-resort handler.
    script = textwrap.dedent("""
        import time
        from labrunner.drivers.errors import InstrumentError
        from labrunner.fault_kinds import FaultKind
        from labrunner.lab import simulated_lab

        lab = simulated_lab(max_rate_dps=150.0)
        lab.table.connect()
        lab.imu.connect()
        lab.table.jog(5.0)
        lab.sim.apply_fault(FaultKind.TABLE_SILENT)
        try:
            lab.table.velocity()
        except InstrumentError:
            pass
        lab.sim.clear_fault(FaultKind.TABLE_SILENT)
        lab.sim.apply_fault(FaultKind.IMU_LINK_DROP)
        deadline = time.monotonic() + 5
        while lab.imu.link_drops == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        lab.close()
        print("link drops", lab.imu.link_drops)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert int(proc.stdout.split()[-1]) >= 1  # the warning was logged
    assert proc.stderr == ""
