"""Opening a serial line: a device path, a pty, or a pyserial URL such as socket://host:port."""

from __future__ import annotations

import serial

from labrunner.clock import Deadline, io_timeouts

from .errors import InstrumentTimeout


def open_serial(url: str, *, baudrate: int, timeout_s: float, instrument: str) -> serial.SerialBase:
    """Open `url` raw 8N1; failure names the instrument and the port.

    The write timeout is the policy's (`io_timeouts`): pyserial's socket:// write checks its clock
    after sending, so a slow machine alone would fail a write to a simulator on a short timeout.
    """
    wait_s = io_timeouts.wall_timeout(url, timeout_s) if timeout_s > 0 else timeout_s
    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=wait_s, write_timeout=wait_s,
                                     bytesize=8, parity="N", stopbits=1)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise InstrumentTimeout(instrument, url, f"cannot open serial line: {exc}") from None


def close_quietly(ser: serial.SerialBase | None) -> None:
    """Close a port that may already be broken; nothing it raises matters any more."""
    if ser is not None:
        try:
            ser.close()
        except Exception:
            pass


def read_reply(ser: serial.SerialBase, terminator: bytes, deadline: Deadline) -> bytes:
    """Read until `terminator` or until the deadline says the wait is over; what arrived (maybe partial).

    The deadline (`labrunner.clock.io_timeouts`) is one timeout on a real line, and short polls on a
    simulated one, so a dry run's answer is waited for however slow the machine is.
    """
    raw = b""
    while not raw.endswith(terminator):
        wait = deadline.next_wait()
        if wait <= 0:
            break
        if ser.timeout != wait:
            ser.timeout = wait
        # A terminator split across two reads: look for the rest of it.
        k = next((k for k in range(len(terminator) - 1, 0, -1) if raw.endswith(terminator[:k])), 0)
        raw += ser.read_until(terminator[k:])
    return raw
