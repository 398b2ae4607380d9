"""The Modbus chamber driver against the simulated controller, over TCP and RTU-over-socket."""

import socket
import time

import pytest
from pymodbus.client import ModbusTcpClient

from labrunner.drivers.chamber_modbus import ModbusAddress, ModbusChamber
from labrunner.drivers.chamber_profiles import PROFILES, profile_from
from labrunner.drivers.errors import InstrumentProtocolError, InstrumentRefused, InstrumentTimeout, LimitError
from labrunner.sims.chamber_server import ChamberServer
from labrunner.sims.world import SimLabConfig, SimWorld

from .expected_bytes import ExpectedLine, modbus_crc, rtu


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
    ch.units()  # the decimal places and units are read first, at connect
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
        assert ch.read_setpoint() == -12.25 and ch.current_setpoint() == -12.25
        lo, hi = ch.read_words(2782, 2)
        assert (hi << 16 | lo) == 0xC1440000  # -12.25 as IEEE float, low word first
        assert ch.setpoint_range() == (-70.0, 180.0)  # read from 2774/2776
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


# --- exact bytes (the registers from Espec's ChamberConnectLibrary watlowf4.py / watlowf4t.py) ----------


def _rtu_driver(line, profile, clock):
    return ModbusChamber(ModbusAddress(transport="rtu", serial_port=line.url, baudrate=19200, device_id=1), profile,
                         timeout_s=1.0, retries=0, sleep=clock.sleep)


def test_the_crc_helper_gives_the_textbook_frame():
    assert rtu("010300000001") == bytes.fromhex("010300000001840a")  # read 1 holding register at 0, device 1
    assert modbus_crc(b"") == b"\xff\xff"


def test_watlow_f4_in_fahrenheit_with_one_decimal_exact_bytes(clock):
    """An F4 set to deg F with one decimal: 606 reads 1, 901 reads 0 (F); every value is converted."""
    line = ExpectedLine([
        (rtu("0103025e0001"), rtu("0103020001")),          # 606 decimal places -> 1
        (rtu("010303850001"), rtu("0103020000")),          # 901 units -> 0: deg F
        (rtu("010300640001"), rtu("01030202d5")),          # 100 process value -> 725 = 72.5 F
        (rtu("0103025a0001"), rtu("010302fc18")),          # 602 range low -> -1000 = -100.0 F
        (rtu("0103025b0001"), rtu("0103020dac")),          # 603 range high -> 3500 = 350.0 F
        (rtu("0106012cff7e"), rtu("0106012cff7e")),        # write 300 <- -130 = -13.0 F (-25 C); echoed
        (rtu("0103012c0001"), rtu("010302ff7e")),          # read back 300 -> -13.0 F
    ])
    ch = _rtu_driver(line, "watlow_f4", clock)
    try:
        assert ch.read_temperature() == pytest.approx(22.5)  # 72.5 F
        assert ch.setpoint_range() == pytest.approx((-73.333333, 176.666667))
        ch.set_setpoint(-25.0)
    finally:
        ch.close()
    line.check()
    assert (ch.units().fahrenheit, ch.units().decimals) == (True, 1)


def test_watlow_f4_whole_degrees_celsius_exact_bytes(clock):
    line = ExpectedLine([
        (rtu("0103025e0001"), rtu("0103020000")),          # 606 -> 0 decimals
        (rtu("010303850001"), rtu("0103020001")),          # 901 -> 1: deg C
        (rtu("010300640001"), rtu("010302ffe7")),          # 100 -> -25 = -25 C
    ])
    ch = _rtu_driver(line, "watlow_f4", clock)
    try:
        assert ch.read_temperature() == -25.0
    finally:
        ch.close()
    line.check()


