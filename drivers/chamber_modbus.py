"""Modbus TCP / RTU client for a thermal chamber controller described by a register-map profile.

The maps and their sources are in `chamber_profiles` (Espec North America's ChamberConnectLibrary,
`watlowf4.py` and `watlowf4t.py`). Where a map names the controller's decimal-places and units
registers (the Watlow F4's 606 and 901), they are read at each (re)connect and every temperature
is converted between the controller's units and °C; the `Chamber` interface is always °C.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException
from pymodbus.framer import FramerType
from pymodbus.pdu import ModbusPDU

from labrunner.clock import io_timeouts

from .chamber_profiles import CELSIUS_TENTHS, ChamberProfile, ControllerUnits, profile_from
from .errors import InstrumentError, InstrumentProtocolError, InstrumentRefused, InstrumentTimeout, LimitError
from .protocols import Identity
from .retry import Sleep, with_retry

# Wire traffic (register addresses and values) at DEBUG, connects at INFO. pymodbus' own logging
# is left alone: the application quiets it (labrunner.logs.configure), not a driver at import.
log = logging.getLogger(__name__)

# Plausible air temperatures: anything else read from the PV register is garbage, not a reading.
PLAUSIBLE_C = (-100.0, 300.0)
MODBUS_EXCEPTIONS = {
    1: "illegal function", 2: "illegal data address", 3: "illegal data value", 4: "server device failure",
    5: "acknowledge (busy with a long command)", 6: "server device busy", 10: "gateway path unavailable",
    11: "gateway target failed to respond",
}
TRANSIENT_EXCEPTIONS = {5, 6, 10, 11}


class _SerialClient(ModbusSerialClient):
    """pymodbus' RTU client; on a caller-fed line (a dry run's line inside the process, `caller_fed` on the
    pyserial object) the reply is whole when the request's write has returned, so it is read at once
    instead of polled for in 1 ms sleeps until the bytes stop coming."""

    def recv(self, size: int | None) -> bytes:
        line = self.socket
        if line is None or not getattr(line, "caller_fed", False):
            return super().recv(size)
        try:
            return bytes(line.read(line.in_waiting if size is None else size))
        except OSError:  # the line was lost (pyserial's SerialException is one)
            self.close()
            raise ConnectionException(str(self)) from None


@dataclass(frozen=True)
class ModbusAddress:
    """Where the controller is: TCP host/port, or an RTU serial port (device path or socket:// URL)."""

    transport: str = "tcp"  # "tcp" or "rtu"
    host: str = "127.0.0.1"
    port: int = 502
    serial_port: str | None = None
    baudrate: int = 19200
    device_id: int = 1

    def __str__(self) -> str:
        if self.transport == "tcp":
            return f"modbus-tcp://{self.host}:{self.port} (device {self.device_id})"
        return f"modbus-rtu:{self.serial_port} @ {self.baudrate} (device {self.device_id})"


class ModbusChamber:
    """A chamber controller over Modbus (implements `drivers.protocols.Chamber`)."""

    def __init__(self, address: ModbusAddress, profile: ChamberProfile | str = "watlow_f4", *,
                 name: str = "chamber", timeout_s: float = 1.0, retries: int = 2, backoff_s: float = 0.5,
                 sleep: Sleep = time.sleep,
                 on_retry: Callable[[int, InstrumentError], None] | None = None) -> None:
        if address.transport not in ("tcp", "rtu"):
            raise ValueError(f"{name}: transport must be 'tcp' or 'rtu', got {address.transport!r}")
        if address.transport == "rtu" and not address.serial_port:
            raise ValueError(f"{name}: an RTU chamber needs serial_port")
        self.name = name
        self.addr = address
        self.address = str(address)
        self.profile = profile_from(profile) if isinstance(profile, str) else profile
        self.timeout_s = timeout_s
        self.retries = retries
        self.backoff_s = backoff_s
        self._sleep = sleep
        self.on_retry = on_retry
        self._client: ModbusTcpClient | ModbusSerialClient | None = None
        self._connects = 0  # successful connects: a second one is a reconnect
        self._range: tuple[float, float] | None = None
        self._units: ControllerUnits | None = None  # read from the controller after each (re)connect
        self._lock = threading.RLock()

    # --- connection -----------------------------------------------------------------

    def _link(self) -> str:
        return f"{self.addr.host}:{self.addr.port}" if self.addr.transport == "tcp" else str(self.addr.serial_port)

    def _make_client(self) -> ModbusTcpClient | ModbusSerialClient:
        timeout = io_timeouts.wall_timeout(self._link(), self.timeout_s)  # a dry run waits in virtual time
        if self.addr.transport == "tcp":
            return ModbusTcpClient(self.addr.host, port=self.addr.port, timeout=timeout, retries=0)
        assert self.addr.serial_port, "an RTU address has a serial port (checked in __init__)"
        return _SerialClient(self.addr.serial_port, framer=FramerType.RTU, baudrate=self.addr.baudrate,
                             timeout=timeout, retries=0)

    def _ensure_connected(self) -> ModbusTcpClient | ModbusSerialClient:
        if self._client is None:
            self._client = self._make_client()
        if not self._client.connected:
            try:
                ok = self._client.connect()
            except Exception as exc:  # pymodbus/pyserial raise assorted OSErrors on connect
                ok = False
                reason = str(exc)
            else:
                reason = "connection refused or no answer"
            if not ok:
                self._client.close()
                log.debug("%s: cannot connect to %s: %s", self.name, self.address, reason)
                raise InstrumentTimeout(self.name, self.address, f"cannot connect: {reason}")
            self._connects += 1
            self._units = None  # someone may have changed the controller's settings meanwhile
            self._range = None
            log.info("%s: %s %s (profile %s)", self.name, "reconnected to" if self._connects > 1 else "connected to",
                     self.address, self.profile.name)
        return self._client

    def connect(self) -> None:
        with self._lock:
            with_retry(self._ensure_connected, retries=self.retries, backoff_s=self.backoff_s, sleep=self._sleep,
                       on_retry=self.on_retry)

    def close(self) -> None:
        with self._lock:
            if self._client is not None:
                self._client.close()
                self._client = None
                log.debug("%s: closed %s", self.name, self.address)

    # --- register access ----------------------------------------------------------------

    def _transact(self, register: int, op: str,
                  fn: Callable[[ModbusTcpClient | ModbusSerialClient], ModbusPDU]) -> ModbusPDU:
        def attempt() -> ModbusPDU:
            client = self._ensure_connected()
            deadline = io_timeouts.deadline(self._link(), self.timeout_s)
            try:
                response = fn(client)
            except ModbusException as exc:
                client.close()  # a half-read reply leaves the stream out of step: start clean
                log.debug("%s: %s at register %d: no valid answer (%s); connection closed", self.name, op,
                          register, exc)
                why = f"no valid answer {deadline.why()}" if deadline.next_wait() == 0 else f"no valid answer ({exc})"
                raise InstrumentTimeout(self.name, self.address, f"{op}: {why}", register=register) from None
            except OSError as exc:
                client.close()
                log.debug("%s: %s at register %d: link error (%s); connection closed", self.name, op, register, exc)
                raise InstrumentTimeout(self.name, self.address, f"{op}: link error ({exc})",
                                        register=register) from None
            if response.isError():
                code = int(getattr(response, "exception_code", 0))
                text = MODBUS_EXCEPTIONS.get(code, f"code {code}")
                log.debug("%s: %s at register %d: Modbus exception %s (%s)", self.name, op, register, code, text)
                if code in TRANSIENT_EXCEPTIONS:
                    raise InstrumentError(self.name, self.address, f"{op}: Modbus exception {code} ({text})",
                                          register=register)
                raise InstrumentRefused(self.name, self.address, f"{op}: Modbus exception {code} ({text})",
                                        register=register)
            return response

        with self._lock:
            return with_retry(attempt, retries=self.retries, backoff_s=self.backoff_s, sleep=self._sleep,
                              on_retry=self.on_retry)

    def read_words(self, register: int, count: int) -> list[int]:
        response = self._transact(register, f"read {count} register(s)", lambda c: c.read_holding_registers(
            register, count=count, device_id=self.addr.device_id))
        words = list(getattr(response, "registers", []) or [])
        if len(words) != count:
            raise InstrumentProtocolError(self.name, self.address, f"asked for {count} register(s), got {len(words)}",
                                          register=register)
        log.debug("%s: read %d register(s) at %d -> %s", self.name, count, register, words)
        return words

    def write_words(self, register: int, words: list[int]) -> None:
        log.debug("%s: write %d register(s) at %d <- %s", self.name, len(words), register, words)
        if len(words) == 1:
            self._transact(register, "write register", lambda c: c.write_register(
                register, words[0], device_id=self.addr.device_id))
        else:
            self._transact(register, f"write {len(words)} registers", lambda c: c.write_registers(
                register, words, device_id=self.addr.device_id))

    def units(self) -> ControllerUnits:
        """The controller's decimal places and °F/°C (read once per connection where the map has them)."""
        with self._lock:
            if self._units is None:
                self._units = self._read_units()
            return self._units

    def _read_units(self) -> ControllerUnits:
        p = self.profile
        decimals, fahrenheit = CELSIUS_TENTHS.decimals, False
        if p.decimals_register is not None:
            decimals = self.read_words(p.decimals_register, 1)[0]
            if not 0 <= decimals <= 3:
                raise InstrumentProtocolError(self.name, self.address, f"decimal places register reads {decimals}, "
                                              "expected 0..3", register=p.decimals_register)
        if p.units_register is not None:
            code = self.read_words(p.units_register, 1)[0]
            if code not in (0, 1):
                raise InstrumentProtocolError(self.name, self.address, f"units register reads {code}, expected "
                                              "0 (F) or 1 (C)", register=p.units_register)
            fahrenheit = code == 0
        units = ControllerUnits(decimals=decimals, fahrenheit=fahrenheit)
        if p.decimals_register is not None or p.units_register is not None:
            log.info("%s: controller shows %d decimal place(s) in deg %s", self.name, units.decimals, units.symbol)
        return units

    def _read_value(self, register: int, *, output: bool = False) -> float:
        units = CELSIUS_TENTHS if output else self.units()
        return self.profile.decode(self.read_words(register, self.profile.words), output=output, units=units)

    # --- the Chamber interface ------------------------------------------------------------

    def identity(self) -> Identity:
        extra: dict[str, str] = {"profile": self.profile.name}
        if self.profile.decimals_register is not None or self.profile.units_register is not None:
            units = self.units()
            extra["units"] = units.symbol
            extra["decimals"] = str(units.decimals)
        if self.profile.model_register is not None:
            code = self.read_words(self.profile.model_register, 1)[0]
            extra["model_code"] = str(code)
            if self.profile.model_code is not None and code != self.profile.model_code:
                raise InstrumentProtocolError(
                    self.name, self.address, f"model register reads {code}, profile {self.profile.name!r} expects "
                    f"{self.profile.model_code}: wrong controller or wrong profile",
                    register=self.profile.model_register)
        return Identity(vendor=self.profile.vendor, model=self.profile.model, extra=extra)

    def setpoint_range(self) -> tuple[float, float]:
        if self._range is None:
            if self.profile.setpoint_min is not None and self.profile.setpoint_max is not None:
                lo = self._read_value(self.profile.setpoint_min)
                hi = self._read_value(self.profile.setpoint_max)
                if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                    raise InstrumentProtocolError(self.name, self.address, f"setpoint range reads {lo}..{hi}",
                                                  register=self.profile.setpoint_min)
                self._range = (lo, hi)
            else:
                assert self.profile.fixed_range_c is not None
                self._range = self.profile.fixed_range_c
        return self._range

    def read_temperature(self) -> float:
        """The process value; a garbage reading (sensor break, corrupted reply) is re-read, bounded."""
        for attempt in range(self.retries + 1):
            value = self._read_value(self.profile.process_value)
            if math.isfinite(value) and PLAUSIBLE_C[0] <= value <= PLAUSIBLE_C[1]:
                return value
            err = InstrumentProtocolError(self.name, self.address, f"process value reads {value!r}, not a plausible "
                                          "temperature (sensor break?)", register=self.profile.process_value)
            if attempt < self.retries:
                log.info("%s: process value reads %r; reading again (%d of %d)", self.name, value, attempt + 1,
                         self.retries)
                if self.on_retry:
                    self.on_retry(attempt + 1, err)
                self._sleep(self.backoff_s * (2 ** attempt))
        raise err

    def read_setpoint(self) -> float:
        return self._read_value(self.profile.setpoint)

    def current_setpoint(self) -> float:
        """The working (closed-loop) setpoint where the map has one (F4T 2810), else the setpoint."""
        register = self.profile.current_setpoint
        return self._read_value(register) if register is not None else self.read_setpoint()

    def set_setpoint(self, value_c: float) -> None:
        lo, hi = self.setpoint_range()
        if not (math.isfinite(value_c) and lo <= value_c <= hi):
            raise LimitError(self.name, self.address, f"setpoint {value_c} C is outside the controller's range "
                             f"{lo}..{hi} C; nothing was written", register=self.profile.setpoint)
        units = self.units()
        words = self.profile.encode(value_c, units=units)
        self.write_words(self.profile.setpoint, words)
        back = self.read_setpoint()
        # A 16-bit register holds the setpoint to one count (of 10**-decimals, in °F or °C).
        slack = 0.501 * units.resolution_c() + 1e-9 if self.profile.encoding == "int16_tenths" else 1e-3
        if abs(back - value_c) > slack:
            raise InstrumentProtocolError(self.name, self.address, f"setpoint written as {value_c} reads back {back}",
                                          register=self.profile.setpoint)

    def outputs(self) -> tuple[float | None, float | None]:
        """Heat and cool output, percent (None where the profile has no register)."""
        heat = self._read_value(self.profile.heat_output, output=True) if self.profile.heat_output is not None else None
        cool = self._read_value(self.profile.cool_output, output=True) if self.profile.cool_output is not None else None
        return heat, cool
