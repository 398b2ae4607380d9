"""The simulated lab: chamber, rate table and IMU servers on one world and one clock.

In a dry run the clock is virtual and the IMU stream is a clock listener; served
standalone (`labrunner sim serve`) the clock is wall time, optionally sped up, and
the IMU has a ticker thread. Either way the drivers reach the sims through real
sockets or pseudo-terminals.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from labrunner.clock import Clock, VirtualClock

from .aio import LoopThread
from .chamber_server import ChamberServer
from .imu_stream import ImuStreamSim
from .links import PtyPort, SimPort, TcpSerialPort
from .table_server import TableServer
from .world import SimLabConfig, SimWorld


@dataclass(frozen=True)
class SimPorts:
    chamber: int = 0
    table: int = 0
    imu: int = 0


class SimLab:
    def __init__(self, config: SimLabConfig, clock: Clock, *, host: str = "127.0.0.1", link: str = "tcp",
                 chamber_transport: str = "tcp", chamber_profile: str = "watlow_f4",
                 ports: SimPorts = SimPorts()) -> None:
        if link not in ("tcp", "pty"):
            raise ValueError(f"sim link must be 'tcp' or 'pty', got {link!r}")
        self.config = config
        self.clock = clock
        self.world = SimWorld(config, clock.now())
        self.loop = LoopThread("sim-modbus")
        self.chamber = ChamberServer(self.world, clock, chamber_profile, transport=chamber_transport, host=host,
                                     port=ports.chamber, loop=self.loop)
        self.table_port: SimPort = TcpSerialPort(host, ports.table) if link == "tcp" else PtyPort()
        self.imu_port: SimPort = TcpSerialPort(host, ports.imu) if link == "tcp" else PtyPort()
        self.table = TableServer(self.world, clock, self.table_port, seed=config.seed)
        self.imu = ImuStreamSim(self.world, clock, self.imu_port, rate_hz=config.imu_rate_hz, seed=config.seed)
        if isinstance(clock, VirtualClock):
            clock.add_listener(self.imu.emit_until)
        else:
            self.imu.start_ticker()
        self._apply_plant_faults(config.faults.get("chamber") or {})
        self.host = host
        self.link = link
        self.chamber_transport = chamber_transport
        self.chamber_profile = chamber_profile

    def _apply_plant_faults(self, spec: dict[str, Any]) -> None:
        """Faults present from the start, from the sim configuration (e.g. a failed compressor)."""
        known = {"heater_failed", "compressor_failed"}
        unknown = set(spec) - known
        if unknown:
            raise ValueError(f"sim configuration faults.chamber: unknown key(s) {', '.join(sorted(unknown))}; "
                             f"known: {', '.join(sorted(known))}")
        plant = self.world.chamber
        plant.heater_failed = bool(spec.get("heater_failed", False))
        plant.compressor_failed = bool(spec.get("compressor_failed", False))

    def lab_config(self) -> dict[str, Any]:
        """A lab configuration (see `labrunner.lab`) that points the drivers at these sims."""
        if self.chamber_transport == "tcp":
            chamber: dict[str, Any] = {"transport": "tcp", "host": self.host, "port": self.chamber.port}
        else:
            chamber = {"transport": "rtu", "serial_port": self.chamber.url, "baudrate": 115200}
        chamber["profile"] = self.chamber_profile
        # Loopback answers within a millisecond: short timeouts keep faulted dry runs quick.
        chamber["timeout_s"] = 0.25
        return {
            "name": "simulated lab",
            "chamber": chamber,
            "table": {"port": self.table_port.url, "baudrate": 115200, "timeout_s": 0.25},
            "imu": {"port": self.imu_port.url, "baudrate": 921600, "rate_hz": self.config.imu_rate_hz},
        }

    def remount(self, orientation: str) -> None:
        """What the operator does at a mounting prompt: power down, turn the IMU, power up."""
        self.world.remount(orientation, self.clock.now())

    def close(self) -> None:
        if isinstance(self.clock, VirtualClock):
            self.clock.remove_listener(self.imu.emit_until)
        self.imu.close()
        self.table.close()
        self.chamber.close()
        self.table_port.close()
        self.imu_port.close()
        self.loop.stop()
