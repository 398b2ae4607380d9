"""The simulated rate table: the ASCII three-letter protocol over a serial link.

Commands (CR LF terminated) and replies:

    IDN            -> IDN <vendor>,<model>,<serial>
    LIM            -> LIM <max rate deg/s> <acceleration deg/s^2>
    JOG<rate>      -> OK                      (e.g. JOG+100.0000; rate mode)
    STO            -> OK                      (decelerate to rest)
    PVE            -> PVE <rate deg/s>         (measured velocity, e.g. PVE -99.99870)
    STA            -> STA <JOG|STOP|FAULT> <SETTLED|RAMPING|code>
    anything else  -> ERR 1 UNKNOWN COMMAND
    errors         -> ERR <code> <text>       (2 bad number, 3 rate out of range, 5 table fault)

State is the shared `SimWorld`'s table at the clock's time. Faults: garbage replies,
silence, a table fault.
"""

from __future__ import annotations

import logging
import random
import threading
from dataclasses import dataclass

from labrunner.clock import Clock, io_timeouts

from .links import SimPort
from .world import SimWorld

log = logging.getLogger(__name__)

VENDOR, MODEL, SERIAL = "LABRUNNER", "RT-SIM-1", "SN0001"


@dataclass
class TableFaults:
    garbage: bool = False  # replies are line noise
    silent: bool = False  # no replies
    fault: str | None = None  # the table is in a fault state (e.g. "E17 OVERCURRENT")


class TableServer:
    def __init__(self, world: SimWorld, clock: Clock, port: SimPort, seed: int = 0) -> None:
        self.world = world
        self.clock = clock
        self.port = port
        self.faults = TableFaults()
        self.commands = 0
        self._rng = random.Random(seed)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="sim-table", daemon=True)
        self._thread.start()
        log.info("rate table sim: serving on %s", port.url)

    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            data = self.port.read(0.05)
            if not data:
                continue
            buf += data
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

    def handle(self, line: str) -> bytes | None:
        """Reply bytes for one command line (None: no reply)."""
        self.commands += 1
        f = self.faults
        if f.silent:
            io_timeouts.withhold(self.port.url)  # a dry run's driver stops waiting now, in virtual time
            return None
        if f.garbage:
            return bytes(self._rng.randrange(256) for _ in range(self._rng.randrange(3, 20))) + b"\r\n"
        return (self._answer(line.upper()) + "\r\n").encode("ascii")

    def _answer(self, cmd: str) -> str:
        table = self.world.table
        now = self.clock.now()
        with self.world.lock:
            if cmd == "IDN":
                return f"IDN {VENDOR},{MODEL},{SERIAL}"
            if cmd == "LIM":
                return f"LIM {table.p.max_rate_dps:.1f} {table.p.accel_dps2:.1f}"
            if cmd == "PVE":
                return f"PVE {table.measured_rate(now):+.5f}"
            if cmd == "STA":
                if self.faults.fault:
                    return f"STA FAULT {self.faults.fault.split()[0]}"
                mode = "STOP" if table.commanded_dps == 0 else "JOG"
                return f"STA {mode} {'SETTLED' if table.settled(now) else 'RAMPING'}"
            if cmd == "STO":
                table.command(now, 0.0)
                return "OK"
            if cmd.startswith("JOG"):
                if self.faults.fault:
                    return f"ERR 5 TABLE FAULT {self.faults.fault}"
                try:
                    rate = float(cmd[3:])
                except ValueError:
                    return "ERR 2 BAD NUMBER"
                if not abs(rate) <= table.p.max_rate_dps:
                    return "ERR 3 RATE OUT OF RANGE"
                table.command(now, rate)
                return "OK"
        return "ERR 1 UNKNOWN COMMAND"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