def test_watlow_f4_refuses_a_units_register_it_cannot_read(clock):
    line = ExpectedLine([(rtu("0103025e0001"), rtu("0103020001")), (rtu("010303850001"), rtu("0103020007"))])
    ch = _rtu_driver(line, "watlow_f4", clock)
    try:
        with pytest.raises(InstrumentProtocolError, match=r"register 901: units register reads 7, expected 0 \(F\)"):
            ch.read_temperature()
    finally:
        ch.close()
    line.check()


def test_watlow_f4t_sourced_map_exact_bytes(clock):
    """F4T loop 1: range 2774/2776, setpoint 2782, working setpoint 2810, PV 2820; float32, low word first."""
    line = ExpectedLine([
        (rtu("01030ad60002"), rtu("0103040000c292")),      # 2774 range min -> -73.0 (0xC2920000)
        (rtu("01030ad80002"), rtu("01030400004343")),      # 2776 range max -> 195.0 (0x43430000)
        (rtu("01100ade000204" "0000c144"), rtu("01100ade0002")),  # write 2782 <- -12.25 (0xC1440000)
        (rtu("01030ade0002"), rtu("0103040000c144")),      # read back 2782
        (rtu("01030afa0002"), rtu("0103040000c144")),      # 2810 working setpoint
        (rtu("01030b040002"), rtu("0103040000420c")),      # 2820 process value -> 35.0 (0x420C0000)
    ])
    ch = _rtu_driver(line, "watlow_f4t", clock)
    try:
        assert ch.setpoint_range() == (-73.0, 195.0)
        ch.set_setpoint(-12.25)
        assert ch.current_setpoint() == -12.25
        assert ch.read_temperature() == 35.0
    finally:
        ch.close()
    line.check()


def test_watlow_f4t_loop_two_is_160_registers_on():
    p = PROFILES["watlow_f4t"].for_loop(2)
    assert (p.setpoint, p.current_setpoint, p.process_value, p.setpoint_min, p.setpoint_max) == (
        2942, 2970, 2980, 2934, 2936)
    with pytest.raises(ValueError, match="one control loop"):
        PROFILES["watlow_f4"].for_loop(2)


# --- the driver against the simulated F4 in other units ------------------------------------------------


@pytest.mark.parametrize(("units", "decimals"), [("F", 1), ("F", 0), ("C", 0), ("C", 2)])
def test_driver_against_a_sim_in_other_units(clock, units, decimals):
    world = SimWorld(SimLabConfig.from_dict({"seed": 7, "chamber": {"controller_units": units,
                                                                    "controller_decimals": decimals}}), clock.now())
    srv = ChamberServer(world, clock, "watlow_f4")
    try:
        ch = _driver(srv.port, clock)
        ident = ch.identity()
        assert (ident.extra["units"], ident.extra["decimals"]) == (units, str(decimals))
        assert ch.setpoint_range() == pytest.approx((-70.0, 180.0), abs=0.3)
        assert ch.read_temperature() == pytest.approx(23.0, abs=0.6)
        ch.set_setpoint(-25.0)
        step = 10.0 ** -decimals * (5 / 9 if units == "F" else 1.0)
        assert ch.read_setpoint() == pytest.approx(-25.0, abs=step / 2 + 1e-9)
        clock.sleep(4 * 3600)
        assert ch.read_temperature() == pytest.approx(-25.0, abs=0.3 + step)
        # What is on the wire is in the controller's units: -25 C is -13 F.
        raw = ch.read_words(300, 1)[0]
        raw = raw - 0x10000 if raw & 0x8000 else raw
        shown = -13.0 if units == "F" else -25.0
        assert raw == round(shown * 10 ** decimals)
    finally:
        srv.close()


def test_sim_refuses_units_its_profile_cannot_report(clock):
    world = SimWorld(SimLabConfig.from_dict({"chamber": {"controller_units": "F"}}), clock.now())
    with pytest.raises(ValueError, match="profile 'watlow_f4t' has no units register"):
        ChamberServer(world, clock, "watlow_f4t")
