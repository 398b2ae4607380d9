"""Interlocks, in the manner of bluesky's suspenders: each watches one signal against a limit.

An interlock has a signal (what it watches: the chamber temperature, the table rate, the IMU
temperature), a limit, a reason text naming the reading and the limit, and a rule for when it
clears (back inside the limit by a margin: hysteresis, so a reading hovering at the limit does
not trip and clear on every poll). The sequencer asks an `Interlocks` set at each reading and,
on a trip, brings the lab to its safe stop with the reason.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

from labrunner.procedure import Safety

log = logging.getLogger(__name__)

Signal = Literal["chamber_c", "rate_dps", "imu_temp_c"]


@dataclass(frozen=True)
class Readings:
    """What was just read; a signal not read this time is None."""

    chamber_c: float | None = None
    rate_dps: float | None = None
    imu_temp_c: float | None = None

    def get(self, signal: Signal) -> float | None:
        value: float | None = getattr(self, signal)
        return value


@dataclass(frozen=True)
class Trip:
    interlock: str
    signal: Signal
    value: float
    reason: str


@dataclass(frozen=True)
class Interlock(ABC):
    name: str
    signal: Signal
    reason: str  # str.format template: {value} and the interlock's own fields (e.g. {limit})

    @abstractmethod
    def trips(self, value: float) -> bool:
        """The reading is outside the limit."""

    @abstractmethod
    def clears(self, value: float) -> bool:
        """After a trip: the reading is back far enough inside the limit."""

    def describe(self, value: float) -> str:
        return self.reason.format(value=value, **{k: v for k, v in vars(self).items() if k != "reason"})


@dataclass(frozen=True)
class OutsideBand(Interlock):
    """Trips below `low` or above `high`. A reading that is not a number trips too: a chamber whose
    temperature is unknown is not known to be safe."""

    low: float = -math.inf
    high: float = math.inf
    clear_margin: float = 0.0

    def trips(self, value: float) -> bool:
        return not self.low <= value <= self.high

    def clears(self, value: float) -> bool:
        return self.low + self.clear_margin <= value <= self.high - self.clear_margin


@dataclass(frozen=True)
class Above(Interlock):
    """Trips above `limit` x `allowance` (of |value| with `magnitude`). A non-finite reading is no
    reading (an IMU without a sample yet) and neither trips nor clears."""

    limit: float = math.inf
    allowance: float = 1.0  # the table may exceed its commanded limit by its rate accuracy
    magnitude: bool = False
    clear_margin: float = 0.0

    def _v(self, value: float) -> float:
        return abs(value) if self.magnitude else value

    def trips(self, value: float) -> bool:
        return math.isfinite(value) and self._v(value) > self.limit * self.allowance

    def clears(self, value: float) -> bool:
        return math.isfinite(value) and self._v(value) <= self.limit - self.clear_margin


class Interlocks:
    """A set of interlocks, asked in order; the first that trips gives the reason.

    A tripped interlock stays tripped, and is reported again, until its clear rule holds on a
    later reading of its signal.
    """

    def __init__(self, interlocks: Iterable[Interlock]) -> None:
        self.interlocks = list(interlocks)
        self._tripped: dict[str, Trip] = {}

    @classmethod
    def from_safety(cls, s: Safety, *, clear_margin_c: float = 1.0) -> Interlocks:
        """The procedure's `safety` section: chamber band, table rate, IMU rating."""
        return cls([
            OutsideBand("chamber", "chamber_c",
                        "chamber at {value:.1f} C, outside the safety limits {low}..{high} C",
                        low=s.chamber_min_c, high=s.chamber_max_c, clear_margin=clear_margin_c),
            Above("table rate", "rate_dps", "table at {value:.2f} deg/s, above the limit {limit} deg/s",
                  limit=s.max_rate_dps, allowance=1.01, magnitude=True),
            Above("IMU temperature", "imu_temp_c", "IMU at {value:.1f} C, above its rating {limit} C",
                  limit=s.imu_max_temp_c, clear_margin=clear_margin_c),
        ])

    @property
    def tripped(self) -> list[Trip]:
        return list(self._tripped.values())

    def check(self, readings: Readings) -> Trip | None:
        """Judge the readings; returns the first interlock (in order) that is tripped, if any."""
        for lock in self.interlocks:
            value = readings.get(lock.signal)
            if value is None:
                continue
            if lock.name in self._tripped:
                if lock.clears(value):
                    log.info("interlock %s cleared at %r", lock.name, value)
                    del self._tripped[lock.name]
            elif lock.trips(value):
                trip = Trip(lock.name, lock.signal, value, lock.describe(value))
                log.warning("interlock %s tripped: %s", lock.name, trip.reason)
                self._tripped[lock.name] = trip
        for lock in self.interlocks:
            if lock.name in self._tripped:
                return self._tripped[lock.name]
        return None
