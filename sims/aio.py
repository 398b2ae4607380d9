"""An asyncio event loop in a daemon thread, for the pymodbus servers of the sims."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Coroutine
from typing import Any, TypeVar

from labrunner.clock import SAFETY_NET_S

T = TypeVar("T")


class LoopThread:
    def __init__(self, name: str = "sim-asyncio") -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_forever()

    def run(self, coro: Coroutine[Any, Any, T], timeout: float = SAFETY_NET_S) -> T:
        """Run a coroutine on the loop and wait for its result (a wall-clock safety net, far beyond any load)."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def stop(self) -> None:
        if self.loop.is_running():
            self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout=5)
