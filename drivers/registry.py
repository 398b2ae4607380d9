"""Instrument drivers by name, found through the `labrunner.drivers` entry-point group.

A lab configuration names each instrument's driver (`driver: watlow_f4`). The built-in
drivers are declared in labrunner's own pyproject.toml; a lab adds its own from a separate
package, without editing labrunner, by declaring

    [project.entry-points."labrunner.drivers"]
    my_table = "my_lab.drivers:MY_TABLE"

where `MY_TABLE` is a `Driver`: the kind of instrument it drives, a factory, and the pydantic
model of its configuration section. The factory gets the validated section, the lab's clock
(every wait goes through it) and the common `DriverOptions`, and returns an object that
satisfies the instrument's typed protocol in `drivers.protocols` (checked here: a factory
returning anything else is a clear error, not a failure deep inside a run).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib import metadata
from typing import Any, Literal

from pydantic import BaseModel

from labrunner.clock import Clock

from .errors import InstrumentError
from .protocols import Chamber, Imu, RateTable

log = logging.getLogger(__name__)

GROUP = "labrunner.drivers"
Kind = Literal["chamber", "table", "imu"]
KINDS: tuple[Kind, ...] = ("chamber", "table", "imu")
PROTOCOLS: dict[str, type] = {"chamber": Chamber, "table": RateTable, "imu": Imu}
# The driver an instrument section without a `driver:` key gets (the configurations written before
# drivers had names): the project's own Modbus chamber, ASCII rate table and IMU frame stream.
DEFAULTS: dict[str, str] = {"chamber": "modbus_chamber", "table": "labrunner_table", "imu": "labrunner_imu"}


@dataclass(frozen=True)
class DriverOptions:
    """What every driver gets besides its own section: the run's limits and where to report."""

    name: str  # the instrument's role in the lab ("chamber", "rate table", "imu"), used in its errors
    max_rate_dps: float = 1000.0  # the procedure's rate limit (a table driver refuses more before sending)
    on_retry: Callable[[int, InstrumentError], None] | None = None  # a retry, for the campaign's events
    on_event: Callable[[str, str], None] | None = None  # (kind, message): link lost / restored


Factory = Callable[[Any, Clock, DriverOptions], object]


@dataclass(frozen=True)
class Driver:
    """One entry of the `labrunner.drivers` group."""

    kind: Kind
    factory: Factory  # (validated section, clock, options) -> a Chamber / RateTable / Imu
    section: type[BaseModel]  # the configuration section's model (without the `driver` key)
    summary: str = ""


@dataclass(frozen=True)
class InstalledDriver:
    name: str
    source: str  # the entry point's value, "module:attribute"
    distribution: str  # the package that declares it
    driver: Driver | None  # None when it could not be loaded
    problem: str = ""  # why it could not be loaded

    @property
    def kind(self) -> str:
        return self.driver.kind if self.driver is not None else "?"


class DriverLookupError(LookupError):
    """An unknown or broken driver name; the message lists what is installed."""


class DriverContractError(TypeError):
    """A factory returned something that does not satisfy its instrument's protocol."""


def _load(ep: metadata.EntryPoint) -> InstalledDriver:
    dist = ep.dist.name if ep.dist is not None else "?"
    try:
        obj = ep.load()
    except Exception as exc:  # a third-party package's import error must not hide the other drivers
        # Said where it matters: `check --lab` lists it as broken, and naming it in a lab is an error.
        log.info("driver %r (%s from %s) cannot be loaded: %s", ep.name, ep.value, dist, exc)
        return InstalledDriver(ep.name, ep.value, dist, None, f"cannot be loaded: {type(exc).__name__}: {exc}")
    if not isinstance(obj, Driver):
        return InstalledDriver(ep.name, ep.value, dist, None,
                               f"{ep.value} is a {type(obj).__name__}, not a labrunner.drivers.registry.Driver")
    if obj.kind not in KINDS:
        return InstalledDriver(ep.name, ep.value, dist, None,
                               f"kind {obj.kind!r} is not one of {', '.join(KINDS)}")
    return InstalledDriver(ep.name, ep.value, dist, obj)


