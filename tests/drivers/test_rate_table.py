"""The rate-table driver: exact bytes on the wire, and against the simulated table over TCP and a pty."""

import os
import select
import threading
import tty

import pytest

from labrunner.drivers.errors import InstrumentProtocolError, InstrumentRefused, InstrumentTimeout, LimitError
from labrunner.drivers.protocols import Identity, TableStatus
from labrunner.drivers.rate_table import SerialRateTable
from labrunner.drivers.table_profiles import language_from
from labrunner.sims.links import PtyPort, TcpSerialPort
from labrunner.sims.table_server import TableServer

from .expected_bytes import ExpectedLine


class ScriptedPeer:
    """A pty whose far end records exactly what the driver sends and replies from a script."""

    def __init__(self, replies):
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.url = os.ttyname(slave)
        self._slave = slave
        self.received = b""
        self.replies = list(replies)
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        buf = b""
        while self.replies:
            r, _, _ = select.select([self.master], [], [], 2)
            if not r:
                return
            chunk = os.read(self.master, 1024)
            self.received += chunk
            buf += chunk
            while b"\r\n" in buf and self.replies:
                _, buf = buf.split(b"\r\n", 1)
                reply = self.replies.pop(0)
                if reply is not None:
                    os.write(self.master, reply)


def test_exact_bytes_of_each_command():
    peer = ScriptedPeer([b"OK\r\n", b"OK\r\n", b"PVE -99.99870\r\n", b"STA JOG SETTLED\r\n", b"IDN ACME,RT9,42\r\n"])
    t = SerialRateTable(peer.url, max_rate_dps=150, timeout_s=0.5, retries=0)
    t.jog(-100)
    t.stop()
    assert t.velocity() == -99.9987
    assert t.status().settled
    assert t.identity().model == "RT9"
    assert peer.received == b"JOG-100.0000\r\nSTO\r\nPVE\r\nSTA\r\nIDN\r\n"


def test_rate_beyond_limit_is_refused_before_sending():
    peer = ScriptedPeer([b"OK\r\n"])
    t = SerialRateTable(peer.url, max_rate_dps=100, timeout_s=0.3, retries=0)
    with pytest.raises(LimitError, match="rate 100.5 deg/s exceeds the configured limit 100.0"):
        t.jog(100.5)
    with pytest.raises(LimitError):
        t.jog(float("nan"))
    t.jog(-100.0)
    assert peer.received == b"JOG-100.0000\r\n"


def test_unexpected_reply_is_retried_then_reported():
    peer = ScriptedPeer([b"PVE banana\r\n", b"PVE 12.5\r\n"])
    t = SerialRateTable(peer.url, max_rate_dps=100, timeout_s=0.3, retries=1, backoff_s=0.0)
    assert t.velocity() == 12.5
    peer = ScriptedPeer([b"HELLO\r\n", b"HELLO\r\n"])
    t = SerialRateTable(peer.url, max_rate_dps=100, timeout_s=0.3, retries=1, backoff_s=0.0)
    with pytest.raises(InstrumentProtocolError, match=r"command 'PVE': unexpected reply 'HELLO'"):
        t.velocity()


@pytest.fixture(params=["tcp", "pty"])
def table(request, world, clock):
    port = TcpSerialPort() if request.param == "tcp" else PtyPort()
    srv = TableServer(world, clock, port)
    drv = SerialRateTable(port.url, max_rate_dps=200, timeout_s=0.3, retries=1, backoff_s=0.01, sleep=clock.sleep)
    drv.connect()
    yield drv, srv, clock
    drv.close()
    srv.close()
    port.close()


def test_acceleration_limited_and_accurate(table):
    drv, srv, clock = table
    assert drv.identity().model == "RT-SIM-1"
    assert drv.limits() == (1000.0, 100.0)
    drv.jog(100.0)
    assert not drv.status().settled
    clock.sleep(0.5)
    assert drv.velocity() == pytest.approx(50.0, rel=0.02)
    clock.sleep(2.0)
    st = drv.status()
    assert st.mode == "JOG" and st.settled
    assert abs(drv.velocity() / 100.0 - 1.0) <= 1.0001e-4  # +-0.01 %
    drv.stop()
    clock.sleep(2.0)
    assert drv.velocity() == 0.0


def test_garbage_silence_and_fault(table):
    drv, srv, clock = table
    srv.faults.garbage = True
    with pytest.raises(InstrumentProtocolError, match="garbage reply|unexpected reply"):
        drv.velocity()
    srv.faults.garbage = False
    srv.faults.silent = True
    with pytest.raises(InstrumentTimeout, match=r"command 'PVE': no reply within 0.3 s"):
        drv.velocity()
    srv.faults.silent = False
    srv.faults.fault = "E17 OVERCURRENT"
    assert drv.status().fault == "E17"
    with pytest.raises(InstrumentRefused, match="error 5: TABLE FAULT E17"):
        drv.jog(10.0)
    srv.faults.fault = None
    drv.jog(10.0)  # recovers


def test_link_that_drops_is_reopened(world, clock):
    port = TcpSerialPort()
    srv = TableServer(world, clock, port)
    drv = SerialRateTable(port.url, max_rate_dps=200, timeout_s=0.3, retries=2, backoff_s=0.01, sleep=clock.sleep)
    try:
        assert drv.velocity() == 0.0
        port.disconnect()
        assert drv.velocity() == 0.0  # the driver notices, reopens and asks again
    finally:
        drv.close()
        srv.close()
        port.close()


