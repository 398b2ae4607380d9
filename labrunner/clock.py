"""Clocks: everything in labrunner that waits goes through one.

`WallClock` is real time. `ScaledClock` runs N times faster than real time (for
`labrunner sim serve --speed N` and a lab rehearsed against it). `VirtualClock` is
for dry runs: `sleep` advances simulated time at once, then calls the listeners
(simulated instruments producing what they would have produced meanwhile) and the
barriers (waits until consumers have taken it), so a dry run is deterministic.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

Listener = Callable[[float], None]


@runtime_checkable
class Clock(Protocol):
    """Time source for the sequencer, drivers and simulated instruments."""

    #: True when time only moves because somebody sleeps (a dry run).
    virtual: bool

    def now(self) -> float:
        """Seconds on this clock's time base."""
        ...

    def sleep(self, seconds: float) -> None:
        """Wait `seconds` of this clock's time."""
        ...

    def wall_seconds(self, seconds: float) -> float:
        """How many real seconds `seconds` of clock time take (for I/O timeouts)."""
        ...


class WallClock:
    """Real time, as Unix seconds."""

    virtual = False

    def now(self) -> float:
        return time.time()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def wall_seconds(self, seconds: float) -> float:
        return seconds


class ScaledClock:
    """Real time running `speed` times faster, starting at `start`."""

    virtual = False

    def __init__(self, speed: float = 1.0, start: float | None = None) -> None:
        if speed <= 0:
            raise ValueError(f"clock speed must be > 0, got {speed}")
        self.speed = float(speed)
        self._start = time.time() if start is None else float(start)
        self._mono0 = time.monotonic()

    def now(self) -> float:
        return self._start + (time.monotonic() - self._mono0) * self.speed

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds / self.speed)

    def wall_seconds(self, seconds: float) -> float:
        return seconds / self.speed


class VirtualClock:
    """Simulated time that moves only when somebody sleeps.

    Listeners are called with the new time after every advance, in the sleeping
    thread; barriers are then called and must return once whatever the listeners
    produced has been consumed (or give up after their own timeout).
    """

    virtual = True

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)
        self._lock = threading.RLock()
        self._listeners: list[Listener] = []
        self._barriers: list[Callable[[], None]] = []

    def now(self) -> float:
        return self._t

    def add_listener(self, fn: Listener) -> None:
        with self._lock:
            self._listeners.append(fn)

    def remove_listener(self, fn: Listener) -> None:
        with self._lock:
            if fn in self._listeners:
                self._listeners.remove(fn)

    def add_barrier(self, fn: Callable[[], None]) -> None:
        with self._lock:
            self._barriers.append(fn)

    def remove_barrier(self, fn: Callable[[], None]) -> None:
        with self._lock:
            if fn in self._barriers:
                self._barriers.remove(fn)

    def advance_to(self, t: float) -> None:
        with self._lock:
            if t > self._t:
                self._t = float(t)
            now = self._t
            listeners = list(self._listeners)
            barriers = list(self._barriers)
        for fn in listeners:
            fn(now)
        for barrier in barriers:
            barrier()

    def sleep(self, seconds: float) -> None:
        if seconds < 0:
            seconds = 0.0
        self.advance_to(self._t + seconds)

    def wall_seconds(self, seconds: float) -> float:
        # Virtual time costs no real time; I/O still needs a real timeout.
        return 0.0
