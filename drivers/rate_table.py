"""Serial client for a single-axis rate table whose command language is a profile.

The language (`table_profiles.TableLanguage`: command templates, query suffix, terminator,
reply templates) is data: labrunner's own ASCII language (`IDN LIM JOG STO PVE STA`, see
`sims.table_server`) and Ideal Aerosmith's table language (`JOG`, `STO`, `SRV`, `HOM`, queries
ending in `?`; its sources and what they leave open are in `table_profiles`) are two profiles
of one driver. Every command gets exactly one terminated reply; a missing or unparsable reply
is retried (bounded) after the link is resynchronised, an error reply is a refusal and is
raised at once. Where the language has no status query, settling is judged from the velocity
against the last commanded rate.
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
from .table_profiles import TableLanguage, language_from

_ANY = re.compile(r"^.*$")

# Every line sent and received at DEBUG; (re)opening the line at INFO.
log = logging.getLogger(__name__)


class SerialRateTable:
    """A rate table on a serial line (implements `drivers.protocols.RateTable`)."""

    def __init__(self, url: str, *, max_rate_dps: float, baudrate: int = 115200, name: str = "rate table",
                 timeout_s: float = 0.5, retries: int = 2, backoff_s: float = 0.2, sleep: Sleep = time.sleep,
                 on_retry: Callable[[int, InstrumentError], None] | None = None,
                 language: TableLanguage | str = "labrunner") -> None:
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
        self.language = language_from(language)
        self._commanded: float | None = None  # the last rate sent (None: not since this driver started)
        self._enabled = False  # the language's enable command sent on this connection
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
            self._enabled = False
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
        lang = self.language

        def attempt() -> re.Match[str]:
            ser = self._ensure_open()
            try:
                ser.reset_input_buffer()  # a late reply to an earlier, timed-out command is stale
                out = command.encode("ascii") + lang.terminator_bytes
                log.debug("%s: tx %r", self.name, out)
                deadline = io_timeouts.deadline(self.address, self.timeout_s)  # virtual time on a dry run
                ser.write(out)
                raw = read_reply(ser, lang.terminator_bytes, deadline)
                log.debug("%s: rx %r", self.name, raw)
            except (serial.SerialException, OSError) as exc:
                log.info("%s: link error on %s (%s); the line is reopened", self.name, self.address, exc)
                self._reset_link()
                raise InstrumentTimeout(self.name, self.address, f"link error: {exc}", command=command) from None
            if not raw.endswith(lang.terminator_bytes):
                detail = "no reply" if not raw else f"incomplete reply {raw!r}"
                raise InstrumentTimeout(self.name, self.address, f"{detail} {deadline.why()}", command=command)
            try:
                line = raw[:-len(lang.terminator_bytes)].decode("ascii").strip()
            except UnicodeDecodeError:
                raise InstrumentProtocolError(self.name, self.address, f"garbage reply {raw!r}",
                                              command=command) from None
            if line and not line.isprintable():
                raise InstrumentProtocolError(self.name, self.address, f"garbage reply {raw!r}", command=command)
            m = lang.error_pattern.match(line) if lang.error_pattern is not None else None
            if m:
                detail = ": ".join(v for v in (m.groupdict().get("code"), m.groupdict().get("text")) if v) or line
                raise InstrumentRefused(self.name, self.address, f"error {detail}", command=command)
            m = pattern.match(line)
            if not m:
                raise InstrumentProtocolError(self.name, self.address, f"unexpected reply {line!r}", command=command)
            return m

        with self._lock:
            return with_retry(attempt, retries=self.retries, backoff_s=self.backoff_s, sleep=self._sleep,
                              on_retry=self.on_retry)

    def _act(self, operation: str, **values: float) -> None:
        command = self.language.action(operation, **values)
        self.query(command, self.language.ack_pattern)

    def _ask(self, operation: str) -> dict[str, str]:
        return self.query(self.language.query(operation), self.language.reply_patterns[operation]).groupdict()

    def _number(self, operation: str, reply: dict[str, str], key: str) -> float:
        try:
            return float(reply[key])
        except (KeyError, ValueError):
            raise InstrumentProtocolError(self.name, self.address, f"{operation} reply has no number {key!r}",
                                          command=self.language.query(operation)) from None

    # --- the RateTable interface ------------------------------------------------------------

    def identity(self) -> Identity:
        lang = self.language
        if not lang.has("identity"):
            return Identity(vendor=lang.vendor, model=lang.model, extra={"language": lang.name})
        r = self._ask("identity")
        return Identity(vendor=r.get("vendor", lang.vendor), model=r.get("model", lang.model),
                        serial=r.get("serial", ""), extra={"language": lang.name})

    def limits(self) -> tuple[float, float]:
        """The table's own maximum rate and acceleration (the language's constants where it cannot say)."""
        if not self.language.has("limits"):
            if self.language.fixed_limits is None:
                raise InstrumentProtocolError(self.name, self.address, f"table language {self.language.name!r} "
                                              "has no limits query and no fixed_limits")
            return self.language.fixed_limits
        r = self._ask("limits")
        return self._number("limits", r, "max_rate"), self._number("limits", r, "accel")

    def jog(self, rate_dps: float) -> None:
        if not (math.isfinite(rate_dps) and abs(rate_dps) <= self.max_rate_dps):
            raise LimitError(self.name, self.address, f"rate {rate_dps} deg/s exceeds the configured limit "
                             f"{self.max_rate_dps} deg/s; nothing was sent", command="JOG")
        with self._lock:
            if self.language.has("enable") and not self._enabled:
                self._act("enable")
                self._enabled = True
            self._act("jog", rate=rate_dps)
            self._commanded = float(rate_dps)

    def stop(self) -> None:
        self._act("stop")
        self._commanded = 0.0

    def velocity(self) -> float:
        return self._number("velocity", self._ask("velocity"), "rate")

    def position(self) -> float:
        """The table's angle, degrees, where the language has a position query."""
        return self._number("position", self._ask("position"), "deg")

    def home(self) -> None:
        """Drive the table to its home position (moves it: never called by a check)."""
        self._act("home")

    def status(self) -> TableStatus:
        lang = self.language
        if not lang.has("status"):
            return self._status_from_velocity()
        r = self._ask("status")
        mode = lang.status_modes.get(r.get("mode", ""))
        if mode is None:
            raise InstrumentProtocolError(self.name, self.address, f"status mode {r.get('mode')!r} is none of "
                                          f"{', '.join(lang.status_modes)}", command=lang.query("status"))
        if mode == "FAULT":
            return TableStatus(mode=mode, settled=False, fault=r.get("state") or "fault")
        return TableStatus(mode=mode, settled=(r.get("state") == lang.settled_state))

    def _status_from_velocity(self) -> TableStatus:
        # No status in the language: at the commanded rate (within the profile's tolerance) is settled.
        v = self.velocity()
        lang = self.language
        target = self._commanded
        if target is None:  # a driver that has sent nothing yet (a check, an abort): judge by the motion
            moving = abs(v) > lang.settle_floor_dps
            return TableStatus(mode="JOG" if moving else "STOP", settled=not moving)
        settled = abs(v - target) <= lang.settle_fraction * abs(target) + lang.settle_floor_dps
        return TableStatus(mode="STOP" if target == 0 else "JOG", settled=settled)
