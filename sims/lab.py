"""The simulated lab: chamber, rate table and IMU servers on one world and one clock.

In a dry run the clock is virtual and the IMU stream is a clock listener; served
standalone (`labrunner sim serve`) the clock is wall time, optionally sped up, and
the IMU has a ticker thread. The drivers reach the sims through real sockets or
pseudo-terminals, or, in a dry run built by `labrunner.lab.simulated_lab`, through serial
lines inside the process (`links.MemoryPort`) that carry the same bytes; the chamber is a
pymodbus server either way.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from labrunner.clock import SAFETY_NET_S, Clock, VirtualClock, io_timeouts
from labrunner.fault_kinds import FaultKind

from .aio import LoopThread
from .chamber_server import ChamberServer
from .faults import SimFaults
from .imu_stream import IMU_DRIVERS, IMU_FORMATS, ImuStreamSim
from .links import MemoryPort, PtyPort, SimPort, TcpSerialPort
from .table_server import TableServer
from .world import SimLabConfig, SimWorld

log = logging.getLogger(__name__)
# Plant faults a sim configuration may switch on from the start (faults.chamber).
# How the table and the IMU are reached: "memory" (a dry run's lines inside the process, `MemoryPort`:
# the protocols' bytes without the sockets' thread hand-offs), "tcp" (socket://) or "pty".
LINKS = ("memory", "tcp", "pty")
STARTING_FAULTS = {"heater_failed": FaultKind.HEATER_FAILURE, "compressor_failed": FaultKind.COMPRESSOR_FAILURE}


@dataclass(frozen=True)
class SimPorts:
    chamber: int = 0
    table: int = 0
    imu: int = 0


class SimLab:
    """The simulated instruments of one lab; faults go through `apply_fault` / `clear_fault`."""

    def __init__(self, config: SimLabConfig, clock: Clock, *, host: str = "127.0.0.1", link: str = "tcp",
                 chamber_transport: str = "tcp", chamber_profile: str = "watlow_f4",
                 ports: SimPorts = SimPorts(), imu_on_demand: bool = False) -> None:
        if link not in LINKS:
            raise ValueError(f"sim link must be one of {', '.join(LINKS)}, got {link!r}")
        if link == "memory" and not isinstance(clock, VirtualClock):
            # Served in real time, frames come from a ticker thread and a driver in another process may read.
            raise ValueError("sim link 'memory' needs a virtual clock (a dry run)")
        self.config = config
        self.clock = clock
        self.world = SimWorld(config, clock.now())
        # On memory links the chamber is Modbus RTU inside the process too: no event loop thread.
        served = "memory" if link == "memory" else chamber_transport
        self.loop = LoopThread("sim-modbus") if served != "memory" else None
        self.chamber = ChamberServer(self.world, clock, chamber_profile, transport=served, host=host,
                                     port=ports.chamber, loop=self.loop)
        # On a virtual clock a dry run waits for its reader however slow the machine is (the safety net
        # only catches a hang); served in real time, a line with nobody reading loses its bytes.
        virtual = isinstance(clock, VirtualClock)
        send_s = SAFETY_NET_S if virtual else 2.0
        self.table_port: SimPort
        self.imu_port: SimPort
        if link == "memory":
            self.table_port, self.imu_port = MemoryPort("table"), MemoryPort("imu")
        elif link == "tcp":
            self.table_port = TcpSerialPort(host, ports.table, send_s)
            self.imu_port = TcpSerialPort(host, ports.imu, send_s, await_close=virtual)
        else:
            self.table_port, self.imu_port = PtyPort(send_s), PtyPort(send_s)
        self.table = TableServer(self.world, clock, self.table_port, seed=config.seed)
        self.imu = ImuStreamSim(self.world, clock, self.imu_port, rate_hz=config.imu_rate_hz, seed=config.seed,
                                codec=IMU_FORMATS[config.imu_format])
        if isinstance(clock, VirtualClock):
            clock.add_listener(self.imu.on_clock)
        else:
            self.imu.start_ticker()
        if imu_on_demand and link == "memory":
            # Frames made when the driver reads its line (or before a command, remount or fault changes
            # them), not at every advance: the same bytes in fewer chunks (`ImuStreamSim.make_on_demand`).
            self.imu.make_on_demand()
            self.table.before_command = self.imu.flush
        # The drivers' waits on these links are decided in virtual time (labrunner.clock.io_timeouts).
        self._virtual_links = [self.chamber.url, self.table_port.url, self.imu_port.url] if virtual else []
        for url in self._virtual_links:
            io_timeouts.serve_virtually(url)
        self._faults = SimFaults(self.world, clock, self.chamber, self.table, self.imu, self.table_port,
                                 self.imu_port)
        self._apply_starting_faults(config.faults.get("chamber") or {})
        self.host = host
        self.link = link
        self.chamber_transport = served
        self.chamber_profile = chamber_profile
        log.info("simulated lab up: chamber %s (%s), table %s, imu %s", self.chamber.url, chamber_transport,
                 self.table_port.url, self.imu_port.url)

    def _apply_starting_faults(self, spec: dict[str, Any]) -> None:
        """Faults present from the start, from the sim configuration (e.g. a failed compressor)."""
        unknown = set(spec) - set(STARTING_FAULTS)
        if unknown:
            raise ValueError(f"sim configuration faults.chamber: unknown key(s) {', '.join(sorted(unknown))}; "
                             f"known: {', '.join(sorted(STARTING_FAULTS))}")
        for key, kind in STARTING_FAULTS.items():
            if spec.get(key, False):
                self.apply_fault(kind)

    # --- the fault interface (fault plans use only this) ------------------------------------

    def apply_fault(self, kind: FaultKind | str, *, duration_s: float = 0.0, count: int = 0) -> None:
        """Start a fault now (see `labrunner.fault_kinds.FaultKind`); unknown kinds are a ValueError."""
        self.imu.stop_on_demand()  # faults act on the stream as it is sent at each advance
        self._faults.apply(kind, duration_s=duration_s, count=count)

    def clear_fault(self, kind: FaultKind | str) -> None:
        """End a fault now."""
        self.imu.stop_on_demand()
        self._faults.clear(kind)

    # --- what the dry run's operator and barrier need -----------------------------------------

    def power_off(self) -> None:
        """The IMU loses power (the operator opened the door to remount it)."""
        self.imu.flush()
        self.world.power_off()

    def settle_imu(self, imu: object) -> None:
        """A dry run's barrier, after each clock advance: wait until the IMU driver has read every byte the
        simulated IMU put on the line (frames, corrupt ones too), so what it parsed does not depend on
        how fast the machine is. Drivers without `wait_received` (not a stream reader) are left alone."""
        if self.imu.on_demand:  # the driver's reads take the frames: nothing was sent unread
            return
        wait = getattr(imu, "wait_received", None)
        if wait is not None and getattr(imu, "streaming", False):
            if not wait(self.imu_port.bytes_written, SAFETY_NET_S):
                log.warning("simulated IMU: the driver did not read what was sent within %g s", SAFETY_NET_S)

    @property
    def last_imu_counter(self) -> int | None:
        """16-bit counter of the last intact IMU frame put on the line (None: none since power-on)."""
        return self.imu.last_sent_counter

    def lab_config(self) -> dict[str, Any]:
        """A lab configuration (see `labrunner.lab`) that points the drivers at these sims."""
        if self.chamber_transport == "tcp":
            chamber: dict[str, Any] = {"transport": "tcp", "host": self.host, "port": self.chamber.port}
        elif self.chamber_transport == "memory":
            chamber = {"transport": "rtu", "serial_port": self.chamber.url, "baudrate": 115200}
        else:
            chamber = {"transport": "rtu", "serial_port": self.chamber.url, "baudrate": 115200}
        if self.chamber_profile in ("watlow_f4", "watlow_f4t"):  # a controller with its own driver
            chamber = {"driver": self.chamber_profile, **chamber}
        else:
            chamber["profile"] = self.chamber_profile
        # Loopback answers within a millisecond: short timeouts keep faulted dry runs quick.
        chamber["timeout_s"] = 0.25
        imu: dict[str, Any] = {"port": self.imu_port.url, "baudrate": 921600, "rate_hz": self.config.imu_rate_hz}
        driver = IMU_DRIVERS[self.config.imu_format]
        if driver is not None:  # another wire format than the project's frame: the driver that reads it
            imu = {"driver": driver, **imu}
        return {
            "name": "simulated lab",
            "chamber": chamber,
            "table": {**({"driver": self.table.language.name} if self.table.language.name != "labrunner" else {}),
                      "port": self.table_port.url, "baudrate": 115200, "timeout_s": 0.25},
            "imu": imu,
        }

    def remount(self, orientation: str) -> None:
        """What the operator does at a mounting prompt: power down, turn the IMU, power up."""
        self.imu.flush()
        self.world.remount(orientation, self.clock.now())

    @property
    def mounted_orientation(self) -> str:
        """How the simulated IMU stands on the table now."""
        return self.world.orientation

    def restore(self, *, orientation: str, air_c: float, setpoint_c: float, powered_since: float, run: int,
                imu_c: float | None = None) -> None:
        """A resumed dry run's lab as the last session left it (`SimWorld.restore`)."""
        self.imu.flush()
        self.world.restore(orientation=orientation, air_c=air_c, setpoint_c=setpoint_c, powered_since=powered_since,
                           run=run, imu_c=imu_c)

    def close(self) -> None:
        log.debug("simulated lab closing")
        if isinstance(self.clock, VirtualClock):
            self.clock.remove_listener(self.imu.on_clock)
        self.imu.close()
        self.table.close()
        self.chamber.close()
        self.table_port.close()
        self.imu_port.close()
        if self.loop is not None:
            self.loop.stop()
        for url in self._virtual_links:
            io_timeouts.release(url)
        self._virtual_links = []
