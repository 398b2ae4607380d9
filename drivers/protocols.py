"""What the sequencer needs from each instrument, independent of protocol and of simulation.

`labrunner.sequencer` talks only to these interfaces; a Modbus chamber, a serial rate
table and a serial IMU stream implement them, and so would a different controller.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Identity:
    """Who answered: checked at preflight against the lab configuration."""

    vendor: str
    model: str
    serial: str = ""
    extra: dict[str, str] = field(default_factory=dict)


@runtime_checkable
class Chamber(Protocol):
    name: str
    address: str

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def identity(self) -> Identity: ...
    def setpoint_range(self) -> tuple[float, float]: ...
    def read_temperature(self) -> float: ...
    def read_setpoint(self) -> float: ...
    def set_setpoint(self, value_c: float) -> None: ...


@dataclass(frozen=True)
class TableStatus:
    mode: str  # "JOG", "STOP", "FAULT"
    settled: bool
    fault: str | None = None


@runtime_checkable
class RateTable(Protocol):
    name: str
    address: str
    max_rate_dps: float

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def identity(self) -> Identity: ...
    def jog(self, rate_dps: float) -> None: ...
    def stop(self) -> None: ...
    def velocity(self) -> float: ...
    def status(self) -> TableStatus: ...


@dataclass
class ImuRecord:
    """Consecutive IMU frames (by counter) in physical units, plus what went missing."""

    counter: np.ndarray  # int64, unwrapped frame counter
    accel_g: np.ndarray  # (N, 3)
    gyro_dps: np.ndarray  # (N, 3)
    temp_c: np.ndarray  # (N,)
    expected: int  # frames the window should hold
    dropped: int  # expected minus received (counter gaps)
    corrupt: int  # corrupted stretches seen while recording
    lsb: tuple[float, float, float] | None = None  # accel, gyro, temp LSB when values are whole counts

    def __len__(self) -> int:
        return int(self.counter.size)


@dataclass(frozen=True)
class ImuSample:
    counter: int
    accel_g: tuple[float, float, float]
    gyro_dps: tuple[float, float, float]
    temp_c: float


@runtime_checkable
class Imu(Protocol):
    name: str
    address: str
    rate_hz: float

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def latest(self) -> ImuSample | None: ...
    def begin_record(self) -> int: ...
    def end_record(self, start: int, n_frames: int, timeout_s: float) -> ImuRecord: ...
    def restart_stream(self) -> None: ...


class Operator(Protocol):
    """Whoever remounts the IMU when the procedure asks."""

    def remount(self, orientation: str, prompt: str) -> None: ...


class Instruments(Protocol):
    """What the sequencer runs on: the connected instruments, the operator and the clock.

    `labrunner.lab.Lab` is the concrete bundle; tests pass fakes.
    """

    chamber: Chamber
    table: RateTable
    imu: Imu
    operator: Operator
    clock: Any
