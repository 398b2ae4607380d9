"""Chamber controller register maps as data: another controller is a new profile, not new code.

A profile names the holding registers (0-based) of the process value, the setpoint,
the heat/cool outputs and the setpoint range, and how values are encoded: signed
16-bit tenths (Watlow F4 style) or IEEE float32 over two registers, low word first
(F4T style) or high word first. The simulated chamber serves any profile, so a
profile is tested against the same driver code.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

ENCODINGS = ("int16_tenths", "float32_lwf", "float32_hwf")


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

    def encode(self, value: float, *, output: bool = False) -> list[int]:
        """Register words for a temperature (or an output % when output=True)."""
        if not math.isfinite(value):
            raise ValueError(f"cannot encode {value!r}")
        if self.encoding == "int16_tenths":
            raw = int(round(value * (100.0 if output else 10.0)))
            if not -32768 <= raw <= 32767:
                raise ValueError(f"{value} does not fit a signed 16-bit register")
            return [raw & 0xFFFF]
        hi, lo = struct.unpack(">HH", struct.pack(">f", value))
        return [lo, hi] if self.encoding == "float32_lwf" else [hi, lo]

    def decode(self, words: list[int], *, output: bool = False) -> float:
        if len(words) != self.words:
            raise ValueError(f"expected {self.words} register(s), got {len(words)}")
        if self.encoding == "int16_tenths":
            raw = words[0] - 0x10000 if words[0] & 0x8000 else words[0]
            return raw / (100.0 if output else 10.0)
        hi, lo = (words[1], words[0]) if self.encoding == "float32_lwf" else (words[0], words[1])
        return struct.unpack(">f", struct.pack(">HH", hi, lo))[0]

    def registers(self) -> dict[str, int]:
        """Named registers this profile uses (for the simulator's register layout)."""
        names = ("process_value", "setpoint", "setpoint_min", "setpoint_max", "heat_output", "cool_output",
                 "model_register")
        return {n: getattr(self, n) for n in names if getattr(self, n) is not None}


PROFILES: dict[str, ChamberProfile] = {
    # The default map (docs/design.md, "Instruments"): Watlow F4 style, signed tenths of a degree;
    # register 0 reads the model number.
    "watlow_f4": ChamberProfile(
        name="watlow_f4", encoding="int16_tenths", process_value=100, setpoint=300, setpoint_min=602,
        setpoint_max=603, heat_output=103, cool_output=107, model_register=0, model_code=5270,
        vendor="Watlow", model="F4",
    ),
    # F4T style: IEEE float, low word first (PV 'Analog Input 1', SP 'Control Loop 1 set point');
    # check the addresses against your controller's manual before pointing it at hardware.
    "watlow_f4t": ChamberProfile(
        name="watlow_f4t", encoding="float32_lwf", process_value=360, setpoint=2160, setpoint_min=None,
        setpoint_max=None, fixed_range_c=(-73.0, 190.0), vendor="Watlow", model="F4T",
    ),
}


def profile_from(spec: str | Mapping[str, Any]) -> ChamberProfile:
    """A profile by name, or from a mapping (a custom map in the lab configuration)."""
    if isinstance(spec, str):
        try:
            return PROFILES[spec]
        except KeyError:
            raise ValueError(f"unknown chamber profile {spec!r}; known: {', '.join(PROFILES)}") from None
    data = dict(spec)
    base = data.pop("base", None)
    if base is not None:
        merged = {f.name: getattr(profile_from(base), f.name) for f in fields(ChamberProfile)}
        merged.update(data)
        data = merged
    known = {f.name for f in fields(ChamberProfile)}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"chamber profile: unknown key(s) {', '.join(sorted(unknown))}")
    if "fixed_range_c" in data and data["fixed_range_c"] is not None:
        data["fixed_range_c"] = tuple(float(v) for v in data["fixed_range_c"])
    try:
        return ChamberProfile(**data)
    except TypeError as exc:
        raise ValueError(f"chamber profile: {exc}") from None
