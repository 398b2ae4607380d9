"""A dry run's lines inside the process (`sims.links.MemoryPort`, `labsim://`) carry the protocols' exact bytes.

The drivers open them as any serial line; the table server, the chamber's pymodbus RTU framer and the
IMU stream answer in the driver's thread. These tests look at the bytes on the line (taps on the port),
not at what the drivers made of them only.
"""

from __future__ import annotations

import threading

import pytest
import serial

from labrunner.clock import VirtualClock
from labrunner.fault_kinds import FaultKind
from labrunner.lab import Lab
from labrunner.sims.links import MemoryPort
from tests.drivers.expected_bytes import rtu
from tests.sim_lab import connected_lab  # noqa: F401 - the `lab` fixture


class Tap:
    """Records what the driver writes to a port's server and what the server writes back."""

    def __init__(self, port: MemoryPort) -> None:
        self.sent: list[bytes] = []
        self.replies: list[bytes] = []
        serve = port._server
        assert serve is not None, "the port has a server"
        write = port.write

        def on_request(data: bytes) -> None:
            self.sent.append(data)
            serve(data)

        def on_reply(data: bytes) -> int:
            self.replies.append(data)
            return write(data)

        port.attach_server(on_request)
        port.write = on_reply  # type: ignore[method-assign]




def test_a_memory_line_passes_every_byte_both_ways() -> None:
    port = MemoryPort("echo")
    got: list[bytes] = []

    def serve(data: bytes) -> None:  # answers each request with its bytes reversed, then a terminator
        got.append(data)
        port.write(data[::-1] + b"\r\n")

    port.attach_server(serve)
    ser = serial.serial_for_url(port.url, baudrate=115200, timeout=0)
    try:
        payload = bytes(range(256))
        assert ser.write(payload) == 256
        assert got == [payload]
        assert ser.in_waiting == 258
        assert ser.read_until(b"\r\n") == payload[::-1] + b"\r\n"  # reversed, 0D and 0A are not adjacent
        port.write(b"A\r\nB")
        assert ser.read_until(b"\r\n") == b"A\r\n"
        assert ser.read(10) == b"B"  # what is there, without waiting (timeout 0)
        assert ser.read(10) == b""
    finally:
        ser.close()
        port.close()
    assert MemoryPort.lookup(port.url) is None


def test_a_lost_memory_line_gives_what_was_sent_then_fails() -> None:
    port = MemoryPort("lossy")
    ser = serial.serial_for_url(port.url, baudrate=115200, timeout=0)
    told: list[str] = []
    ser.on_lost = lambda: told.append("lost")
    port.write(b"last frame")
    port.refuse(True)
    assert told == ["lost"]
    assert ser.read(100) == b"last frame"
    with pytest.raises(serial.SerialException, match="connection lost"):
        ser.read(100)
    assert port.write(b"nobody") == 0 and port.dropped_bytes == 6
    with pytest.raises(serial.SerialException, match="connection refused"):
        serial.serial_for_url(port.url, baudrate=115200, timeout=0)
    port.refuse(False)
    again = serial.serial_for_url(port.url, baudrate=115200, timeout=0)
    port.write(b"x")
    assert again.read(1) == b"x"
    again.close()
    port.close()


def test_the_chamber_is_modbus_rtu_frames_on_the_memory_line(lab: Lab) -> None:
    assert lab.sim is not None
    line = lab.sim.chamber.line
    assert line is not None, "a dry run serves the chamber on a memory line"
    lab.chamber.read_temperature()  # the controller's units and decimals are read once per connection
    lab.chamber.setpoint_range()
    tap = Tap(line.port)
    pv = lab.chamber.read_temperature()
    # Watlow F4: process value in holding register 100, tenths of a degree, one 16-bit word.
    assert tap.sent == [rtu("01 03 0064 0001")]
    word = round(pv * 10) & 0xFFFF
    assert tap.replies == [rtu(f"01 03 02 {word:04x}")]
    lab.chamber.set_setpoint(-20.0)
    write = rtu(f"01 06 012c {(-200) & 0xFFFF:04x}")  # setpoint register 300 <- -20.0 C
    assert tap.sent[1:] == [write, rtu("01 03 012c 0001")]  # written, then read back
    assert tap.replies[1:] == [write, rtu(f"01 03 02 {(-200) & 0xFFFF:04x}")]  # a write's reply echoes it


def test_the_table_speaks_its_language_on_the_memory_line(lab: Lab) -> None:
    assert lab.sim is not None
    tap = Tap(lab.sim.table_port)  # type: ignore[arg-type]
    lab.table.jog(20.0)
    lab.clock.sleep(30.0)
    rate = lab.table.velocity()
    assert tap.sent == [b"JOG+20.0000\r\n", b"PVE\r\n"]
    assert tap.replies[0] == b"OK\r\n"
    assert tap.replies[1].startswith(b"PVE ") and tap.replies[1].endswith(b"\r\n")
    assert float(tap.replies[1][4:-2]) == rate == pytest.approx(20.0, abs=0.01)


def test_the_imu_stream_is_read_in_the_callers_thread(lab: Lab) -> None:
    assert lab.sim is not None
    names = {t.name for t in threading.enumerate()}
    assert not {"imu-reader", "sim-table", "sim-modbus"} & names, names  # no thread between driver and sim
    start = lab.imu.begin_record()
    lab.clock.sleep(10.0)
    rec = lab.imu.end_record(start, 500, timeout_s=5.0)
    assert len(rec) == 500 and rec.dropped == 0
    assert lab.imu.bytes_received == lab.sim.imu_port.bytes_written  # type: ignore[attr-defined]
    assert lab.sim.imu_port.bytes_written == 20 * lab.sim.imu.frames_sent  # the 20-byte frames, all read


def test_an_imu_link_drop_on_the_memory_line_is_seen_at_once_and_healed(lab: Lab) -> None:
    assert lab.sim is not None
    lab.sim.apply_fault(FaultKind.IMU_LINK_DROP)
    assert lab.imu.link_drops == 1 and not lab.imu.link_up  # no thread to notice it later: told by the line
    lab.sim.clear_fault(FaultKind.IMU_LINK_DROP)
    lab.clock.sleep(1.0)  # the barrier reopens the line after this advance (its frames were sent to nobody)
    assert lab.imu.link_up and lab.imu.link_drops == 1
    lab.clock.sleep(1.0)  # frames arrive again (a record counts from the newest frame received)
    start = lab.imu.begin_record()
    lab.clock.sleep(2.0)
    rec = lab.imu.end_record(start, 100, timeout_s=1.0)
    assert rec.dropped == 0 and len(rec) == 100


def test_memory_links_need_a_virtual_clock() -> None:
    from labrunner.clock import ScaledClock
    from labrunner.sims.lab import SimLab
    from labrunner.sims.world import SimLabConfig

    with pytest.raises(ValueError, match="needs a virtual clock"):
        SimLab(SimLabConfig(), ScaledClock(10.0), link="memory")
    lab = SimLab(SimLabConfig(), VirtualClock(), link="memory")
    try:
        assert lab.lab_config()["chamber"]["serial_port"].startswith("labsim://chamber-")
    finally:
        lab.close()
