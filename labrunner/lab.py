"""The lab: which instruments, their drivers and addresses, and the connected drivers.

A lab configuration (YAML) names each instrument's driver (`driver: watlow_f4`; found through
the `labrunner.drivers` entry-point group, `drivers/registry.py`) and that driver's keys (the
chamber's Modbus address, the table's and the IMU's serial lines), and optionally a clock speed
(to rehearse against `labrunner sim serve --speed N`). `--sim` builds a simulated lab instead
and points the same drivers at it.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, create_model

from labrunner.clock import Clock, ScaledClock, VirtualClock, WallClock
from labrunner.drivers import registry
from labrunner.drivers.builtin import RANGES
from labrunner.drivers.protocols import Chamber, Imu, Operator, RateTable
from labrunner.drivers.registry import InstalledDriver
from labrunner.operator import ConsoleOperator, SimOperator  # the operators live there; importable here
from labrunner.yaml_config import ConfigError, Range, RangedModel, load_yaml, read_text, validate

if TYPE_CHECKING:  # the sims are imported only when a dry run is built
    from labrunner.sims.lab import SimLab

log = logging.getLogger(__name__)
# Each instrument's name in its driver's errors and log lines.
ROLE_NAMES = {"chamber": "chamber", "table": "rate table", "imu": "imu"}


class _Strict(RangedModel):
    RANGES: ClassVar[dict[str, Range]] = RANGES


class ClockSection(_Strict):
    SECTION: ClassVar[str] = "clock"
    speed: float = Field(1.0, gt=0, le=100000)


@dataclass(frozen=True)
class ResolvedInstrument:
    """An instrument section with its driver found and its keys validated against the driver's model."""

    kind: str
    driver: InstalledDriver
    section: BaseModel


class LabConfig(_Strict):
    """A lab configuration. Each instrument section names its `driver` (an entry of the
    `labrunner.drivers` group; without one, labrunner's own for that instrument) and holds that
    driver's keys, validated against the driver's own model (`section(kind)`)."""

    name: str = "lab"
    chamber: dict[str, Any]
    table: dict[str, Any]
    imu: dict[str, Any]
    clock: ClockSection = ClockSection()
    _resolved: dict[str, ResolvedInstrument] = PrivateAttr(default_factory=dict)

    def driver_name(self, kind: str) -> str:
        return str(getattr(self, kind).get("driver") or registry.DEFAULTS[kind])

    def instrument(self, kind: str) -> ResolvedInstrument:
        if kind not in self._resolved:
            resolve_drivers(self, {}, f"lab configuration '{self.name}'")
        return self._resolved[kind]

    def section(self, kind: str) -> Any:
        """The instrument's validated section (the driver's model: `.port`, `.timeout_s`, ...)."""
        return self.instrument(kind).section


def resolve_drivers(config: LabConfig, positions: Mapping[tuple[Any, ...], int], source: str,
                    drivers: Mapping[str, InstalledDriver] | None = None) -> LabConfig:
    """Find each instrument's driver and validate its section; every problem is one located line."""
    drivers = registry.installed() if drivers is None else drivers
    problems: list[str] = []
    for kind in registry.KINDS:
        raw = dict(getattr(config, kind))
        name = raw.pop("driver", None) or registry.DEFAULTS[kind]
        line = positions.get((kind, "driver"), positions.get((kind,), 1))
        if not isinstance(name, str):
            problems.append(f"{source}:{line}: {kind}.driver must be a driver's name, got {name!r}")
            continue
        try:
            found = registry.lookup(name, kind, drivers)
        except registry.DriverLookupError as exc:
            problems.append(f"{source}:{line}: {kind}.driver: {exc}")
            continue
        assert found.driver is not None, "lookup() returns loadable drivers only"
        # One field named for the instrument, so errors read `chamber.port` at that key's line.
        wrapper = create_model(f"{kind}_section", __config__=ConfigDict(extra="forbid"),
                               **{kind: (found.driver.section, ...)})  # type: ignore[call-overload]
        try:
            checked = validate(wrapper, {kind: raw}, positions, source)
        except ConfigError as exc:
            problems.extend(exc.messages)
            continue
        config._resolved[kind] = ResolvedInstrument(kind, found, getattr(checked, kind))
    if problems:
        raise ConfigError(problems)
    return config


def load_lab_config(path: str | Path) -> tuple[LabConfig, str]:
    text = read_text(path)
    data, positions = load_yaml(text, str(path))
    return resolve_drivers(validate(LabConfig, data, positions, str(path)), positions, str(path)), text


