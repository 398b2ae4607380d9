"""Opening a serial line: a device path, a pty, or a pyserial URL such as socket://host:port."""

from __future__ import annotations

import serial

from .errors import InstrumentTimeout


def open_serial(url: str, *, baudrate: int, timeout_s: float, instrument: str) -> serial.SerialBase:
    """Open `url` raw 8N1; failure names the instrument and the port."""
    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s, write_timeout=timeout_s,
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
