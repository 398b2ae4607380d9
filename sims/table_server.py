"""The simulated rate table: a command language (`drivers.table_profiles`) over a serial link.

It speaks whichever language its plant's parameters name (`table.language` in a sim
configuration: `labrunner`, the default, or `ideal_aerosmith`), parsing commands and formatting
replies from the same profile the driver uses. labrunner's own language (CR LF terminated):

    IDN            -> IDN <vendor>,<model>,<serial>
    LIM            -> LIM <max rate deg/s> <acceleration deg/s^2>
    JOG<rate>      -> OK                      (e.g. JOG+100.0000; rate mode)
    STO            -> OK                      (decelerate to rest)
    PVE            -> PVE <rate deg/s>         (measured velocity, e.g. PVE -99.99870)
    STA            -> STA <JOG|STOP|FAULT> <SETTLED|RAMPING|code>
    anything else  -> ERR 1 UNKNOWN COMMAND
    errors         -> ERR <code> <text>       (2 bad number, 3 rate out of range, 5 table fault)

A language without error replies (Ideal Aerosmith's, as far as its sources say) leaves a
refused or unknown command unanswered; a jog before the servo is enabled (`SRV 1`) is refused
that way too. State is the shared `SimWorld`'s table at the clock's time. Faults: garbage
replies, silence, a table fault.
"""

from __future__ import annotations

import logging
import random
import threading
from collections.abc import Callable
from dataclasses import dataclass

from labrunner.clock import Clock, io_timeouts
from labrunner.drivers.table_profiles import TableLanguage, language_from

from .links import MemoryPort, SimPort
from .world import SimWorld

log = logging.getLogger(__name__)

VENDOR, MODEL, SERIAL = "LABRUNNER", "RT-SIM-1", "SN0001"


@dataclass
class TableFaults:
    garbage: bool = False  # replies are line noise
    silent: bool = False  # no replies
    fault: str | None = None  # the table is in a fault state (e.g. "E17 OVERCURRENT")


class TableServer:
    def __init__(self, world: SimWorld, clock: Clock, port: SimPort, seed: int = 0,
                 language: TableLanguage | str | None = None) -> None:
        self.world = world
        self.language = language_from(language if language is not None else world.table.p.language)
        self.servo_on = not self.language.has("enable")  # a language with an enable command starts off
        self.clock = clock
        self.port = port
        self.faults = TableFaults()
        self.commands = 0
        self._rng = random.Random(seed)
        self._stop = threading.Event()
        self._buf = b""
        self._thread: threading.Thread | None = None
        # Called before a command changes the rate (an IMU making its frames on demand sends the ones due).
        self.before_command: Callable[[], None] | None = None
        if isinstance(port, MemoryPort):  # a dry run's line inside the process: answered in the driver's thread
            port.attach_server(self.receive)
        else:
            self._thread = threading.Thread(target=self._serve, name="sim-table", daemon=True)
            self._thread.start()
        log.info("rate table sim: serving on %s (language %s)", port.url, self.language.name)

    def _serve(self) -> None:
        while not self._stop.is_set():
            data = self.port.read(0.05)
            if data:
                self.receive(data)

    def receive(self, data: bytes) -> None:
        """Bytes from the line: every complete command line is answered on the port."""
        buf = self._buf + data
        while True:
            cut = min((i for i in (buf.find(b"\r"), buf.find(b"\n")) if i >= 0), default=-1)
            if cut < 0:
                break
            line, buf = buf[:cut], buf[cut + 1:]
            if line.strip():
                reply = self.handle(line.decode("ascii", errors="replace").strip())
                if reply is not None:
                    self.port.write(reply)
        if len(buf) > 4096:  # a line that never ends is noise
            log.debug("rate table sim: discarded %d bytes without a line end", len(buf))
            buf = b""
        self._buf = buf

    def handle(self, line: str) -> bytes | None:
        """Reply bytes for one command line (None: no reply)."""
        self.commands += 1
        f = self.faults
        if f.silent:
            io_timeouts.withhold(self.port.url)  # a dry run's driver stops waiting now, in virtual time
            return None
        term = self.language.terminator_bytes
        if f.garbage:
            return bytes(self._rng.randrange(256) for _ in range(self._rng.randrange(3, 20))) + term
        answer = self._answer(line.upper())
        if answer is None:  # a language without error replies: the command goes unanswered
            io_timeouts.withhold(self.port.url)  # a dry run's driver stops waiting now, in virtual time
            return None
        return answer.encode("ascii") + term

    def _error(self, code: int, text: str) -> str | None:
        err = self.language.error
        return err.format(code=code, text=text) if err is not None else None

    def _answer(self, cmd: str) -> str | None:
        lang = self.language
        for operation, pattern in lang.command_patterns.items():
            m = pattern.match(cmd)
            if m:
                return self._operate(operation, m.groupdict())
        return self._error(1, "UNKNOWN COMMAND")

    def _operate(self, operation: str, values: dict[str, str]) -> str | None:
        lang = self.language
        table = self.world.table
        ack = lang.ack.format()
        if operation in ("stop", "home", "jog") and self.before_command is not None:
            self.before_command()
        with self.world.lock:
            # The time is read under the world's lock: the IMU stream (a ticker thread on a served clock)
            # generates its frames under it too, so no frame is timed after a command yet made before it
            # with the old rate. Read before the lock, a command waiting for a chunk of up to MAX_CHUNK_S
            # took effect in the past: at 600x the first seconds of a record carried the previous rate.
            now = self.clock.now()
            if operation == "identity":
                return lang.replies["identity"].format(vendor=VENDOR, model=MODEL, serial=SERIAL)
            if operation == "limits":
                return lang.replies["limits"].format(max_rate=table.p.max_rate_dps, accel=table.p.accel_dps2)
            if operation == "velocity":
                return lang.replies["velocity"].format(rate=table.measured_rate(now))
            if operation == "position":
                return lang.replies["position"].format(deg=table.angle_at(now))
            if operation == "status":
                words = {v: k for k, v in lang.status_modes.items()}
                if self.faults.fault:
                    return lang.replies["status"].format(mode=words["FAULT"], state=self.faults.fault.split()[0])
                mode = "STOP" if table.commanded_dps == 0 else "JOG"
                return lang.replies["status"].format(mode=words[mode],
                                                     state=lang.settled_state if table.settled(now) else "RAMPING")
            if operation == "stop":
                table.command(now, 0.0)
                return ack
            if operation == "enable":
                self.servo_on = True
                return ack
            if operation == "home":  # no angle is kept beyond the rate's integral: a stop at home
                table.command(now, 0.0)
                return ack
            if operation == "jog":
                if self.faults.fault:
                    return self._error(5, f"TABLE FAULT {self.faults.fault}")
                if not self.servo_on:
                    return self._error(4, "SERVO OFF")
                try:
                    rate = float(values["rate"])
                except (KeyError, ValueError):
                    return self._error(2, "BAD NUMBER")
                if not abs(rate) <= table.p.max_rate_dps:
                    return self._error(3, "RATE OUT OF RANGE")
                table.command(now, rate)
                return ack
        return self._error(1, "UNKNOWN COMMAND")

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
