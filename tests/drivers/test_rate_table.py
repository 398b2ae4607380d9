"""The rate-table driver: exact bytes on the wire, and against the simulated table over TCP and a pty."""

import os
import select
import threading
import tty

import pytest

from labrunner.drivers.errors import InstrumentProtocolError, InstrumentRefused, InstrumentTimeout, LimitError
from labrunner.drivers.rate_table import SerialRateTable
from labrunner.sims.links import PtyPort, TcpSerialPort
from labrunner.sims.table_server import TableServer


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
