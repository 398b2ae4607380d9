"""The Modbus chamber driver against the simulated controller, over TCP and RTU-over-socket."""

import socket
import time

import pytest
from pymodbus.client import ModbusTcpClient

from labrunner.drivers.chamber_modbus import ModbusAddress, ModbusChamber
from labrunner.drivers.chamber_profiles import PROFILES, profile_from
from labrunner.drivers.errors import InstrumentProtocolError, InstrumentRefused, InstrumentTimeout, LimitError
from labrunner.sims.chamber_server import ChamberServer


@pytest.fixture
def server(world, clock):
    srv = ChamberServer(world, clock, "watlow_f4")
    yield srv
    srv.close()


def _driver(port, clock, **kw):
    kw.setdefault("timeout_s", 0.3)
    kw.setdefault("retries", 1)
    kw.setdefault("backoff_s", 0.01)
    return ModbusChamber(ModbusAddress(port=port), "watlow_f4", sleep=clock.sleep, **kw)


def test_identity_range_and_negative_setpoint_over_tcp(server, clock):
    ch = _driver(server.port, clock)
    ch.connect()
    ident = ch.identity()
    assert (ident.vendor, ident.model, ident.extra["model_code"]) == ("Watlow", "F4", "5270")
    assert ch.setpoint_range() == (-70.0, 180.0)
    ch.set_setpoint(-25.0)
    assert ch.read_setpoint() == -25.0
    start = ch.read_temperature()
    clock.sleep(600)
    mid = ch.read_temperature()
    assert start - mid > 5.0  # cooling a few degrees per minute
    clock.sleep(4 * 3600)
    assert ch.read_temperature() == pytest.approx(-25.0, abs=0.3)
    heat, cool = ch.outputs()
    assert heat == 0.0 and 0.0 < cool < 100.0


def test_wire_encoding_of_a_negative_setpoint(server, clock):
    ch = _driver(server.port, clock)
    ch.set_setpoint(-25.0)
    raw = ch.read_words(300, 1)[0]
    assert raw == 0xFF06  # -250 tenths as a signed 16-bit register


def test_setpoint_outside_range_is_refused_before_writing(server, clock):
    ch = _driver(server.port, clock)
    ch.set_setpoint(10.0)
    before = server.requests
    with pytest.raises(LimitError,
                       match=r"register 300: setpoint -80.0 C is outside .* -70.0..180.0 C; nothing was written"):
        ch.set_setpoint(-80.0)
    # Only the (cached) range was consulted: no write reached the controller.
    assert server.requests == before
    assert ch.read_setpoint() == 10.0


def test_controller_refuses_a_bad_write_with_an_exception(server, clock):
    ch = _driver(server.port, clock)
    with pytest.raises(InstrumentRefused, match=r"register 100: write register: Modbus exception 2"):
        ch.write_words(100, [5])  # the process value is read-only


def test_exception_responses_are_named_and_transient_ones_retried(server, clock):
    ch = _driver(server.port, clock, retries=2)
    server.faults.exception_code = 4
    with pytest.raises(InstrumentRefused, match=r"chamber at modbus-tcp://127.0.0.1:\d+ \(device 1\), register 100: "
                                                r".*Modbus exception 4 \(server device failure\)"):
        ch.read_temperature()
    server.faults.clear()
    server.faults.exception_code, server.faults.exception_count = 6, 2  # busy twice, then fine
    assert ch.read_temperature() == pytest.approx(23.0, abs=0.5)


def test_server_that_stops_answering_times_out_after_bounded_retries(server, clock):
    ch = _driver(server.port, clock, retries=2, timeout_s=0.2)
    ch.read_temperature()
    server.faults.silent = True
    t0 = time.monotonic()
    with pytest.raises(InstrumentTimeout, match="register 100"):
        ch.read_temperature()
    elapsed = time.monotonic() - t0
    assert 0.5 < elapsed < 3.0  # three attempts of 0.2 s, backoff on the virtual clock


def test_garbage_process_value_is_an_error_not_a_reading(server, clock):
    ch = _driver(server.port, clock)
    server.faults.garbage_pv = True
    with pytest.raises(InstrumentProtocolError, match=r"register 100: process value reads 3276.7"):
        ch.read_temperature()


def test_dropped_connection_reconnects(server, clock):
    ch = _driver(server.port, clock)
    ch.read_temperature()
    assert server.drop_connections() == 1
    assert ch.read_temperature() == pytest.approx(23.0, abs=0.5)


def test_nothing_listening_names_the_address(clock):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ch = _driver(port, clock, retries=1)
    with pytest.raises(InstrumentTimeout, match=rf"chamber at modbus-tcp://127.0.0.1:{port} .*cannot connect"):
        ch.connect()


def test_rtu_framing_over_a_socket(world, clock):
    srv = ChamberServer(world, clock, "watlow_f4", transport="rtu")
    try:
        ch = ModbusChamber(ModbusAddress(transport="rtu", serial_port=srv.url, baudrate=115200), "watlow_f4",
                           timeout_s=0.5, retries=1, sleep=clock.sleep)
        assert ch.identity().model == "F4"
        ch.set_setpoint(-20.5)
        assert ch.read_setpoint() == -20.5
    finally:
        srv.close()


def test_float_profile_is_data_not_code(world, clock):
    srv = ChamberServer(world, clock, "watlow_f4t")
    try:
        ch = ModbusChamber(ModbusAddress(port=srv.port), "watlow_f4t", timeout_s=0.3, sleep=clock.sleep)
        ch.set_setpoint(-12.25)
        assert ch.read_setpoint() == -12.25
        lo, hi = ch.read_words(2160, 2)
        assert (hi << 16 | lo) == 0xC1440000  # -12.25 as IEEE float, low word first
        with pytest.raises(LimitError):
            ch.set_setpoint(-100.0)
    finally:
        srv.close()
    custom = profile_from({"base": "watlow_f4", "name": "my_f4", "process_value": 110})
    assert custom.process_value == 110 and custom.setpoint == 300
    with pytest.raises(ValueError, match="unknown chamber profile"):
        profile_from("nope")


@pytest.mark.parametrize("name", sorted(PROFILES))
def test_profiles_encode_and_decode_negative_values(name):
    p = PROFILES[name]
    for v in (-25.0, -0.1, 0.0, 55.5):
        assert p.decode(p.encode(v)) == pytest.approx(v, abs=1e-6)


def test_independent_client_sees_the_same_registers(server, clock):
    # A plain pymodbus client, not this project's driver.
    c = ModbusTcpClient("127.0.0.1", port=server.port, timeout=1)
    assert c.connect()
    try:
        assert not c.write_register(300, (-250) & 0xFFFF, device_id=1).isError()
        clock.sleep(300)
        pv = c.read_holding_registers(100, count=1, device_id=1).registers[0]
        pv = (pv - 0x10000 if pv & 0x8000 else pv) / 10
        assert pv < 15.0
        assert c.read_holding_registers(602, count=2, device_id=1).registers == [(-700) & 0xFFFF, 1800]
    finally:
        c.close()
