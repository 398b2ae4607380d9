"""Serial links for the simulated instruments: a TCP 'terminal server' port or a pseudo-terminal.

The driver opens `port.url` with `serial.serial_for_url`: `socket://127.0.0.1:N` for a
TCP port (as with a serial-to-Ethernet converter in a real lab), or the slave device
path of a pty pair. The simulated instrument writes and reads the other end. A dry run on a
virtual clock uses a `MemoryPort` (`labsim://NAME-N`): the same bytes, inside the process, with
the server answering in the driver's thread.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import socket
import threading
import time
import tty
from collections.abc import Callable
from typing import Any, Protocol

import serial

log = logging.getLogger(__name__)

# `labsim://` URLs open a MemoryPort's driver end (sims/protocol_labsim.py, found by pyserial by its name).
if __package__ and __package__ not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append(__package__)


class SimPort(Protocol):
    url: str
    bytes_written: int

    def write(self, data: bytes) -> int: ...
    def read(self, timeout: float) -> bytes: ...
    def close(self) -> None: ...


class _ClientSlot:
    """A served line's one client and its refuse fault (`refuse(on)` is each line's own)."""

    _client: Any
    _refusing: bool

    @property
    def connected(self) -> bool:
        return self._client is not None

    @property
    def refusing(self) -> bool:
        return self._refusing

    @refusing.setter
    def refusing(self, on: bool) -> None:
        self.refuse(on)

    def refuse(self, on: bool) -> None:
        raise NotImplementedError


class TcpSerialPort(_ClientSlot):
    """One serial line served on a TCP port; a new client replaces the previous one.

    A connection the kernel has completed is taken before each write and read, not only by the
    accept thread, so bytes sent just after a driver connected reach it however the threads are
    scheduled. Refusing connections (a link-drop fault) closes the listener: a driver's connect is
    refused, as by a terminal server that is down. With `await_close` (a stream a dry run's driver
    reads all the time) a drop waits until the driver has closed its end.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, send_timeout_s: float = 2.0,
                 await_close: bool = False) -> None:
        self.host = host
        self._lock = threading.Lock()
        self._connected = threading.Condition(self._lock)
        self._listener: socket.socket | None = self._listen(port)
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://{host}:{self.port}"
        self.send_timeout_s = send_timeout_s
        self.await_close = await_close
        self.bytes_written = 0
        self.dropped_bytes = 0
        self._refusing = False
        self._client: socket.socket | None = None
        self._closed = False
        self._accept_thread = threading.Thread(target=self._accept_loop, name=f"sim-port-{self.port}", daemon=True)
        self._accept_thread.start()

    def _listen(self, port: int) -> socket.socket:
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((self.host, port))
        listener.listen(4)
        listener.setblocking(False)  # two threads may try to accept: neither blocks
        return listener

    def _accept_loop(self) -> None:
        while not self._closed:
            listener = self._listener
            if listener is None:
                time.sleep(0.02)
                continue
            try:
                ready, _, _ = select.select([listener], [], [], 0.05)
            except (OSError, ValueError):
                continue  # closed by refuse(): the next round sees it
            if ready:
                self._accept_pending()

    def _accept_pending(self) -> None:
        """Take every connection the kernel has completed (the newest replaces the client)."""
        while True:
            listener = self._listener
            if listener is None:
                return
            try:
                conn, _ = listener.accept()
            except (BlockingIOError, OSError):
                return
            conn.setblocking(True)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(self.send_timeout_s)
            with self._lock:
                old, self._client = self._client, conn
                self._connected.notify_all()
            log.debug("sim port %s: client connected%s", self.url, " (replacing the previous one)" if old else "")
            if old is not None:
                old.close()

    def refuse(self, on: bool) -> None:
        """Fault: stop listening (connects are refused) and drop the client; or listen again on the same port."""
        if on == self._refusing:
            return
        self._refusing = on
        if on:
            listener, self._listener = self._listener, None
            if listener is not None:
                _close_listener(listener)
            self.disconnect()
        elif not self._closed:
            self._listener = self._listen(self.port)
        log.debug("sim port %s: %s connections", self.url, "refusing" if on else "accepting")

    def wait_connected(self, timeout: float) -> bool:
        self._accept_pending()
        with self._connected:
            return self._connected.wait_for(lambda: self._client is not None, timeout)

    def write(self, data: bytes) -> int:
        """Send to the connected client; with nobody listening the bytes are lost, as on a real line."""
        if self._client is None:
            self._accept_pending()
        client = self._client
        if client is None:
            self.dropped_bytes += len(data)
            return 0
        try:
            client.sendall(data)
        except OSError:
            self._drop(client)
            self.dropped_bytes += len(data)
            return 0
        self.bytes_written += len(data)
        return len(data)

    def read(self, timeout: float) -> bytes:
        if self._client is None:
            self._accept_pending()
        client = self._client
        if client is None:
            with self._connected:
                self._connected.wait(timeout)
            return b""
        try:
            ready, _, _ = select.select([client], [], [], timeout)
            if not ready:
                return b""
            data = client.recv(65536)
        except (OSError, ValueError):
            self._drop(client)
            return b""
        if not data:
            self._drop(client)
        return data

    def _drop(self, client: socket.socket) -> None:
        with self._lock:
            if self._client is client:
                self._client = None
        try:
            client.close()
        except OSError:
            pass

    def disconnect(self) -> None:
        """Fault: the line drops (the driver sees its connection close).

        With `await_close` (a stream a dry run's driver reads all the time) the drop returns once
        the driver has closed its end, so it notices the loss at this moment of virtual time.
        """
        client = self._client
        if client is not None:
            log.debug("sim port %s: client disconnected", self.url)
            if self.await_close:
                self._until_closed_by_peer(client)
            try:
                client.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._drop(client)

    def _until_closed_by_peer(self, client: socket.socket) -> None:
        try:
            client.shutdown(socket.SHUT_WR)  # the driver reads what was sent, then the end of the stream
        except OSError:
            return
        end = time.monotonic() + self.send_timeout_s
        while time.monotonic() < end:
            try:
                ready, _, _ = select.select([client], [], [], 0.05)
                if ready and not client.recv(65536):
                    return
            except (OSError, ValueError):
                return
        log.warning("sim port %s: the client did not close its end within %g s", self.url, self.send_timeout_s)

    def close(self) -> None:
        self._closed = True
        self.await_close = False  # closing the lab: nobody waits for the driver any more
        self.disconnect()
        listener, self._listener = self._listener, None
        if listener is not None:
            _close_listener(listener)


