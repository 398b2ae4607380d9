"""The simulated chamber controller: a real pymodbus server (TCP, or RTU framing over socket://).

Registers follow a `drivers.chamber_profiles.ChamberProfile`, in the controller units the
chamber's parameters set (`controller_units` °C/°F, `controller_decimals`; served in the
decimal-places and units registers where the map has them, Watlow F4 606/901). Every request runs the
action hook, which brings the chamber plant to the clock's current time and puts
process value, setpoint, outputs and limits into the registers, or applies a
setpoint write (refusing values outside the controller's range, like the real one).
Faults (timeouts, exception replies, garbage process value, dropped and refused
connections) are switched through `ChamberFaults`.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Coroutine
from dataclasses import dataclass
from typing import Any, TypeVar, cast

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.framer import FramerRTU, FramerType
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.simulator.simcore import SimCore

from labrunner.clock import Clock, io_timeouts
from labrunner.drivers.chamber_profiles import ChamberProfile, ControllerUnits, profile_from

from .aio import LoopThread
from .links import MemoryPort
from .world import SimWorld

log = logging.getLogger(__name__)

T = TypeVar("T")
READ_FCS = {3, 4}
WRITE_FCS = {6, 16}


@dataclass
class ChamberFaults:
    """Switchable misbehaviour of the simulated controller."""

    exception_code: int | None = None  # answer every request with this Modbus exception
    exception_count: int = 0  # ... for this many requests (0 = while set)
    silent: bool = False  # do not answer at all (the client times out)
    garbage_pv: bool = False  # process value register reads a sensor-break pattern

    def clear(self) -> None:
        self.exception_code = None
        self.exception_count = 0
        self.silent = False
        self.garbage_pv = False


class ChamberServer:
    """Serves one `SimWorld`'s chamber over Modbus."""

    def __init__(self, world: SimWorld, clock: Clock, profile: ChamberProfile | str = "watlow_f4", *,
                 transport: str = "tcp", host: str = "127.0.0.1", port: int = 0, device_id: int = 1,
                 loop: LoopThread | None = None) -> None:
        self.world = world
        self.clock = clock
        self.profile = profile_from(profile) if isinstance(profile, str) else profile
        self.transport = transport
        self.host = host
        self.device_id = device_id
        self.faults = ChamberFaults()
        params = world.chamber.p
        self.units = ControllerUnits(decimals=params.controller_decimals, fahrenheit=params.controller_units == "F")
        missing = [what for what, needed, register in (
            ("units", self.units.fahrenheit, self.profile.units_register),
            ("decimal places", self.units.decimals != 1 and self.profile.encoding == "int16_tenths",
             self.profile.decimals_register)) if needed and register is None]
        if missing:
            # A controller cannot show what its map cannot tell the driver: refused, not served wrong.
            raise ValueError(f"chamber sim: profile {self.profile.name!r} has no {' or '.join(missing)} register; "
                             "serve it with controller_units C and controller_decimals 1")
        self.requests = 0
        self._last_words: dict[int, tuple[float, bool, list[int]]] = {}  # register -> (value, output, words)
        regs = self.profile.registers()
        top = max(regs.values()) + self.profile.words + 1
        device = SimDevice(id=device_id, simdata=[SimData(address=0, count=top, values=0, datatype=DataType.REGISTERS)],
                           action=self._action)
        self._device = device
        self.line: ModbusLine | None = None
        if transport == "memory":  # a dry run's RTU line inside the process: answered in the driver's thread
            self.line = ModbusLine(device, MemoryPort("chamber"), self)
            self.port = 0
            log.info("chamber sim: Modbus RTU on %s, profile %s", self.line.port.url, self.profile.name)
            return
        self._loop = loop or LoopThread("sim-chamber")
        self._own_loop = loop is None
        self._server = self._loop.run(self._start(device, port))
        # pymodbus keeps the listening asyncio.Server as the protocol's `transport` (typed BaseTransport).
        self.port = int(cast(asyncio.Server, self._server.transport).sockets[0].getsockname()[1])
        log.info("chamber sim: Modbus %s server on %s:%d, profile %s", transport.upper(), host, self.port,
                 self.profile.name)

    async def _start(self, device: SimDevice, port: int) -> ModbusTcpServer | ModbusSerialServer:
        if self.transport == "tcp":
            server: ModbusTcpServer | ModbusSerialServer = ModbusTcpServer(device, address=(self.host, port))
        elif self.transport == "rtu":
            if port == 0:
                port = _free_port(self.host)
            server = ModbusSerialServer(device, port=f"socket://{self.host}:{port}", framer=FramerType.RTU,
                                        baudrate=115200)
        else:
            raise ValueError(f"chamber sim transport must be 'tcp' or 'rtu', got {self.transport!r}")
        await server.serve_forever(background=True)
        return server

    @property
    def url(self) -> str:
        if self.line is not None:
            return self.line.port.url
        return f"socket://{self.host}:{self.port}" if self.transport == "rtu" else f"{self.host}:{self.port}"

    # --- the register hook ------------------------------------------------------------

    def _put(self, regs: list[int], start: int, register: int | None, value: float, *, output: bool = False) -> None:
        if register is None:
            return
        words = self._encoded(register, value, output)
        i = register - start
        if 0 <= i and i + len(words) <= len(regs):
            regs[i:i + len(words)] = words

    def _encoded(self, register: int, value: float, output: bool) -> list[int]:
        """The register words of a value: the last ones of this register again when the value is the same
        (the setpoint and its limits between commands; a value that cannot be encoded raises every time)."""
        last = self._last_words.get(register)
        if last is not None and last[1] == output and _same_value(last[0], value):
            return last[2]
        words = self.profile.encode(value, output=output, units=self.units)
        self._last_words[register] = (value, output, words)
        return words

    def _refresh(self, regs: list[int], start: int) -> None:
        p = self.profile
        plant = self.world.chamber
        with self.world.lock:
            self.world.advance(self.clock.now())
            pv: float | None = plant.air_c
            if self.faults.garbage_pv:
                # A broken thermocouple: the F4 shows a huge value; float maps get NaN.
                if p.encoding == "int16_tenths":
                    i = p.process_value - start
                    if 0 <= i < len(regs):
                        regs[i] = 0x7FFF
                    pv = None
                else:
                    pv = float("nan")
            if pv is not None:
                self._put(regs, start, p.process_value, pv)
            self._put(regs, start, p.setpoint, plant.setpoint_c)
            self._put(regs, start, p.heat_output, plant.heat_output_pct, output=True)
            self._put(regs, start, p.cool_output, plant.cool_output_pct, output=True)
            self._put(regs, start, p.setpoint_min, plant.p.setpoint_min_c)
            self._put(regs, start, p.setpoint_max, plant.p.setpoint_max_c)
            self._put(regs, start, p.current_setpoint, plant.setpoint_c)  # no ramp program: the setpoint
            for register, value in ((p.model_register, p.model_code), (p.decimals_register, self.units.decimals),
                                    (p.units_register, 0 if self.units.fahrenheit else 1)):
                if register is not None and value is not None and 0 <= register - start < len(regs):
                    regs[register - start] = value & 0xFFFF

    async def _action(self, fc: int, start: int, address: int, count: int, regs: list[int],
                      set_values: list[int] | list[bool] | None) -> ExcCodes | None:
        self.requests += 1
        f = self.faults
        if f.silent:
            if io_timeouts.is_virtual(self.url):
                # A dry run's client waits in virtual time: told that no answer comes, it times out now.
                io_timeouts.withhold(self.url)
                for conn in list(self._server.active_connections.values()):
                    conn.close()
            while f.silent:  # unanswered until the fault clears (the client has timed out by then)
                await asyncio.sleep(0.05)
            return ExcCodes.DEVICE_BUSY
        if f.exception_code is not None:
            if f.exception_count:
                f.exception_count -= 1
                code = f.exception_code
                if f.exception_count == 0:
                    f.exception_code = None
            else:
                code = f.exception_code
            return ExcCodes(code)
        if fc in WRITE_FCS:
            if set_values is None:
                return None
            return self._write(start, address, [int(v) for v in set_values], regs)
        self._refresh(regs, start)
        return None

    def _write(self, start: int, address: int, values: list[int], regs: list[int]) -> ExcCodes | None:
        p = self.profile
        if address != p.setpoint or len(values) != p.words:
            return ExcCodes.ILLEGAL_ADDRESS  # only the setpoint is writable here
        value = p.decode(values, units=self.units)
        plant = self.world.chamber
        if not (plant.p.setpoint_min_c <= value <= plant.p.setpoint_max_c):
            return ExcCodes.ILLEGAL_VALUE
        with self.world.lock:
            self.world.advance(self.clock.now())
            plant.set_setpoint(value)
        return None

    # --- connection faults ---------------------------------------------------------------

    def drop_connections(self) -> int:
        """Close every client connection (the client sees the link drop)."""
        if self.line is not None:
            was = self.line.port.connected
            self.line.port.disconnect()
            return int(was)
        async def drop() -> int:
            conns = list(self._server.active_connections.values())
            for c in conns:
                c.close()
            return len(conns)
        n = self._loop.run(drop())
        log.debug("chamber sim: dropped %d client connection(s)", n)
        return n

    def refuse_connections(self, refuse: bool) -> None:
        """Fault: stop listening (connects are refused) and drop clients; or listen again."""
        log.debug("chamber sim: %s connections", "refusing" if refuse else "accepting")
        if self.line is not None:
            self.line.port.refuse(refuse)
            return

        async def toggle() -> None:
            if refuse and self._server.transport is not None:
                for c in list(self._server.active_connections.values()):
                    c.close()
                self._server.transport.close()
                self._server.transport = None  # type: ignore[assignment]  # None: not listening
            elif not refuse and self._server.transport is None:
                self._server = await self._start(self._device, self.port)
        self._loop.run(toggle())

    def close(self) -> None:
        if self.line is not None:
            self.line.port.close()
            return
        try:
            self._loop.run(self._server.shutdown())
        except Exception:
            pass
        if self._own_loop:
            self._loop.stop()


