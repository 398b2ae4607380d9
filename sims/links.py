"""Serial links for the simulated instruments: a TCP 'terminal server' port or a pseudo-terminal.

The driver opens `port.url` with `serial.serial_for_url`: `socket://127.0.0.1:N` for a
TCP port (as with a serial-to-Ethernet converter in a real lab), or the slave device
path of a pty pair. The simulated instrument writes and reads the other end.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import socket
import threading
import tty
from typing import Protocol

log = logging.getLogger(__name__)


class SimPort(Protocol):
    url: str
    bytes_written: int

    def write(self, data: bytes) -> int: ...
    def read(self, timeout: float) -> bytes: ...
    def close(self) -> None: ...


class TcpSerialPort:
    """One serial line served on a TCP port; a new client replaces the previous one."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, send_timeout_s: float = 2.0) -> None:
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((host, port))
        self._listener.listen(4)
        self.host = host
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://{host}:{self.port}"
        self.send_timeout_s = send_timeout_s
        self.bytes_written = 0
        self.dropped_bytes = 0
        self.refusing = False  # fault: connections are accepted and closed at once
        self._client: socket.socket | None = None
        self._lock = threading.Lock()
        self._connected = threading.Condition(self._lock)
        self._closed = False
        self._accept_thread = threading.Thread(target=self._accept_loop, name=f"sim-port-{self.port}", daemon=True)
        self._accept_thread.start()

    def _accept_loop(self) -> None:
        while not self._closed:
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return
            if self.refusing:
                conn.close()
                log.debug("sim port %s: connection refused (link down)", self.url)
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(self.send_timeout_s)
            with self._lock:
                old, self._client = self._client, conn
                self._connected.notify_all()
            log.debug("sim port %s: client connected%s", self.url, " (replacing the previous one)" if old else "")
            if old is not None:
                old.close()

    @property
    def connected(self) -> bool:
        return self._client is not None

    def wait_connected(self, timeout: float) -> bool:
        with self._connected:
            return self._connected.wait_for(lambda: self._client is not None, timeout)

    def write(self, data: bytes) -> int:
        """Send to the connected client; with nobody listening the bytes are lost, as on a real line."""
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
        """Fault: the line drops (the driver sees its connection close)."""
        client = self._client
        if client is not None:
            log.debug("sim port %s: client disconnected", self.url)
            try:
                client.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            self._drop(client)

    def close(self) -> None:
        self._closed = True
        self.disconnect()
        try:
            self._listener.close()
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
