"""Fake instruments for in-process runner tests, on a `VirtualClock`.

They implement `labrunner.drivers.protocols` (Chamber, RateTable, Imu, Operator, Instruments)
with the least physics that makes a campaign meaningful: the chamber's air moves to its setpoint
at a fixed rate, the table reaches a commanded rate at once, the IMU streams frames at its rate
whose temperature is the chamber's and whose gyro z is the table's rate. Each fake records the
calls it gets (with the clock time) and can be told to fail.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from labrunner.clock import VirtualClock
from labrunner.domain import up_vector
from labrunner.drivers.errors import InstrumentError, InstrumentTimeout, LimitError
from labrunner.drivers.protocols import Identity, ImuRecord, ImuSample, TableStatus


class _Fake:
    """Call log and failure injection shared by the fakes."""

    name = "fake"
    address = "fake:0"

    def __init__(self, clock: VirtualClock) -> None:
        self.clock = clock
        self.calls: list[tuple[float, str, tuple[object, ...]]] = []
        self._failures: dict[str, int] = defaultdict(int)
        self.connected = False

    def fail(self, method: str, times: int = 1) -> None:
        """The next `times` calls of `method` raise an InstrumentTimeout (as a driver whose retries ran out)."""
        self._failures[method] += times

    def _call(self, method: str, *args: object) -> None:
        self.calls.append((self.clock.now(), method, args))
        if self._failures[method] > 0:
            self._failures[method] -= 1
            raise InstrumentTimeout(self.name, self.address, f"no reply to {method} (fake failure)")

    def called(self, method: str) -> list[tuple[float, tuple[object, ...]]]:
        return [(t, args) for t, m, args in self.calls if m == method]

    def connect(self) -> None:
        self._call("connect")
        self.connected = True

    def close(self) -> None:
        self.connected = False


class FakeChamber(_Fake):
    name = "chamber"
    address = "fake:chamber"

    def __init__(self, clock: VirtualClock, *, start_c: float = 23.0, ramp_c_per_s: float = 0.1,
                 setpoint_range: tuple[float, float] = (-70.0, 180.0)) -> None:
        super().__init__(clock)
        self.pv = start_c
        self.setpoint = start_c
        self.ramp_c_per_s = ramp_c_per_s
        self.range = setpoint_range
        self.stuck_heater_c: float | None = None  # a stuck heater drives the air here, whatever the setpoint
        self._t = clock.now()

    def air_c(self) -> float:
        """The air temperature now (moves towards its target at the ramp rate)."""
        now = self.clock.now()
        target = self.stuck_heater_c if self.stuck_heater_c is not None else self.setpoint
        step = self.ramp_c_per_s * (now - self._t)
        self.pv = target if abs(target - self.pv) <= step else self.pv + np.sign(target - self.pv) * step
        self._t = now
        return float(self.pv)

    def identity(self) -> Identity:
        self._call("identity")
        return Identity(vendor="Fake", model="chamber")

    def setpoint_range(self) -> tuple[float, float]:
        self._call("setpoint_range")
        return self.range

    def read_temperature(self) -> float:
        self._call("read_temperature")
        return self.air_c()

    def read_setpoint(self) -> float:
        self._call("read_setpoint")
        return self.setpoint

    def set_setpoint(self, value_c: float) -> None:
        self._call("set_setpoint", value_c)
        if not self.range[0] <= value_c <= self.range[1]:
            raise LimitError(self.name, self.address, f"setpoint {value_c} C outside {self.range}")
        self.air_c()
        self.setpoint = value_c


class FakeTable(_Fake):
    name = "rate table"
    address = "fake:table"

    def __init__(self, clock: VirtualClock, *, max_rate_dps: float = 300.0) -> None:
        super().__init__(clock)
        self.max_rate_dps = max_rate_dps
        self.rate = 0.0
        self.overspeed_dps: float | None = None  # a runaway drive reports this rate

    def identity(self) -> Identity:
        self._call("identity")
        return Identity(vendor="Fake", model="table")

    def jog(self, rate_dps: float) -> None:
        self._call("jog", rate_dps)
        if abs(rate_dps) > self.max_rate_dps:
            raise LimitError(self.name, self.address, f"rate {rate_dps} above {self.max_rate_dps}")
        self.rate = rate_dps

    def stop(self) -> None:
        self._call("stop")
        self.rate = 0.0

    def velocity(self) -> float:
        self._call("velocity")
        return self.overspeed_dps if self.overspeed_dps is not None else self.rate

    def status(self) -> TableStatus:
        self._call("status")
        return TableStatus(mode="JOG" if self.rate else "STOP", settled=True)


class FakeImu(_Fake):
    """Frames at `rate_hz` from the last (re)start of the stream, computed from the clock."""

    name = "imu"
    address = "fake:imu"

    def __init__(self, clock: VirtualClock, chamber: FakeChamber, table: FakeTable, *, rate_hz: float = 50.0) -> None:
        super().__init__(clock)
        self.chamber = chamber
        self.table = table
        self.rate_hz = rate_hz
        self.orientation = "z_up"
        self.self_heating_c = 0.0
        self._t_stream: float | None = None
        self._lose: list[int] = []  # frames lost in each of the next records

    def lose_frames(self, per_record: list[int]) -> None:
        """The next len(per_record) end_record calls each miss that many frames (at the end)."""
        self._lose.extend(per_record)

    def connect(self) -> None:
        super().connect()
        if self._t_stream is None:
            self._t_stream = self.clock.now()

    def restart_stream(self) -> None:
        self._call("restart_stream")
        self._t_stream = self.clock.now()

    def _last_counter(self) -> int:
        if self._t_stream is None:
            return -1
        return int(np.floor((self.clock.now() - self._t_stream) * self.rate_hz + 1e-9))

    def _temp_c(self) -> float:
        return self.chamber.air_c() + self.self_heating_c

    def latest(self) -> ImuSample | None:
        k = self._last_counter()
        if k < 0:
            return None
        g = tuple(float(v) for v in up_vector(self.orientation))
        return ImuSample(counter=k, accel_g=(g[0], g[1], g[2]), gyro_dps=(0.0, 0.0, self.table.rate),
                         temp_c=self._temp_c())

    def begin_record(self) -> int:
        self._call("begin_record")
        return self._last_counter()

    def end_record(self, start: int, n_frames: int, timeout_s: float) -> ImuRecord:
        self._call("end_record", start, n_frames)
        last = min(self._last_counter(), start + n_frames)
        lost = self._lose.pop(0) if self._lose else 0
        counter = np.arange(start + 1, max(start + 1, last - lost + 1), dtype=np.int64)
        n = counter.size
        accel = np.tile(up_vector(self.orientation), (n, 1))
        gyro = np.zeros((n, 3))
        gyro[:, 2] = self.table.rate
        return ImuRecord(counter=counter, accel_g=accel, gyro_dps=gyro, temp_c=np.full(n, self._temp_c()),
                         expected=n_frames, dropped=n_frames - n, corrupt=0)


class FakeOperator:
    """Remounts at once in the orientation asked (taking `remount_s` of clock time), and says so; `mount_wrongly`
    makes the next remounts turn the IMU elsewhere (or, with None, leave it as it was)."""

    def __init__(self, clock: VirtualClock, imu: FakeImu, remount_s: float = 60.0) -> None:
        self.clock = clock
        self.imu = imu
        self.remount_s = remount_s
        self.remounts: list[tuple[float, str, str]] = []
        self._wrong: list[str | None] = []

    def mount_wrongly(self, *orientations: str | None) -> None:
        """The next len(orientations) remounts mount these instead of the one asked (None: skipped)."""
        self._wrong.extend(orientations)

    def remount(self, orientation: str, prompt: str) -> None:
        self.remounts.append((self.clock.now(), orientation, prompt))
        self.clock.sleep(self.remount_s)
        if self._wrong:
            orientation = self._wrong.pop(0) or self.imu.orientation
        self.imu.orientation = orientation


@dataclass
class FakeLab:
    """The `Instruments` bundle the runner runs on."""

    clock: VirtualClock = field(default_factory=VirtualClock)
    chamber: FakeChamber = field(init=False)
    table: FakeTable = field(init=False)
    imu: FakeImu = field(init=False)
    operator: FakeOperator = field(init=False)

    def __post_init__(self) -> None:
        self.chamber = FakeChamber(self.clock)
        self.table = FakeTable(self.clock)
        self.imu = FakeImu(self.clock, self.chamber, self.table)
        self.operator = FakeOperator(self.clock, self.imu)

    def close(self) -> None:
        for inst in (self.chamber, self.table, self.imu):
            inst.close()


__all__ = ["FakeChamber", "FakeImu", "FakeLab", "FakeOperator", "FakeTable", "InstrumentError"]
