"""ACME's rate table for labrunner: the labrunner ASCII language behind ACME's own class, which counts
what it sends (the test reads the count from its identity's `extra`), plus two entries that are wrong on
purpose: a factory whose object is not a RateTable, and an entry point whose module does not exist."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from labrunner.clock import Clock
from labrunner.drivers.builtin import SerialFields
from labrunner.drivers.protocols import Identity, TableStatus
from labrunner.drivers.rate_table import SerialRateTable
from labrunner.drivers.registry import Driver, DriverOptions


class AcmeSection(SerialFields):
    """The built-in serial keys plus ACME's own one."""

    asset_tag: str = Field("ACME-0", min_length=1)


class AcmeTable:
    """Satisfies drivers.protocols.RateTable by delegating to the serial driver."""

    def __init__(self, inner: SerialRateTable, asset_tag: str) -> None:
        self._inner = inner
        self.name = f"acme table {asset_tag}"
        self.address = inner.address
        self.max_rate_dps = inner.max_rate_dps
        self.asset_tag = asset_tag
        self.sent = 0

    def connect(self) -> None:
        self._inner.connect()

    def close(self) -> None:
        self._inner.close()

    def identity(self) -> Identity:
        self.sent += 1
        ident = self._inner.identity()
        return Identity("ACME", ident.model, self.asset_tag, {"driver": "acme_table", "sent": str(self.sent)})

    def jog(self, rate_dps: float) -> None:
        self.sent += 1
        self._inner.jog(rate_dps)

    def stop(self) -> None:
        self.sent += 1
        self._inner.stop()

    def velocity(self) -> float:
        self.sent += 1
        return self._inner.velocity()

    def status(self) -> TableStatus:
        self.sent += 1
        return self._inner.status()


def make_acme(section: AcmeSection, clock: Clock, options: DriverOptions) -> AcmeTable:
    inner = SerialRateTable(section.port, max_rate_dps=options.max_rate_dps, baudrate=section.baudrate,
                            name=options.name, timeout_s=section.timeout_s, retries=section.retries,
                            backoff_s=section.backoff_s, sleep=clock.sleep, on_retry=options.on_retry)
    return AcmeTable(inner, section.asset_tag)


class NotATable:
    name = "not a table"
    address = "nowhere"

    def connect(self) -> None: ...


def make_broken(section: Any, clock: Clock, options: DriverOptions) -> NotATable:
    return NotATable()


ACME_TABLE = Driver("table", make_acme, AcmeSection, "ACME rate table (labrunner language, asset-tagged)")
ACME_BROKEN = Driver("table", make_broken, SerialFields, "returns what is not a RateTable")
