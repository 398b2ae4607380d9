"""Chamber controller register maps as data: another controller is a new profile, not new code.

A profile names the holding registers (0-based PDU addresses) of the process value, the
setpoint, the heat/cool outputs and the setpoint range, and how values are encoded: signed
16-bit counts (Watlow F4 style) or IEEE float32 over two registers, low word first (F4T style)
or high word first. A 16-bit map may name the controller's decimal-places and units registers;
the driver reads them at connect (`ControllerUnits`) and converts every temperature (process
value, setpoint writes, limits) between the controller's units and degrees Celsius. The
simulated chamber serves any profile in any units, so a profile is tested against the same
driver code.

Sources (cited per profile below): Espec North America's ChamberConnectLibrary,
`chamberconnectlibrary/watlowf4.py` and `watlowf4t.py` with its `modbus.py` (word order), and the
Watlow F4 / TestEquity F4T Modbus register lists they follow.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from .named_spec import from_spec

ENCODINGS = ("int16_tenths", "float32_lwf", "float32_hwf")  # int16_tenths: 10**-decimals counts (1 unless read)


@dataclass(frozen=True)
class ControllerUnits:
    """How the controller shows temperatures: decimal places of its 16-bit values, and °F or °C.

    Watlow F4 (Espec `watlowf4.py`): register 606 is input 1's decimal places, each temperature
    register holds value x 10**decimals (Espec scales by 1/(606 x 10), the same for 0 and 1
    decimals; for 2 decimals it gives 1/20, where the F4's display means 1/100 -- we use
    10**-decimals). Register 901 is the temperature units, 0 = °F, 1 = °C (Espec
    `get_loop_units`: `'°C' if read_holding(901) else '°F'`)."""

    decimals: int = 1
    fahrenheit: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.decimals <= 3:
            raise ValueError(f"decimal places must be 0..3, got {self.decimals}")

    @property
    def symbol(self) -> str:
        return "F" if self.fahrenheit else "C"

    def to_controller(self, value_c: float) -> float:
        return value_c * 9.0 / 5.0 + 32.0 if self.fahrenheit else value_c

    def to_celsius(self, value: float) -> float:
        return (value - 32.0) * 5.0 / 9.0 if self.fahrenheit else value

    def resolution_c(self) -> float:
        """One count of a 16-bit register, in °C (a setpoint reads back within half of it)."""
        step = 10.0 ** -self.decimals
        return step * 5.0 / 9.0 if self.fahrenheit else step


CELSIUS_TENTHS = ControllerUnits()


@dataclass(frozen=True)
class ChamberProfile:
    name: str
    encoding: str  # one of ENCODINGS
    process_value: int
    setpoint: int
    setpoint_min: int | None  # register of the controller's setpoint range, or None
    setpoint_max: int | None
    heat_output: int | None = None  # output %, same encoding (int16: % x100)
    cool_output: int | None = None
    model_register: int | None = None  # register that reads `model_code` (identity check)
    model_code: int | None = None
    vendor: str = ""
    model: str = ""
    fixed_range_c: tuple[float, float] | None = None  # when the range has no register
    decimals_register: int | None = None  # read at connect: decimal places of the 16-bit values
    units_register: int | None = None  # read at connect: 0 = °F, 1 = °C
    current_setpoint: int | None = None  # the working (closed-loop) setpoint, read-only
    loop_stride: int | None = None  # registers between one control loop's map and the next (None: one loop)

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise ValueError(f"chamber profile {self.name!r}: encoding must be one of {', '.join(ENCODINGS)}")
        if (self.setpoint_min is None) != (self.setpoint_max is None):
            raise ValueError(f"chamber profile {self.name!r}: give both setpoint_min and setpoint_max registers")
        if self.setpoint_min is None and self.fixed_range_c is None:
            raise ValueError(f"chamber profile {self.name!r}: needs setpoint range registers or fixed_range_c")

    @property
    def words(self) -> int:
        return 1 if self.encoding == "int16_tenths" else 2

    def encode(self, value: float, *, output: bool = False, units: ControllerUnits = CELSIUS_TENTHS) -> list[int]:
        """Register words for a temperature in °C, in the controller's `units` (or an output %, output=True)."""
        if not math.isfinite(value):
            raise ValueError(f"cannot encode {value!r}")
        shown = value if output else units.to_controller(value)
        if self.encoding == "int16_tenths":
            raw = int(round(shown * (100.0 if output else 10.0 ** units.decimals)))
            if not -32768 <= raw <= 32767:
                raise ValueError(f"{value} does not fit a signed 16-bit register")
            return [raw & 0xFFFF]
        hi, lo = struct.unpack(">HH", struct.pack(">f", shown))
        return [lo, hi] if self.encoding == "float32_lwf" else [hi, lo]

    def decode(self, words: list[int], *, output: bool = False, units: ControllerUnits = CELSIUS_TENTHS) -> float:
        """A temperature in °C from register words in the controller's `units` (or an output %)."""
        if len(words) != self.words:
            raise ValueError(f"expected {self.words} register(s), got {len(words)}")
        if self.encoding == "int16_tenths":
            raw = words[0] - 0x10000 if words[0] & 0x8000 else words[0]
            shown = raw / (100.0 if output else 10.0 ** units.decimals)
        else:
            hi, lo = (words[1], words[0]) if self.encoding == "float32_lwf" else (words[0], words[1])
            shown = struct.unpack(">f", struct.pack(">HH", hi, lo))[0]
        return shown if output else units.to_celsius(shown)

    def for_loop(self, loop: int) -> ChamberProfile:
        """The map of control loop `loop` (1-based): loop 1 as is, others shifted by `loop_stride`."""
        if loop == 1:
            return self
        if self.loop_stride is None:
            raise ValueError(f"chamber profile {self.name!r} has one control loop; loop {loop} does not exist")
        shift = (loop - 1) * self.loop_stride
        moved = {n: getattr(self, n) + shift for n in LOOP_REGISTERS if getattr(self, n) is not None}
        return replace(self, name=f"{self.name}_loop{loop}", **moved)

    def registers(self) -> dict[str, int]:
        """Named registers this profile uses (for the simulator's register layout)."""
        names = ("process_value", "setpoint", "setpoint_min", "setpoint_max", "heat_output", "cool_output",
                 "model_register", "decimals_register", "units_register", "current_setpoint")
        return {n: getattr(self, n) for n in names if getattr(self, n) is not None}


