"""How each fault kind is switched on and off inside the simulated lab.

The only place that knows which simulated part a `FaultKind` touches: the chamber
server's `ChamberFaults`, the plants in the world, the table server, the IMU stream,
or a serial link. `SimLab.apply_fault` / `clear_fault` call it; nothing outside the
sims sets these attributes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from labrunner.clock import Clock
from labrunner.fault_kinds import FaultKind, fault_kind

from .chamber_server import ChamberServer
from .imu_stream import ImuStreamSim
from .links import MemoryPort, SimPort, TcpSerialPort
from .table_server import TableServer
from .world import SimWorld

log = logging.getLogger(__name__)

TABLE_FAULT_CODE = "E17 OVERCURRENT"
OVERSPEED_FACTOR = 1.6
OVERHEAT_C = 70.0
K = FaultKind


@dataclass
class SimFaults:
    """The simulated parts faults act on (wired by `SimLab`)."""

    world: SimWorld
    clock: Clock
    chamber: ChamberServer
    table: TableServer
    imu: ImuStreamSim
    table_port: SimPort
    imu_port: SimPort

    def apply(self, kind: FaultKind | str, *, duration_s: float = 0.0, count: int = 0) -> None:
        k = fault_kind(kind) if not isinstance(kind, FaultKind) else kind
        now = self.clock.now()
        log.debug("sim fault on: %s (duration %.1f s, count %d)", k.value, duration_s, count)
        if k in (K.MODBUS_TIMEOUT, K.GARBAGE_PV, K.HEATER_FAILURE, K.COMPRESSOR_FAILURE, K.HEATER_STUCK,
                 K.TABLE_SILENT, K.TABLE_GARBAGE):
            self._flag(k, True)
        elif k in (K.MODBUS_EXCEPTION, K.MODBUS_BUSY):
            self.chamber.faults.exception_code = 4 if k is K.MODBUS_EXCEPTION else 6
            self.chamber.faults.exception_count = max(1, count)
        elif k is K.MODBUS_DROP:
            self.chamber.drop_connections()
        elif k is K.MODBUS_OUTAGE:
            self.chamber.refuse_connections(True)
        elif k is K.TABLE_FAULT:
            self.table.faults.fault = TABLE_FAULT_CODE
            with self.world.lock:
                self.world.table.command(now, 0.0)  # a faulted drive coasts to rest
        elif k is K.IMU_STALL:
            self.imu.faults.stall_from, self.imu.faults.stall_until = now, now + duration_s
        elif k is K.IMU_CORRUPT:
            self.imu.faults.corrupt_frames += max(1, count)
        elif k is K.IMU_GAP:
            self.imu.faults.skip_frames += max(1, count)
        elif k in (K.TABLE_LINK_DROP, K.IMU_LINK_DROP):
            self._link_down(k, True)
        elif k is K.TABLE_OVERSPEED:
            with self.world.lock:
                self.world.table.overspeed = OVERSPEED_FACTOR
                self.world.table.command(now, self.world.table.commanded_dps)  # the drive runs away now
        elif k is K.IMU_OVERHEAT:
            self.world.imu_extra_heat_c = OVERHEAT_C

    def clear(self, kind: FaultKind | str) -> None:
        k = fault_kind(kind) if not isinstance(kind, FaultKind) else kind
        log.debug("sim fault off: %s", k.value)
        if k in (K.MODBUS_TIMEOUT, K.GARBAGE_PV, K.HEATER_FAILURE, K.COMPRESSOR_FAILURE, K.HEATER_STUCK,
                 K.TABLE_SILENT, K.TABLE_GARBAGE):
            self._flag(k, False)
        elif k in (K.MODBUS_EXCEPTION, K.MODBUS_BUSY):
            self.chamber.faults.exception_code = None
            self.chamber.faults.exception_count = 0
        elif k is K.MODBUS_OUTAGE:
            self.chamber.refuse_connections(False)
        elif k is K.TABLE_FAULT:
            self.table.faults.fault = None
        elif k is K.IMU_STALL:
            # Frames already sent stay lost; the stall ends for frames timed from now on.
            self.imu.faults.stall_from = self.imu.faults.stall_until = None
        elif k is K.IMU_CORRUPT:
            self.imu.faults.corrupt_frames = 0
        elif k is K.IMU_GAP:
            self.imu.faults.skip_frames = 0
        elif k in (K.TABLE_LINK_DROP, K.IMU_LINK_DROP):
            self._link_down(k, False)
        elif k is K.TABLE_OVERSPEED:
            with self.world.lock:
                self.world.table.overspeed = 1.0
        elif k is K.IMU_OVERHEAT:
            self.world.imu_extra_heat_c = 0.0
        # MODBUS_DROP is one-shot: nothing to clear.

    def _flag(self, k: FaultKind, on: bool) -> None:
        # Faults that are a flag on a simulated part, set while the fault lasts: (part, attribute).
        flags = {
            K.MODBUS_TIMEOUT: (self.chamber.faults, "silent"),
            K.GARBAGE_PV: (self.chamber.faults, "garbage_pv"),
            K.HEATER_FAILURE: (self.world.chamber, "heater_failed"),
            K.COMPRESSOR_FAILURE: (self.world.chamber, "compressor_failed"),
            K.HEATER_STUCK: (self.world.chamber, "heater_stuck"),
            K.TABLE_SILENT: (self.table.faults, "silent"),
            K.TABLE_GARBAGE: (self.table.faults, "garbage"),
        }
        with self.world.lock:
            if k in flags:
                part, attribute = flags[k]
                setattr(part, attribute, on)

    def _link_down(self, k: FaultKind, down: bool) -> None:
        port = self.table_port if k is K.TABLE_LINK_DROP else self.imu_port
        if not isinstance(port, (TcpSerialPort, MemoryPort)):
            # A pty cannot refuse its one client; the fault needs the socket:// links.
            log.warning("sim fault %s: not possible on a %s link; ignored", k.value, type(port).__name__)
            return
        port.refuse(down)  # closes the listener and drops the client, or listens again


__all__ = ["SimFaults"]