def installed() -> dict[str, InstalledDriver]:
    """Every driver the environment declares, by name (read each time: a package may be added at run time)."""
    found: dict[str, InstalledDriver] = {}
    for ep in sorted(metadata.entry_points(group=GROUP), key=lambda e: e.name):
        if ep.name in found:  # two packages claim one name: the first stays, the clash is said
            log.warning("driver %r declared twice (%s and %s); using %s", ep.name, found[ep.name].source, ep.value,
                        found[ep.name].source)
            continue
        found[ep.name] = _load(ep)
    return found


def describe_installed(drivers: Mapping[str, InstalledDriver] | None = None) -> list[str]:
    """One line per installed driver: name, kind, where it comes from (or why it is broken)."""
    drivers = installed() if drivers is None else drivers
    lines = []
    for d in drivers.values():
        if d.driver is None:
            lines.append(f"{d.name} (BROKEN: {d.problem}; {d.source}, from {d.distribution})")
        else:
            summary = f": {d.driver.summary}" if d.driver.summary else ""
            lines.append(f"{d.name} ({d.kind}{summary}; {d.source}, from {d.distribution})")
    return lines


def lookup(name: str, kind: str, drivers: Mapping[str, InstalledDriver] | None = None) -> InstalledDriver:
    """The driver `name` for an instrument of `kind`; unknown, broken or of another kind: DriverLookupError."""
    drivers = installed() if drivers is None else drivers
    same_kind = sorted(n for n, d in drivers.items() if d.kind == kind)
    choice = f"installed {kind} drivers: {', '.join(same_kind) or 'none'}"
    found = drivers.get(name)
    if found is None:
        raise DriverLookupError(f"unknown {kind} driver {name!r}; {choice}")
    if found.driver is None:
        raise DriverLookupError(f"{kind} driver {name!r} ({found.source}, from {found.distribution}) "
                                f"{found.problem}; {choice}")
    if found.driver.kind != kind:
        raise DriverLookupError(f"driver {name!r} drives a {found.driver.kind}, not a {kind}; {choice}")
    return found


def protocol_members(protocol: type) -> list[str]:
    """The attributes and methods a `typing.Protocol` asks for."""
    names = set(getattr(protocol, "__annotations__", {}))
    names |= {n for n, v in vars(protocol).items() if callable(v) and not n.startswith("_")}
    return sorted(names)


def check_contract(obj: object, kind: str, origin: str) -> None:
    """Raise DriverContractError naming what `obj` lacks to be the `kind`'s protocol."""
    protocol = PROTOCOLS[kind]
    missing = [m for m in protocol_members(protocol) if not hasattr(obj, m)]
    not_callable = [m for m in protocol_members(protocol)
                    if m in vars(protocol) and callable(vars(protocol)[m]) and hasattr(obj, m)
                    and not callable(getattr(obj, m))]
    if missing or not_callable:
        problems = []
        if missing:
            problems.append(f"missing {', '.join(missing)}")
        if not_callable:
            problems.append(f"not callable: {', '.join(not_callable)}")
        raise DriverContractError(f"{origin} returned a {type(obj).__name__}, which is not a {protocol.__name__} "
                                  f"(drivers.protocols): {'; '.join(problems)}")


def build(found: InstalledDriver, section: BaseModel, clock: Clock, options: DriverOptions) -> Any:
    """Call the driver's factory and check that what it returns satisfies the instrument's protocol."""
    assert found.driver is not None, "lookup() returns loadable drivers only"
    obj = found.driver.factory(section, clock, options)
    check_contract(obj, found.driver.kind, f"driver {found.name!r} ({found.source})")
    log.debug("driver %r built a %s for the %s", found.name, type(obj).__name__, options.name)
    return obj


__all__ = [
    "DEFAULTS", "GROUP", "KINDS", "Driver", "DriverContractError", "DriverLookupError", "DriverOptions", "Factory",
    "InstalledDriver", "build", "check_contract", "describe_installed", "installed", "lookup", "protocol_members",
]