def _close_listener(listener: socket.socket) -> None:
    """Stop listening now: the accept thread's select holds the socket open, and with it the port,
    until it returns; shutting it down first refuses connects at once and frees the port."""
    try:
        listener.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        listener.close()
    except OSError:
        pass


class PtyPort:
    """A pseudo-terminal pair: the driver opens the slave path; the sim uses the master."""

    def __init__(self, write_timeout_s: float = 2.0) -> None:
        self._master, self._slave = os.openpty()
        # Raw at once: otherwise the line discipline echoes and rewrites bytes before the driver opens it.
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.url = os.ttyname(self._slave)
        self.write_timeout_s = write_timeout_s
        self.bytes_written = 0
        self.dropped_bytes = 0

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        sent = 0
        while sent < len(view):
            try:
                sent += os.write(self._master, view[sent:])
            except BlockingIOError:
                _, ready, _ = select.select([], [self._master], [], self.write_timeout_s)
                if not ready:  # nobody reads: the rest is lost, as a UART overrun would lose it
                    break
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EBADF):
                    break
                raise
        self.bytes_written += sent
        self.dropped_bytes += len(view) - sent
        return sent

    def read(self, timeout: float) -> bytes:
        try:
            ready, _, _ = select.select([self._master], [], [], timeout)
            if not ready:
                return b""
            return os.read(self._master, 65536)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