def _same_value(a: float, b: float) -> bool:
    """Equal, zeros of one sign (a float register holds -0.0 and 0.0 apart)."""
    return a == b and (a != 0 or math.copysign(1.0, a) == math.copysign(1.0, b))


def _free_port(host: str) -> int:
    import socket

    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class ModbusLine:
    """A dry run's chamber on a Modbus RTU line inside the process (`MemoryPort`), served in the driver's thread.

    The request's bytes are framed and decoded by pymodbus' own server-side RTU framer and PDU decoder,
    answered from the same simulated device and register hook as the asyncio server's, and the reply
    frame is built by the same framer: what pymodbus' `ServerRequestHandler` does, without the event
    loop and its thread (the hook never waits). A silent controller (`ChamberFaults.silent`) leaves
    the request unanswered and drops the line, as the served one closes its connections.
    """

    def __init__(self, device: SimDevice, port: MemoryPort, server: ChamberServer) -> None:
        self.port = port
        self._server = server
        self._core = SimCore(device)
        self._framer = FramerRTU(DecodePDU(True))
        self._buf = b""
        port.attach_server(self.receive)

    def receive(self, data: bytes) -> None:
        self._buf += data
        while self._buf:
            used, pdu = self._framer.handleFrame(self._buf, 0, 0)
            self._buf = self._buf[used:]
            if pdu is None:
                return
            if self._server.faults.silent:
                self._server.requests += 1
                io_timeouts.withhold(self.port.url)  # the driver stops waiting now, in virtual time
                self._buf = b""
                self.port.disconnect()
                return
            response = self._answer(pdu)
            response.transaction_id = pdu.transaction_id
            response.dev_id = pdu.dev_id
            self.port.write(self._framer.buildFrame(response))

    def _answer(self, pdu: ModbusPDU) -> ModbusPDU:
        try:
            return _run_now(pdu.datastore_update(self._core, pdu.dev_id))  # type: ignore[arg-type]
        except NoSuchIdException:
            return ExceptionResponse(pdu.function_code, ExcCodes.GATEWAY_NO_RESPONSE)
        except Exception as exc:  # as pymodbus' handler: the device failed, the client is told so
            log.error("chamber sim: request failed: %s", exc)
            return ExceptionResponse(pdu.function_code, ExcCodes.DEVICE_FAILURE)


def _run_now(coro: Coroutine[Any, Any, T]) -> T:
    """The result of a coroutine that never waits (the datastore and its register hook)."""
    try:
        coro.send(None)
    except StopIteration as done:
        return cast(T, done.value)
    coro.close()
    raise RuntimeError("a simulated chamber request waited for the event loop")