# --- languages as profiles: exact bytes of each, and the driver against the sim speaking it -----------


def test_labrunner_language_exact_bytes_on_a_socket_line():
    line = ExpectedLine([
        (b"IDN\r\n", b"IDN LABRUNNER,RT-SIM-1,SN0001\r\n"),
        (b"LIM\r\n", b"LIM 1000.0 100.0\r\n"),
        (b"JOG+12.5000\r\n", b"OK\r\n"),
        (b"STA\r\n", b"STA JOG RAMPING\r\n"),
        (b"PVE\r\n", b"PVE +12.49990\r\n"),
        (b"STO\r\n", b"OK\r\n"),
        (b"JOG+999.0000\r\n", b"ERR 3 RATE OUT OF RANGE\r\n"),
    ])
    t = SerialRateTable(line.url, max_rate_dps=1000, timeout_s=1.0, retries=0)
    try:
        assert t.identity() == Identity("LABRUNNER", "RT-SIM-1", "SN0001", {"language": "labrunner"})
        assert t.limits() == (1000.0, 100.0)
        t.jog(12.5)
        assert t.status() == TableStatus(mode="JOG", settled=False)
        assert t.velocity() == 12.4999
        t.stop()
        with pytest.raises(InstrumentRefused, match="error 3: RATE OUT OF RANGE"):
            t.jog(999.0)
    finally:
        t.close()
    line.check()


def test_ideal_aerosmith_language_exact_bytes():
    """JOG/STO/SRV/HOM, queries ending in '?', actions answered by the bare terminator (table_profiles)."""
    line = ExpectedLine([
        (b"SRV 1\r\n", b"\r\n"),               # servo on, once per connection, before the first jog
        (b"JOG 12.5000\r\n", b"\r\n"),
        (b"JOG?\r\n", b"12.4998\r\n"),         # status from the velocity: within 0.1 % + 0.01 of the command
        (b"JOG -30.0000\r\n", b"\r\n"),
        (b"JOG?\r\n", b"-3.2000\r\n"),         # still ramping
        (b"PPO?\r\n", b"123.4560\r\n"),
        (b"STO\r\n", b"\r\n"),
        (b"HOM\r\n", b"\r\n"),
    ])
    t = SerialRateTable(line.url, max_rate_dps=300, timeout_s=1.0, retries=0, language="ideal_aerosmith")
    try:
        assert t.identity().vendor == "Ideal Aerosmith"  # no identity query in the sources: the profile's
        assert t.limits() == (360.0, 100.0)
        t.jog(12.5)
        assert t.status() == TableStatus(mode="JOG", settled=True)
        t.jog(-30.0)
        assert t.status() == TableStatus(mode="JOG", settled=False)
        assert t.position() == 123.456
        t.stop()
        t.home()
    finally:
        t.close()
    line.check()


def test_a_custom_language_is_configuration():
    lang = language_from({"base": "ideal_aerosmith", "name": "cr_only", "terminator": "\r"})
    line = ExpectedLine([(b"JOG?\r", b"0.0000\r")])
    t = SerialRateTable(line.url, max_rate_dps=300, timeout_s=1.0, retries=0, language=lang)
    try:
        assert t.velocity() == 0.0
    finally:
        t.close()
    line.check()
    with pytest.raises(ValueError, match=r"unknown table language 'nope'; known: labrunner, ideal_aerosmith"):
        language_from("nope")
    with pytest.raises(ValueError, match=r"the jog command needs a \{rate\} field"):
        language_from({"base": "labrunner", "commands": {"jog": "JOG"}})
    with pytest.raises(ValueError, match=r"reply of 'velocity' has unknown field\(s\) speed"):
        language_from({"base": "labrunner", "replies": {"velocity": "PVE {speed:f}"}})


@pytest.fixture
def ideal_table(world, clock):
    port = TcpSerialPort()
    srv = TableServer(world, clock, port, language="ideal_aerosmith")
    drv = SerialRateTable(port.url, max_rate_dps=200, timeout_s=0.3, retries=1, backoff_s=0.01, sleep=clock.sleep,
                          language="ideal_aerosmith")
    yield drv, srv, clock
    drv.close()
    srv.close()
    port.close()


def test_ideal_aerosmith_driver_against_the_sim(ideal_table):
    drv, srv, clock = ideal_table
    assert not srv.servo_on
    drv.jog(100.0)
    assert srv.servo_on and srv.commands == 2  # SRV 1, then JOG
    assert not drv.status().settled
    clock.sleep(0.5)
    assert drv.velocity() == pytest.approx(50.0, rel=0.02)
    clock.sleep(2.0)
    assert drv.status() == TableStatus(mode="JOG", settled=True)
    assert abs(drv.velocity() / 100.0 - 1.0) <= 1.0001e-4
    a0 = drv.position()
    clock.sleep(1.0)
    assert (drv.position() - a0) % 360.0 == pytest.approx(100.0, abs=0.1)  # 100 deg/s for 1 s
    drv.stop()
    clock.sleep(2.0)
    assert drv.velocity() == 0.0 and drv.status() == TableStatus(mode="STOP", settled=True)


def test_ideal_aerosmith_sim_leaves_a_refused_jog_unanswered(ideal_table):
    drv, srv, clock = ideal_table
    srv.faults.fault = "E17 OVERCURRENT"
    with pytest.raises(InstrumentTimeout, match=r"command 'JOG 10.0000': no reply"):
        drv.jog(10.0)
    srv.faults.fault = None
    drv.jog(10.0)