class MemoryPort(_ClientSlot):
    """One serial line inside the process, for a dry run on a virtual clock (`labsim://NAME-N`).

    The driver opens `url` with `serial.serial_for_url` as it opens any line (pyserial finds
    `sims.protocol_labsim` by the scheme) and gets a `serial.SerialBase` whose bytes are this
    port's: what the simulated instrument writes waits in the driver's receive buffer, and what
    the driver writes is handed to the attached server (`attach_server`) in the driver's own
    thread, which answers through `write` before the driver's `write` returns. The bytes are the
    protocol's, parsed and formatted by the real server and driver code; what is saved is the
    sockets' and threads' hand-offs (a reply is in the buffer when the request has been written,
    a frame when the clock's listener has sent it). Faults as `TcpSerialPort`'s: `refuse` breaks
    the open end (the driver reads what was sent before, then the line is lost) and refuses opens.
    """

    _ports: dict[str, MemoryPort] = {}
    _count = 0
    _registry_lock = threading.Lock()

    def __init__(self, name: str) -> None:
        with MemoryPort._registry_lock:
            MemoryPort._count += 1
            self.url = f"labsim://{name}-{MemoryPort._count}"
            MemoryPort._ports[self.url] = self
        self.bytes_written = 0
        self.dropped_bytes = 0
        self._refusing = False
        self._client: MemoryEnd | None = None
        self._server: Callable[[bytes], None] | None = None
        # Called before the driver's end is read (an IMU that makes its frames on demand sends them then).
        self.on_read: Callable[[], None] | None = None

    @classmethod
    def lookup(cls, url: str) -> MemoryPort | None:
        return cls._ports.get(url.lower())

    def attach_server(self, serve: Callable[[bytes], None]) -> None:
        """`serve(data)` gets what the driver writes, in the driver's thread."""
        self._server = serve

    def open_end(self) -> MemoryEnd:
        """The driver's end of the line (a new one replaces the previous one, as a new TCP client does)."""
        if self._refusing:
            raise ConnectionRefusedError(f"{self.url}: connection refused")
        old, self._client = self._client, MemoryEnd(self)
        if old is not None:
            old.lose("replaced by a new connection")
        log.debug("sim port %s: client connected%s", self.url, " (replacing the previous one)" if old else "")
        return self._client

    def from_driver(self, end: MemoryEnd, data: bytes) -> None:
        if end is self._client and self._server is not None:
            self._server(data)

    def end_closed(self, end: MemoryEnd) -> None:
        if self._client is end:
            self._client = None

    def refuse(self, on: bool) -> None:
        """Fault: drop the client and refuse opens; or accept them again."""
        if on == self._refusing:
            return
        self._refusing = on
        if on:
            self.disconnect()
        log.debug("sim port %s: %s connections", self.url, "refusing" if on else "accepting")

    def disconnect(self) -> None:
        """Fault: the line drops; the driver reads what was sent before it, then finds the line lost."""
        client, self._client = self._client, None
        if client is not None:
            log.debug("sim port %s: client disconnected", self.url)
            client.lose("connection lost")

    def write(self, data: bytes) -> int:
        """Put bytes on the line for the driver; with nobody connected they are lost, as on a real line."""
        client = self._client
        if client is None:
            self.dropped_bytes += len(data)
            return 0
        client.receive(data)
        self.bytes_written += len(data)
        return len(data)

    def read(self, timeout: float) -> bytes:
        """Nothing to read here: the driver's bytes go to the attached server as they are written."""
        return b""

    def close(self) -> None:
        self.disconnect()
        self._server = None
        with MemoryPort._registry_lock:
            if MemoryPort._ports.get(self.url) is self:
                del MemoryPort._ports[self.url]


class MemoryEnd:
    """The driver's end of a `MemoryPort`: its receive buffer, and whether the line was lost."""

    def __init__(self, port: MemoryPort) -> None:
        self.port = port
        self._buf = bytearray()
        self._cond = threading.Condition()
        self.lost: str | None = None  # why the line was lost (None: up)
        # Told when the port loses the line (not when the driver closes it): with no reader thread
        # waiting on it, the driver reads the rest and finds the loss at that moment, as over TCP.
        self.on_lost: Callable[[], None] | None = None

    def receive(self, data: bytes) -> None:
        with self._cond:
            self._buf += data
            self._cond.notify_all()

    def lose(self, why: str) -> None:
        with self._cond:
            self.lost = why
            self._cond.notify_all()
        tell, self.on_lost = self.on_lost, None
        if tell is not None:
            tell()

    def send(self, data: bytes) -> None:
        if self.lost is not None:
            raise ConnectionResetError(f"{self.port.url}: {self.lost}")
        self.port.from_driver(self, data)

    def _pull(self) -> None:
        """What the port's sender has due comes now (`MemoryPort.on_read`), before the driver reads."""
        pull = self.port.on_read
        if pull is not None and self.lost is None and self.port._client is self:
            pull()

    @property
    def waiting(self) -> int:
        self._pull()
        return len(self._buf)

    def clear(self) -> None:
        with self._cond:
            self._buf.clear()

    def take(self, size: int, timeout: float | None, until: bytes | None = None) -> bytes:
        """Up to `size` bytes (through `until` when given), waiting up to `timeout` real seconds for them
        (None: until they come). A lost line gives what was sent before it, then raises ConnectionResetError."""
        self._pull()
        end = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while True:
                if until is not None:
                    cut = self._buf.find(until)
                    n = min(size, cut + len(until)) if cut >= 0 else (size if len(self._buf) >= size else 0)
                else:
                    n = min(size, len(self._buf))
                if n:
                    out = bytes(self._buf[:n])
                    del self._buf[:n]
                    return out
                if self.lost is not None:
                    if self._buf:  # the rest of a partial line, then the loss
                        out = bytes(self._buf)
                        self._buf.clear()
                        return out
                    raise ConnectionResetError(f"{self.port.url}: {self.lost}")
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:  # timed out: what came of a line, as pyserial's read_until
                    out = bytes(self._buf[:size])
                    del self._buf[:size]
                    return out
                self._cond.wait(left)

    def close(self) -> None:
        self.on_lost = None  # closed by the driver itself
        self.port.end_closed(self)
        self.lose("closed")
