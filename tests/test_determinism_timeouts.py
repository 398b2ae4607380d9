"""The one timeout policy (`labrunner.clock.io_timeouts`): on a real line a reply slower than the configured
timeout is a timeout; on a link a simulator serves in virtual time the same slow reply is waited for, a
withheld reply times out at once with the configured seconds in the message, and a simulator that neither
answers nor withholds is reported as hanging after the wall-clock safety net."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

import labrunner.clock as clock_module
from labrunner.clock import io_timeouts
from labrunner.drivers.errors import InstrumentTimeout
from labrunner.drivers.rate_table import SerialRateTable
from labrunner.sims.links import TcpSerialPort


class Responder:
    """The far end of a table line: answers PVE after `delay_s` of wall time, or withholds, or stays mute."""

    def __init__(self, port: TcpSerialPort, mode: str, delay_s: float = 0.0) -> None:
        self.port, self.mode, self.delay_s = port, mode, delay_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            buf += self.port.read(0.02)
            if b"\r\n" not in buf:
                continue
            buf = buf.split(b"\r\n", 1)[1]
            if self.mode == "withhold":
                io_timeouts.withhold(self.port.url)
            elif self.mode == "answer":
                time.sleep(self.delay_s)  # a machine so loaded the simulator answers late
                self.port.write(b"PVE +1.25000\r\n")

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2)


@pytest.fixture
def line() -> Iterator[tuple[TcpSerialPort, SerialRateTable]]:
    port = TcpSerialPort()
    table = SerialRateTable(port.url, max_rate_dps=100.0, timeout_s=0.25, retries=0)
    yield port, table
    table.close()
    io_timeouts.release(port.url)
    port.close()


def _virtual(port: TcpSerialPort) -> None:
    io_timeouts.serve_virtually(port.url)


def test_real_line_times_out_after_the_configured_seconds(line):
    port, table = line
    responder = Responder(port, "answer", delay_s=0.6)
    try:
        t0 = time.monotonic()
        with pytest.raises(InstrumentTimeout, match=r"command 'PVE': no reply within 0\.25 s"):
            table.velocity()
        assert time.monotonic() - t0 < 0.55
    finally:
        responder.stop()


def test_simulated_line_waits_for_a_late_answer(line):
    port, table = line
    _virtual(port)
    responder = Responder(port, "answer", delay_s=0.6)
    try:
        assert table.velocity() == 1.25  # 0.6 s of wall time is no timeout on a virtual clock
    finally:
        responder.stop()


def test_a_withheld_reply_times_out_at_once_with_the_configured_seconds(line):
    port, table = line
    _virtual(port)
    responder = Responder(port, "withhold")
    try:
        t0 = time.monotonic()
        with pytest.raises(InstrumentTimeout, match=r"command 'PVE': no reply within 0\.25 s"):
            table.velocity()
        assert time.monotonic() - t0 < 5.0  # not the 30 s safety net
    finally:
        responder.stop()


def test_a_simulator_that_hangs_is_reported_after_the_safety_net(line, monkeypatch):
    port, table = line
    _virtual(port)
    monkeypatch.setattr(clock_module, "SAFETY_NET_S", 0.5)
    responder = Responder(port, "mute")
    try:
        with pytest.raises(InstrumentTimeout, match=r"within 0\.5 s of wall time on a dry run's virtual clock: the "
                                                    r"simulated instrument hangs"):
            table.velocity()
    finally:
        responder.stop()


def test_policy_is_per_link_and_released():
    io_timeouts.serve_virtually("socket://127.0.0.1:1")
    assert io_timeouts.is_virtual("socket://127.0.0.1:1") and not io_timeouts.is_virtual("socket://127.0.0.1:2")
    assert io_timeouts.wall_timeout("socket://127.0.0.1:1", 0.25) == clock_module.SAFETY_NET_S
    assert io_timeouts.wall_timeout("socket://127.0.0.1:2", 0.25) == 0.25
    io_timeouts.withhold("socket://127.0.0.1:2")  # a real line: nothing to tell
    assert io_timeouts.withheld_count("socket://127.0.0.1:2") == 0
    io_timeouts.release("socket://127.0.0.1:1")
    assert not io_timeouts.is_virtual("socket://127.0.0.1:1")