# Registers that belong to one control loop (shifted together by `for_loop`).
LOOP_REGISTERS = ("process_value", "setpoint", "setpoint_min", "setpoint_max", "current_setpoint")

PROFILES: dict[str, ChamberProfile] = {
    # Watlow F4 (Espec watlowf4.py, loop 1): PV 100 (`get_loop_pv`), setpoint 300 (`set_loop_sp`),
    # setpoint range 602/603 (`get_loop_range`), outputs 103/107 in hundredths of a percent
    # (`get_output`), all signed 16-bit; decimal places 606 (`__get_scalar`) and units 901
    # (`get_loop_units`) read at connect. Register 0 reads the model number (5270, the F4).
    "watlow_f4": ChamberProfile(
        name="watlow_f4", encoding="int16_tenths", process_value=100, setpoint=300, setpoint_min=602,
        setpoint_max=603, heat_output=103, cool_output=107, model_register=0, model_code=5270,
        vendor="Watlow", model="F4", decimals_register=606, units_register=901,
    ),
    # Watlow F4T (Espec watlowf4t.py, loop N = 1 + k): setpoint 2782 + 160k (`set_loop_sp`), working
    # (closed-loop) setpoint 2810 + 160k (`get_loop_sp` 'current'), process value 2820 + 160k
    # (`get_loop_pv`), range minimum 2774 and maximum 2776 + 160k (`get_loop_range`); IEEE float32
    # over two registers, low word first (Espec modbus.py `low_word_first=True`: struct 'HH' of
    # (word0, word1) on a little-endian host, so word 0 holds the low half). The F4T reports in its
    # display units; this map assumes °C (set the controller's units to °C).
    "watlow_f4t": ChamberProfile(
        name="watlow_f4t", encoding="float32_lwf", process_value=2820, setpoint=2782, setpoint_min=2774,
        setpoint_max=2776, current_setpoint=2810, loop_stride=160, vendor="Watlow", model="F4T",
    ),
}


def profile_from(spec: str | Mapping[str, Any]) -> ChamberProfile:
    """A profile by name, or from a mapping (a custom map in the lab configuration)."""
    return from_spec(spec, PROFILES, ChamberProfile, "chamber profile", pairs=("fixed_range_c",))
