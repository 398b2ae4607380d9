"""The lab: which instruments, at which addresses, and the connected drivers.

A lab configuration (YAML) names the chamber controller (Modbus TCP or RTU, register
profile), the rate table's and the IMU's serial lines, and optionally a clock speed
(to rehearse against `labrunner sim serve --speed N`). `--sim` builds a simulated
lab instead and points the same drivers at it.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from labrunner.clock import Clock, ScaledClock, VirtualClock, WallClock
from labrunner.drivers.chamber_modbus import ModbusAddress, ModbusChamber
from labrunner.drivers.chamber_profiles import profile_from
from labrunner.drivers.imu_serial import SerialImu
from labrunner.drivers.protocols import Chamber, Imu, Operator, RateTable
from labrunner.drivers.rate_table import SerialRateTable
from labrunner.operator import ConsoleOperator, SimOperator  # the operators live there; importable here
from labrunner.yaml_config import load_model, validate

if TYPE_CHECKING:  # the sims are imported only when a dry run is built
    from labrunner.sims.lab import SimLab

log = logging.getLogger(__name__)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ChamberSection(_Strict):
    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = "127.0.0.1"
    port: int = Field(502, ge=1, le=65535)
    serial_port: str | None = None
    baudrate: int = Field(19200, gt=0)
    device_id: int = Field(1, ge=0, le=247)
    profile: str | dict[str, Any] = "watlow_f4"
    timeout_s: float = Field(1.0, gt=0)
    retries: int = Field(2, ge=0, le=20)
    backoff_s: float = Field(0.5, ge=0)

    @field_validator("profile")
    @classmethod
    def _known_profile(cls, v: str | dict[str, Any]) -> str | dict[str, Any]:
        profile_from(v)  # raises ValueError naming the problem
        return v


class SerialSection(_Strict):
    port: str
    baudrate: int = Field(115200, gt=0)
    timeout_s: float = Field(0.5, gt=0)
    retries: int = Field(2, ge=0, le=20)
    backoff_s: float = Field(0.2, ge=0)


class ImuSection(_Strict):
    port: str
    baudrate: int = Field(921600, gt=0)
    rate_hz: float = Field(50.0, gt=0, le=10000)


class ClockSection(_Strict):
    speed: float = Field(1.0, gt=0, le=100000)


class LabConfig(_Strict):
    name: str = "lab"
    chamber: ChamberSection
    table: SerialSection
    imu: ImuSection
    clock: ClockSection = ClockSection()


def load_lab_config(path: str | Path) -> tuple[LabConfig, str]:
    return load_model(LabConfig, path)


def lab_config_from_dict(data: dict[str, Any], source: str = "lab configuration") -> LabConfig:
    return validate(LabConfig, data, {}, source)


@dataclass
class Lab:
    """Connected instruments plus the clock and operator that go with them."""

    chamber: Chamber
    table: RateTable
    imu: Imu
    operator: Operator
    clock: Clock
    config: LabConfig
    sim: SimLab | None = None  # the simulated lab behind a dry run, if any

    def close(self) -> None:
        for inst in (self.imu, self.table, self.chamber):
            try:
                inst.close()
            except Exception as exc:  # closing a broken link must not hide why the run ended
                log.debug("closing %s: %s", type(inst).__name__, exc)
        if self.sim is not None:
            self.sim.close()


def build_drivers(config: LabConfig, clock: Clock, *, max_rate_dps: float,
                  on_retry: Callable[[int, Exception], None] | None = None,
                  on_event: Callable[[str, str], None] | None = None,
                  ) -> tuple[ModbusChamber, SerialRateTable, SerialImu]:
    """Drivers for a lab configuration; waits and backoffs go through `clock`."""
    c = config.chamber
    chamber = ModbusChamber(
        ModbusAddress(transport=c.transport, host=c.host, port=c.port, serial_port=c.serial_port,
                      baudrate=c.baudrate, device_id=c.device_id),
        profile_from(c.profile), timeout_s=c.timeout_s, retries=c.retries, backoff_s=c.backoff_s, sleep=clock.sleep,
        on_retry=on_retry)
    t = config.table
    table = SerialRateTable(t.port, max_rate_dps=max_rate_dps, baudrate=t.baudrate, timeout_s=t.timeout_s,
                            retries=t.retries, backoff_s=t.backoff_s, sleep=clock.sleep, on_retry=on_retry)
    i = config.imu
    imu = SerialImu(i.port, rate_hz=i.rate_hz, baudrate=i.baudrate, on_event=on_event)
    log.info("lab %r: chamber %s (profile %s), rate table %s, IMU %s at %g Hz", config.name, chamber.address,
             chamber.profile.name, table.address, imu.address, imu.rate_hz)
    return chamber, table, imu


def real_lab(config: LabConfig, *, max_rate_dps: float, operator: Operator | None = None,
             on_retry: Callable[[int, Exception], None] | None = None,
             on_event: Callable[[str, str], None] | None = None) -> Lab:
    clock: Clock = WallClock() if config.clock.speed == 1.0 else ScaledClock(config.clock.speed)
    chamber, table, imu = build_drivers(config, clock, max_rate_dps=max_rate_dps, on_retry=on_retry,
                                        on_event=on_event)
    return Lab(chamber=chamber, table=table, imu=imu, operator=operator or ConsoleOperator(), clock=clock,
               config=config)


def simulated_lab(*, max_rate_dps: float, sim_config: Any = None, start_t: float = 0.0, orientation: str | None = None,
                  link: str = "tcp", on_retry: Callable[[int, Exception], None] | None = None,
                  on_event: Callable[[str, str], None] | None = None) -> Lab:
    """A dry-run lab: sims on a virtual clock, reached through the real drivers."""
    from labrunner.sims.lab import SimLab
    from labrunner.sims.world import SimLabConfig

    cfg = sim_config or SimLabConfig()
    if orientation is not None:
        cfg = dataclasses.replace(cfg, orientation=orientation)
    clock = VirtualClock(start=start_t)
    sim = SimLab(cfg, clock, link=link)
    config = lab_config_from_dict(sim.lab_config(), "simulated lab")
    chamber, table, imu = build_drivers(config, clock, max_rate_dps=max_rate_dps, on_retry=on_retry,
                                        on_event=on_event)

    def barrier() -> None:
        # Dry runs are deterministic: after each advance, wait until the driver has parsed every
        # frame the simulated IMU sent for it (bounded, in case a fault ate the last one).
        last = sim.last_imu_counter
        if last is not None and isinstance(imu, SerialImu) and imu.link_up:
            imu.wait_counter16(last, 1.0)

    clock.add_barrier(barrier)
    return Lab(chamber=chamber, table=table, imu=imu, operator=SimOperator(sim, clock), clock=clock,
               config=config, sim=sim)


__all__ = [
    "ConsoleOperator", "Lab", "LabConfig", "Operator", "SimOperator", "build_drivers", "lab_config_from_dict",
    "load_lab_config", "real_lab", "simulated_lab",
]
