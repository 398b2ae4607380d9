"""Instrument errors: each names the instrument, its address, and the register or command."""

from __future__ import annotations


class InstrumentError(RuntimeError):
    """An instrument did not do what was asked."""

    def __init__(self, instrument: str, address: str, message: str, *, register: int | None = None,
                 command: str | None = None) -> None:
        self.instrument = instrument
        self.address = address
        self.register = register
        self.command = command
        self.detail = message
        where = f"{instrument} at {address}"
        if register is not None:
            where += f", register {register}"
        if command is not None:
            where += f", command {command!r}"
        super().__init__(f"{where}: {message}")


class InstrumentTimeout(InstrumentError):
    """No answer within the timeout (after the bounded retries)."""


class InstrumentProtocolError(InstrumentError):
    """An answer that does not parse: garbage, wrong length, wrong echo."""


class InstrumentRefused(InstrumentError):
    """The instrument answered with an error (Modbus exception, ERR reply, fault status)."""


class LimitError(InstrumentError):
    """Refused by the driver before anything was sent: outside the configured limits."""
