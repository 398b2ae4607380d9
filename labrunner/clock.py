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


# --- I/O timeouts: real seconds on a real line, virtual time on a simulated one ------------------------

#: A dry run's wall-clock safety net: far beyond any load, it only catches a simulated instrument that hangs.
SAFETY_NET_S = 30.0
# How often a wait on a simulated link looks whether the simulator withheld the answer (real seconds).
_POLL_S = 0.02


class Deadline(Protocol):
    """One wait for an answer on a link (see `IoTimeouts.deadline`)."""

    def next_wait(self) -> float:
        """Real seconds to block in the next read; 0 when the wait is over."""
        ...

    def why(self) -> str:
        """Why the wait ended without an answer, for the error message."""
        ...


class _RealDeadline:
    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self._end = time.monotonic() + seconds

    def next_wait(self) -> float:
        return max(0.0, self._end - time.monotonic())

    def why(self) -> str:
        return f"within {self.seconds:g} s"


class _VirtualDeadline:
    def __init__(self, owner: IoTimeouts, link: str, seconds: float) -> None:
        self._owner = owner
        self._link = link
        self.seconds = seconds
        self._token = owner.withheld_count(link)
        self._end = time.monotonic() + SAFETY_NET_S

    def withheld(self) -> bool:
        return self._owner.withheld_count(self._link) != self._token

    def next_wait(self) -> float:
        if self.withheld():
            return 0.0
        return max(0.0, min(_POLL_S, self._end - time.monotonic()))

    def why(self) -> str:
        if self.withheld():
            return f"within {self.seconds:g} s"  # the simulated instrument kept silent: a real timeout
        return (f"within {SAFETY_NET_S:g} s of wall time on a dry run's virtual clock: the simulated instrument "
                "hangs")


class IoTimeouts:
    """Whether an I/O wait on a link may time out, decided in one place.

    On a real line a timeout is the configured seconds. A link served by a simulator on a virtual
    clock (registered by the simulated lab) is answered in virtual time, however slow the machine
    is: a wait there ends when the answer comes, when the simulator says it withheld it (an
    injected silence: `withhold`), or after `SAFETY_NET_S` of wall time, reported as a hang.
    Drivers ask `deadline(link, seconds)` for each wait and `wall_timeout(link, seconds)` for a
    library's own socket timeout.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._virtual: dict[str, int] = {}  # link -> simulators serving it (a new sim may reuse a pty name)
        self._withheld: dict[str, int] = {}

    def serve_virtually(self, link: str) -> None:
        with self._lock:
            self._virtual[link] = self._virtual.get(link, 0) + 1

    def release(self, link: str) -> None:
        with self._lock:
            left = self._virtual.get(link, 0) - 1
            if left > 0:
                self._virtual[link] = left
            else:
                self._virtual.pop(link, None)
                self._withheld.pop(link, None)

    def is_virtual(self, link: str) -> bool:
        return link in self._virtual

    def withhold(self, link: str) -> None:
        """The simulator will not answer the request now pending on `link` (an injected silence)."""
        with self._lock:
            if link in self._virtual:  # on a real-time link the client's own timeout says it
                self._withheld[link] = self._withheld.get(link, 0) + 1

    def withheld_count(self, link: str) -> int:
        return self._withheld.get(link, 0)

    def deadline(self, link: str, seconds: float) -> Deadline:
        if self.is_virtual(link):
            return _VirtualDeadline(self, link, seconds)
        return _RealDeadline(seconds)

    def wall_timeout(self, link: str, seconds: float) -> float:
        """A socket timeout for a library that waits itself (pymodbus): the safety net on a simulated link."""
        return SAFETY_NET_S if self.is_virtual(link) else seconds


#: The process's one policy: drivers and simulators agree on a link by its address (URL, host:port).
io_timeouts = IoTimeouts()