def lab_config_from_dict(data: dict[str, Any], source: str = "lab configuration") -> LabConfig:
    return resolve_drivers(validate(LabConfig, data, {}, source), {}, source)


def _where(section: BaseModel) -> str:
    """An instrument's address from its section's usual keys (any driver's: host/port, serial_port, port)."""
    d = section.model_dump()
    if d.get("transport") == "rtu" and d.get("serial_port"):
        return f"Modbus RTU {d['serial_port']}"
    if d.get("host") is not None and d.get("port") is not None:
        return f"{'Modbus TCP ' if 'transport' in d else ''}{d['host']}:{d['port']}"
    return str(d.get("port") or d.get("serial_port") or d.get("url") or "?")


def describe_lab_config(config: LabConfig) -> list[str]:
    """`labrunner check --lab`: which driver each instrument uses and where, then every installed driver."""
    lines = []
    for kind in registry.KINDS:
        inst = config.instrument(kind)
        d = inst.section.model_dump()
        extra = ""
        for key in ("profile", "language"):  # the map or command language a generic driver was given
            if key in d:
                extra += f", {key} {d[key] if isinstance(d[key], str) else 'custom'}"
        lines.append(f"{kind:8s} driver {inst.driver.name} ({inst.driver.distribution}{extra}) at "
                     f"{_where(inst.section)}")
    lines.append("installed drivers:")
    lines += [f"  {line}" for line in registry.describe_installed()]
    return lines


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
                  ) -> tuple[Chamber, RateTable, Imu]:
    """Each instrument's driver from the registry, built on `clock` (waits and backoffs go through it).

    A factory that fails on its section, or returns what does not satisfy the instrument's
    protocol, is a ConfigError naming the instrument and the driver."""
    built: dict[str, Any] = {}
    for kind in registry.KINDS:
        inst = config.instrument(kind)
        options = registry.DriverOptions(name=ROLE_NAMES[kind], max_rate_dps=max_rate_dps, on_retry=on_retry,
                                         on_event=on_event)
        try:
            built[kind] = registry.build(inst.driver, inst.section, clock, options)
        except registry.DriverContractError as exc:
            raise ConfigError([f"lab configuration '{config.name}', {kind}: {exc}"]) from None
        except (ValueError, TypeError) as exc:
            raise ConfigError([f"lab configuration '{config.name}', {kind}: driver {inst.driver.name!r} "
                               f"refused its section: {exc}"]) from None
    chamber, table, imu = built["chamber"], built["table"], built["imu"]
    log.info("lab %r: chamber %s (%s), rate table %s (%s), IMU %s (%s) at %g Hz", config.name, chamber.address,
             config.instrument("chamber").driver.name, table.address, config.instrument("table").driver.name,
             imu.address, config.instrument("imu").driver.name, imu.rate_hz)
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
                  link: str = "memory", on_retry: Callable[[int, Exception], None] | None = None,
                  on_event: Callable[[str, str], None] | None = None, remount_s: float = 300.0) -> Lab:
    """A dry-run lab: sims on a virtual clock, reached through the real drivers; its operator takes
    `remount_s` (the procedure's) for each remount. The table and the IMU are on serial lines inside the
    process by default (`link="memory"`: the same bytes, no socket or thread in between; "tcp" or "pty"
    for real ones)."""
    from labrunner.sims.lab import SimLab
    from labrunner.sims.world import SimLabConfig

    cfg = sim_config or SimLabConfig()
    if orientation is not None:
        cfg = dataclasses.replace(cfg, orientation=orientation)
    clock = VirtualClock(start=start_t)
    sim = SimLab(cfg, clock, link=link, imu_on_demand=True)
    config = lab_config_from_dict(sim.lab_config(), "simulated lab")
    chamber, table, imu = build_drivers(config, clock, max_rate_dps=max_rate_dps, on_retry=on_retry,
                                        on_event=on_event)

    def barrier() -> None:
        # Dry runs are deterministic: after each advance, wait until the driver has read every byte
        # the simulated IMU sent (corrupt frames too), however slow the machine is.
        sim.settle_imu(imu)

    clock.add_barrier(barrier)
    return Lab(chamber=chamber, table=table, imu=imu, operator=SimOperator(sim, clock, remount_s), clock=clock,
               config=config, sim=sim)


__all__ = [
    "ConsoleOperator", "Lab", "LabConfig", "Operator", "ResolvedInstrument", "SimOperator", "build_drivers",
    "describe_lab_config", "lab_config_from_dict", "load_lab_config", "real_lab", "resolve_drivers", "simulated_lab",
]
