"""The faults a simulated lab can rehearse: one vocabulary for fault plans and the sims.

Fault plans (`labrunner.fault_plan`) decide when a fault strikes; the simulated lab
(`labrunner.sims.lab.SimLab`) knows how. They meet only through `FaultKind` and the
`FaultTarget` protocol, so the orchestration never reaches into the simulated world.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Protocol, runtime_checkable


class FaultKind(StrEnum):
    """Every fault kind; the order is the one random plans draw from (keep it stable for seeds)."""

    MODBUS_TIMEOUT = "modbus_timeout"  # the chamber controller stops answering for duration_s
    MODBUS_EXCEPTION = "modbus_exception"  # it answers `count` requests with exception 4 (device failure)
    MODBUS_BUSY = "modbus_busy"  # ... with exception 6 (busy): transient, retried
    MODBUS_DROP = "modbus_drop"  # every Modbus client connection is dropped (once)
    MODBUS_OUTAGE = "modbus_outage"  # connections dropped and refused for duration_s
    HEATER_FAILURE = "heater_failure"  # the heater cannot heat for duration_s
    COMPRESSOR_FAILURE = "compressor_failure"  # the compressor cannot cool for duration_s
    GARBAGE_PV = "garbage_pv"  # the process value reads a sensor-break pattern for duration_s
    TABLE_FAULT = "table_fault"  # the table reports a drive fault (and coasts to rest) for duration_s
    TABLE_SILENT = "table_silent"  # the table does not reply for duration_s
    TABLE_GARBAGE = "table_garbage"  # the table replies line noise for duration_s
    IMU_STALL = "imu_stall"  # the IMU sends nothing for duration_s
    IMU_CORRUPT = "imu_corrupt"  # the next `count` frames are corrupted on the line
    IMU_GAP = "imu_gap"  # the next `count` frames are never sent (counter gap)
    TABLE_LINK_DROP = "table_link_drop"  # the table's serial line disappears for duration_s
    IMU_LINK_DROP = "imu_link_drop"  # the IMU's serial line disappears for duration_s
    HEATER_STUCK = "heater_stuck"  # (interlock) the heater is stuck on for duration_s
    TABLE_OVERSPEED = "table_overspeed"  # (interlock) the drive holds 1.6x the commanded rate
    IMU_OVERHEAT = "imu_overheat"  # (interlock) the IMU runs 70 C hotter


# Rehearsals of the interlocks: they end a campaign in the safe state, so random plans leave them out.
INTERLOCK_KINDS: frozenset[FaultKind] = frozenset(
    {FaultKind.HEATER_STUCK, FaultKind.TABLE_OVERSPEED, FaultKind.IMU_OVERHEAT})


def fault_kind(name: str) -> FaultKind:
    """The kind called `name`; an unknown name is a ValueError listing the known ones."""
    try:
        return FaultKind(name)
    except ValueError:
        raise ValueError(f"unknown fault kind {name!r}; known: {', '.join(k.value for k in FaultKind)}") from None


@runtime_checkable
class FaultTarget(Protocol):
    """Something faults can be switched on and off in (the simulated lab)."""

    def apply_fault(self, kind: FaultKind | str, *, duration_s: float = 0.0, count: int = 0) -> None:
        """Start a fault now: lasting `duration_s` (until cleared) or affecting `count` requests or frames."""
        ...

    def clear_fault(self, kind: FaultKind | str) -> None:
        """End a fault now (a no-op for one-shot faults already over)."""
        ...


__all__ = ["INTERLOCK_KINDS", "FaultKind", "FaultTarget", "fault_kind"]
