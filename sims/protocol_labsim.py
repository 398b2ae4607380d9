"""pyserial's handler for `labsim://` URLs: the driver's end of a simulated line inside the process.

`serial.serial_for_url("labsim://imu-1")` finds this module by its name (`sims.links` puts this
package on `serial.protocol_handler_packages`) and opens the `sims.links.MemoryPort` registered
under that URL. The driver reads and writes it as any serial line; see `MemoryPort` for what
happens to the bytes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from serial.serialutil import LF, PortNotOpenError, SerialBase, SerialException

from .links import MemoryEnd, MemoryPort


class Serial(SerialBase):
    """A `serial.SerialBase` on a `MemoryPort` (8N1 and baud rate are accepted and mean nothing here)."""

    #: Bytes arrive only while this process writes them (a clock listener, or the server answering the
    #: driver's own write): a reader has nothing to wait for between its calls (`drivers.imu_serial`).
    caller_fed = True
    is_open: bool  # SerialBase's, set in its __init__

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._end: MemoryEnd | None = None
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        port = MemoryPort.lookup(str(self._port))
        if port is None:
            raise SerialException(f"could not open port {self._port}: no simulated line of that name")
        try:
            self._end = port.open_end()
        except ConnectionRefusedError as exc:
            raise SerialException(f"could not open port {self._port}: {exc}") from None
        self.is_open = True

    def _reconfigure_port(self, *args: Any, **kwargs: Any) -> None:
        pass  # nothing to set on a line inside the process

    def close(self) -> None:
        if self._end is not None:
            self._end.close()
            self._end = None
        self.is_open = False

    def _the_end(self) -> MemoryEnd:
        if not self.is_open or self._end is None:
            raise PortNotOpenError()
        return self._end

    @property
    def on_lost(self) -> Callable[[], None] | None:
        """Called (in the thread that dropped the line) when the simulated line is lost."""
        return self._end.on_lost if self._end is not None else None

    @on_lost.setter
    def on_lost(self, tell: Callable[[], None] | None) -> None:
        self._the_end().on_lost = tell

    @property
    def in_waiting(self) -> int:
        return self._the_end().waiting

    def read(self, size: int = 1) -> bytes:
        if size <= 0:
            return b""
        try:
            return self._the_end().take(size, self._timeout)
        except ConnectionResetError as exc:
            raise SerialException(f"read failed: {exc}") from None

    def read_until(self, expected: bytes = LF, size: int | None = None) -> bytes:
        """Through `expected` in one step (pyserial's own reads one byte at a time)."""
        try:
            return self._the_end().take(size if size is not None else 1 << 30, self._timeout, until=bytes(expected))
        except ConnectionResetError as exc:
            raise SerialException(f"read failed: {exc}") from None

    def write(self, data: bytes | bytearray | memoryview) -> int:
        end = self._the_end()
        payload = bytes(data)
        try:
            end.send(payload)
        except ConnectionResetError as exc:
            raise SerialException(f"write failed: {exc}") from None
        return len(payload)

    def reset_input_buffer(self) -> None:
        self._the_end().clear()

    def reset_output_buffer(self) -> None:
        pass  # written bytes are delivered at once

    def fileno(self) -> int:
        raise SerialException(f"{self._port}: a simulated line inside the process has no file descriptor")
