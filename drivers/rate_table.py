"""Serial client for a single-axis rate table speaking the ASCII three-letter protocol.

See `sims.table_server` for the command set. Every command gets exactly one CR LF
terminated reply; a missing or unparsable reply is retried (bounded) after the
link is resynchronised, an ERR reply is a refusal and is raised at once.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections.abc import Callable

import serial

from labrunner.clock import io_timeouts

from .errors import InstrumentError, InstrumentProtocolError, InstrumentRefused, InstrumentTimeout, LimitError
from .protocols import Identity, TableStatus
from .retry import Sleep, with_retry
from .serial_link import close_quietly, open_serial, read_reply

_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_PVE = re.compile(rf"^PVE ({_NUMBER})$")
_LIM = re.compile(rf"^LIM ({_NUMBER}) ({_NUMBER})$")
_STA = re.compile(r"^STA (JOG|STOP|FAULT) (\S+)$")
_IDN = re.compile(r"^IDN ([^,]+),([^,]+),([^,]*)$")
_ERR = re.compile(r"^ERR (\d+) (.+)$")
_OK = re.compile(r"^OK$")
_ANY = re.compile(r"^.*$")

# Every line sent and received at DEBUG; (re)opening the line at INFO.
log = logging.getLogger(__name__)


class SerialRateTable:
    """A rate table on a serial line (implements `drivers.protocols.RateTable`)."""

    def __init__(self, url: str, *, max_rate_dps: float, baudrate: int = 115200, name: str = "rate table",
                 timeout_s: float = 0.5, retries: int = 2, backoff_s: float = 0.2, sleep: Sleep = time.sleep,
                 on_retry: Callable[[int, InstrumentError], None] | None = None) -> None:
        if not max_rate_dps > 0:
            raise ValueError(f"{name}: max_rate_dps must be > 0")
        self.name = name
        self.address = url
        self.max_rate_dps = float(max_rate_dps)
        self.baudrate = baudrate
        self.timeout_s = timeout_s
        self.retries = retries
        self.backoff_s = backoff_s
        self._sleep = sleep
        self.on_retry = on_retry
        self._ser: serial.SerialBase | None = None
        self._opens = 0  # successful opens: a second one is a reconnect
        self._lock = threading.RLock()

    def connect(self) -> None:
        with self._lock:
            with_retry(self._ensure_open, retries=self.retries, backoff_s=self.backoff_s, sleep=self._sleep,
                       on_retry=self.on_retry)

    def _ensure_open(self) -> serial.SerialBase:
        if self._ser is None or not self._ser.is_open:
            self._ser = open_serial(self.address, baudrate=self.baudrate, timeout_s=self.timeout_s,
                                    instrument=self.name)
            self._opens += 1
            log.info("%s: %s %s at %d baud", self.name, "reopened" if self._opens > 1 else "opened", self.address,
                     self.baudrate)
        return self._ser

    def close(self) -> None:
        with self._lock:
            self._reset_link()

    def _reset_link(self) -> None:
        close_quietly(self._ser)
        self._ser = None

    def query(self, command: str, expect: re.Pattern[str] | None = None) -> re.Match[str]:
        """Send one command and return its reply matched against `expect` (any line by default).

        ERR replies raise InstrumentRefused; no reply, a garbled one or one that does
        not match are retried (bounded), each attempt resending the command.
        """
        pattern = expect or _ANY

        def attempt() -> re.Match[str]:
            ser = self._ensure_open()
            try:
                ser.reset_input_buffer()  # a late reply to an earlier, timed-out command is stale
                out = command.encode("ascii") + b"\r\n"
                log.debug("%s: tx %r", self.name, out)
                deadline = io_timeouts.deadline(self.address, self.timeout_s)  # virtual time on a dry run
                ser.write(out)
                raw = read_reply(ser, b"\r\n", deadline)
                log.debug("%s: rx %r", self.name, raw)
            except (serial.SerialException, OSError) as exc:
                log.info("%s: link error on %s (%s); the line is reopened", self.name, self.address, exc)
                self._reset_link()
                raise InstrumentTimeout(self.name, self.address, f"link error: {exc}", command=command) from None
            if not raw.endswith(b"\r\n"):
                detail = "no reply" if not raw else f"incomplete reply {raw!r}"
                raise InstrumentTimeout(self.name, self.address, f"{detail} {deadline.why()}", command=command)
            try:
                line = raw[:-2].decode("ascii").strip()
            except UnicodeDecodeError:
                raise InstrumentProtocolError(self.name, self.address, f"garbage reply {raw!r}",
                                              command=command) from None
            if not line.isprintable():
                raise InstrumentProtocolError(self.name, self.address, f"garbage reply {raw!r}", command=command)
            m = _ERR.match(line)
            if m:
                raise InstrumentRefused(self.name, self.address, f"error {m.group(1)}: {m.group(2)}", command=command)
            m = pattern.match(line)
            if not m:
                raise InstrumentProtocolError(self.name, self.address, f"unexpected reply {line!r}", command=command)
            return m

        with self._lock:
            return with_retry(attempt, retries=self.retries, backoff_s=self.backoff_s, sleep=self._sleep,
                              on_retry=self.on_retry)

    def _expect_ok(self, command: str) -> None:
        self.query(command, _OK)

    # --- the RateTable interface ------------------------------------------------------------

    def identity(self) -> Identity:
        m = self.query("IDN", _IDN)
        return Identity(vendor=m.group(1), model=m.group(2), serial=m.group(3))

    def limits(self) -> tuple[float, float]:
        """The table's own maximum rate and acceleration."""
        m = self.query("LIM", _LIM)
        return float(m.group(1)), float(m.group(2))

    def jog(self, rate_dps: float) -> None:
        if not (math.isfinite(rate_dps) and abs(rate_dps) <= self.max_rate_dps):
            raise LimitError(self.name, self.address, f"rate {rate_dps} deg/s exceeds the configured limit "
                             f"{self.max_rate_dps} deg/s; nothing was sent", command="JOG")
        self._expect_ok(f"JOG{rate_dps:+.4f}")

    def stop(self) -> None:
        self._expect_ok("STO")

    def velocity(self) -> float:
        return float(self.query("PVE", _PVE).group(1))

    def status(self) -> TableStatus:
        m = self.query("STA", _STA)
        mode, word = m.group(1), m.group(2)
        if mode == "FAULT":
            return TableStatus(mode=mode, settled=False, fault=word)
        return TableStatus(mode=mode, settled=(word == "SETTLED"))
