"""Preflight checks: the instruments answer and can do what the procedure asks, before anything moves."""

from __future__ import annotations

import logging

from labrunner.drivers.errors import LimitError
from labrunner.drivers.protocols import Chamber, RateTable

log = logging.getLogger(__name__)


def check_chamber(chamber: Chamber, temperatures: list[float]) -> tuple[dict[str, object], str]:
    """The chamber answers and its controller accepts every temperature; returns (identity, message)."""
    ident = chamber.identity()
    lo, hi = chamber.setpoint_range()
    outside = [t for t in temperatures if not lo <= t <= hi]
    if outside:
        raise LimitError(chamber.name, chamber.address, f"procedure temperature {outside[0]} C is outside "
                         f"the controller's setpoint range {lo}..{hi} C")
    return ident.__dict__, f"chamber {ident.vendor} {ident.model} answers; setpoint range {lo}..{hi} C"


def check_table(table: RateTable, rates: list[float]) -> tuple[dict[str, object], str] | None:
    """The table answers and (if its driver reads its limits) can turn at every rate; returns
    (identity, message), or None for a table that does not report its limits."""
    ident = table.identity()
    limits = getattr(table, "limits", None)
    if limits is None:
        return None
    max_rate, accel = limits()
    fastest = max(abs(r) for r in rates)
    if fastest > max_rate:
        raise LimitError(table.name, table.address, f"procedure rate {fastest} deg/s exceeds the "
                         f"table's maximum {max_rate} deg/s")
    return ident.__dict__, f"rate table {ident.vendor} {ident.model} answers; max {max_rate} deg/s, {accel} deg/s^2"
