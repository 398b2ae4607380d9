"""The drivers labrunner ships, as `registry.Driver` entries (declared in pyproject.toml's
`[project.entry-points."labrunner.drivers"]`, so they are found the way a lab's own are).

Each has the pydantic model of its lab-configuration section; `lab.py` validates a section
against it with the file's line numbers, then calls the factory.
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import Field, field_validator, model_validator

from labrunner.clock import Clock
from labrunner.yaml_config import Range, RangedModel

from .chamber_modbus import ModbusAddress, ModbusChamber
from .chamber_profiles import profile_from
from .imu_serial import SerialImu
from .rate_table import SerialRateTable
from .registry import Driver, DriverOptions
from .table_profiles import language_from

# The lab configuration's ranges (item 7 of issue 13, moved here with the sections they check).
# Every number of a lab configuration, finite and physical (checked by `labrunner check --lab` with
# file, line, key, value and range): a 1e-9 s timeout or a speed of 1e-12 would spin or never end.
BAUD = Range(50, 10_000_000, "baud", integer=True)
TIMEOUT_S = Range(0.01, 60.0, "s")
RETRIES = Range(0, 20, integer=True)
BACKOFF_S = Range(0.0, 60.0, "s")
RANGES: dict[str, Range] = {
    "chamber.port": Range(1, 65535, integer=True), "chamber.baudrate": BAUD,
    "chamber.device_id": Range(0, 247, integer=True), "chamber.timeout_s": TIMEOUT_S,
    "chamber.retries": RETRIES, "chamber.backoff_s": BACKOFF_S,
    "table.baudrate": BAUD, "table.timeout_s": TIMEOUT_S, "table.retries": RETRIES, "table.backoff_s": BACKOFF_S,
    "imu.baudrate": BAUD, "imu.rate_hz": Range(0.1, 10000.0, "Hz"),
    "clock.speed": Range(0.01, 100000.0, "x wall time"),
}
REGISTER = Range(0, 65535, integer=True)  # a custom chamber profile's register addresses
PROFILE_REGISTERS = ("process_value", "setpoint", "setpoint_min", "setpoint_max", "heat_output", "cool_output",
                     "model_register", "decimals_register", "units_register", "current_setpoint", "loop_stride")
SETPOINT_C = Range(-100.0, 250.0, "C")


def _profile_problem(spec: dict[str, Any]) -> str | None:
    """A custom profile's registers and fixed range, which the profile's own checks take on trust."""
    for key in PROFILE_REGISTERS:
        if spec.get(key) is not None and (problem := REGISTER.problem(spec[key])):
            return f".{key} {problem}"
    fixed = spec.get("fixed_range_c")
    if fixed is not None:
        if not isinstance(fixed, list) or len(fixed) != 2:
            return f".fixed_range_c must be [low, high] in C, got {fixed!r}"
        for value in fixed:
            if problem := SETPOINT_C.problem(value):
                return f".fixed_range_c {problem}"
        if fixed[0] >= fixed[1]:
            return ".fixed_range_c must be [low, high] with low below high"
    return None


class _Strict(RangedModel):
    RANGES: ClassVar[dict[str, Range]] = RANGES


class ModbusFields(_Strict):
    """Where a Modbus controller is and how hard to try (`watlow_f4`, `watlow_f4t`: the map is the driver's)."""

    SECTION: ClassVar[str] = "chamber"
    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = "127.0.0.1"
    port: int = Field(502, ge=1, le=65535)
    serial_port: str | None = None
    baudrate: int = Field(19200, gt=0)
    device_id: int = Field(1, ge=0, le=247)
    timeout_s: float = Field(1.0, gt=0)
    retries: int = Field(2, ge=0, le=20)
    backoff_s: float = Field(0.5, ge=0)

    @model_validator(mode="after")
    def _transport_keys(self) -> ModbusFields:
        # Keys of the other transport would be ignored: refused, so the file says what is used.
        if self.transport == "rtu" and not self.serial_port:
            raise ValueError("transport: rtu needs serial_port (e.g. /dev/ttyUSB0)")
        unused = ({"serial_port"} if self.transport == "tcp" else {"host", "port"}) & self.model_fields_set
        if unused:
            raise ValueError(f"{', '.join(sorted(unused))} is not used with transport: {self.transport}")
        return self


class ModbusChamberSection(ModbusFields):
    """`modbus_chamber`: any register map, by name or as a mapping (`{base: watlow_f4, ...}`)."""

    profile: str | dict[str, Any] = "watlow_f4"

    @field_validator("profile")
    @classmethod
    def _known_profile(cls, v: str | dict[str, Any]) -> str | dict[str, Any]:
        if isinstance(v, dict) and (problem := _profile_problem(v)):
            raise ValueError(problem)
        profile_from(v)  # raises ValueError naming the problem
        return v


def _modbus_chamber(section: ModbusFields, clock: Clock, options: DriverOptions, profile: Any) -> ModbusChamber:
    s = section
    return ModbusChamber(
        ModbusAddress(transport=s.transport, host=s.host, port=s.port, serial_port=s.serial_port,
                      baudrate=s.baudrate, device_id=s.device_id),
        profile_from(profile), name=options.name, timeout_s=s.timeout_s, retries=s.retries, backoff_s=s.backoff_s,
        sleep=clock.sleep, on_retry=options.on_retry)


def make_modbus_chamber(section: ModbusChamberSection, clock: Clock, options: DriverOptions) -> ModbusChamber:
    return _modbus_chamber(section, clock, options, section.profile)


def make_watlow_f4(section: ModbusFields, clock: Clock, options: DriverOptions) -> ModbusChamber:
    return _modbus_chamber(section, clock, options, "watlow_f4")


def make_watlow_f4t(section: ModbusFields, clock: Clock, options: DriverOptions) -> ModbusChamber:
    return _modbus_chamber(section, clock, options, "watlow_f4t")


class SerialFields(_Strict):
    SECTION: ClassVar[str] = "table"
    port: str
    baudrate: int = Field(115200, gt=0)
    timeout_s: float = Field(0.5, gt=0)
    retries: int = Field(2, ge=0, le=20)
    backoff_s: float = Field(0.2, ge=0)


class SerialTableSection(SerialFields):
    """`serial_table`: a rate table whose command language is a profile (`drivers/table_profiles.py`):
    a shipped one by name, or a mapping (`{base: ideal_aerosmith, terminator: "\\r"}`)."""

    language: str | dict[str, Any] = "labrunner"

    @field_validator("language")
    @classmethod
    def _known_language(cls, v: str | dict[str, Any]) -> str | dict[str, Any]:
        language_from(v)  # raises ValueError naming the problem
        return v


def _serial_table(section: SerialFields, clock: Clock, options: DriverOptions, language: Any) -> SerialRateTable:
    s = section
    return SerialRateTable(s.port, max_rate_dps=options.max_rate_dps, baudrate=s.baudrate, name=options.name,
                           timeout_s=s.timeout_s, retries=s.retries, backoff_s=s.backoff_s, sleep=clock.sleep,
                           on_retry=options.on_retry, language=language_from(language))


def make_serial_table(section: SerialTableSection, clock: Clock, options: DriverOptions) -> SerialRateTable:
    return _serial_table(section, clock, options, section.language)


def make_labrunner_table(section: SerialFields, clock: Clock, options: DriverOptions) -> SerialRateTable:
    return _serial_table(section, clock, options, "labrunner")


def make_ideal_aerosmith(section: SerialFields, clock: Clock, options: DriverOptions) -> SerialRateTable:
    return _serial_table(section, clock, options, "ideal_aerosmith")


class LabrunnerImuSection(_Strict):
    SECTION: ClassVar[str] = "imu"
    port: str
    baudrate: int = Field(921600, gt=0)
    rate_hz: float = Field(50.0, gt=0, le=10000)


def make_labrunner_imu(section: LabrunnerImuSection, clock: Clock, options: DriverOptions) -> SerialImu:
    return SerialImu(section.port, rate_hz=section.rate_hz, baudrate=section.baudrate, name=options.name,
                     on_event=options.on_event)


MODBUS_CHAMBER = Driver("chamber", make_modbus_chamber, ModbusChamberSection,
                        "Modbus TCP/RTU chamber controller, register map from `profile`")
WATLOW_F4 = Driver("chamber", make_watlow_f4, ModbusFields,
                   "Watlow F4 over Modbus (decimals 606 and units 901 read at connect)")
WATLOW_F4T = Driver("chamber", make_watlow_f4t, ModbusFields, "Watlow F4T over Modbus (float32 map)")
SERIAL_TABLE = Driver("table", make_serial_table, SerialTableSection,
                      "serial rate table, command language from `language` (a profile)")
IDEAL_AEROSMITH = Driver("table", make_ideal_aerosmith, SerialFields,
                         "Ideal Aerosmith table language (JOG, STO, SRV, HOM; queries end in '?')")
LABRUNNER_TABLE = Driver("table", make_labrunner_table, SerialFields,
                         "labrunner's own ASCII table language (IDN LIM JOG STO PVE STA)")
LABRUNNER_IMU = Driver("imu", make_labrunner_imu, LabrunnerImuSection,
                       "labrunner's 20-byte IMU frame stream (sync, counter, CRC-16)")
