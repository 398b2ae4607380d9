"""A fake instrument line that checks the exact bytes a driver writes (PyMeasure `expected_protocol` style).

`ExpectedLine([(request, reply), ...])` listens on loopback; a driver pointed at
`socket://127.0.0.1:<port>` (a serial table, a Modbus RTU chamber) must write each request byte
for byte, in order, and gets the reply. Anything else is recorded in `problems` and the line is
closed, so the driver fails the way it would on a real instrument that did not understand it.
"""

from __future__ import annotations

import socket
import threading


def modbus_crc(frame: bytes) -> bytes:
    """Modbus RTU CRC-16 (polynomial 0xA001, initial 0xFFFF), low byte first."""
    crc = 0xFFFF
    for byte in frame:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc & 0xFF, crc >> 8])


def rtu(hex_pdu: str) -> bytes:
    """An RTU frame from its address + PDU written in hex, with its CRC appended."""
    body = bytes.fromhex(hex_pdu)
    return body + modbus_crc(body)


class ExpectedLine:
    def __init__(self, exchanges: list[tuple[bytes, bytes]]) -> None:
        self.exchanges = list(exchanges)
        self.done = 0
        self.problems: list[str] = []
        self._sock = socket.socket()
        self._sock.bind(("127.0.0.1", 0))
        self._sock.listen(1)
        self._sock.settimeout(5.0)
        self.url = f"socket://127.0.0.1:{self._sock.getsockname()[1]}"
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        try:
            conn, _ = self._sock.accept()
        except OSError as exc:
            self.problems.append(f"no connection: {exc}")
            return
        with conn:
            conn.settimeout(5.0)
            for request, reply in self.exchanges:
                got = b""
                try:
                    while len(got) < len(request):
                        chunk = conn.recv(len(request) - len(got))
                        if not chunk:
                            break
                        got += chunk
                except OSError as exc:
                    self.problems.append(f"exchange {self.done}: reading: {exc}")
                    return
                if got != request:
                    self.problems.append(f"exchange {self.done}: expected {request!r}, got {got!r}")
                    return
                conn.sendall(reply)
                self.done += 1

    def close(self) -> None:
        self._thread.join(timeout=5)
        self._sock.close()

    def check(self) -> None:
        """All exchanges happened, byte for byte."""
        self.close()
        assert not self.problems, self.problems
        assert self.done == len(self.exchanges), f"{self.done} of {len(self.exchanges)} exchanges happened"
