"""A table command and the IMU's frames share one order in simulated time.

Served on a scaled clock the IMU stream is a ticker thread that generates frames up to the time it read
from the clock, under the world's lock. A table command read its time before taking that lock, so a
chunk generated meanwhile (up to `MAX_CHUNK_S`, at 600x a tick is 12 s of lab time) put frames timed after
the command on the line with the old rate: record means off by the rate step (the old "z-gyro record
means off by up to ~50 deg/s at 600x"). The race is made deterministic here: the clock read by the
command lets the IMU thread emit 12 s ahead right then, and the test checks the rates those frames got.
"""

from __future__ import annotations

import threading

import numpy as np

from labrunner.clock import VirtualClock
from labrunner.sims.imu_stream import ImuStreamSim
from labrunner.sims.links import TcpSerialPort
from labrunner.sims.table_server import TableServer
from labrunner.sims.world import SimLabConfig, SimWorld


class _RacingClock(VirtualClock):
    """A clock whose next read (`arm`) lets another thread emit IMU frames `ahead_s` past it."""

    def __init__(self, start: float) -> None:
        super().__init__(start=start)
        self.armed: ImuStreamSim | None = None
        self.ahead_s = 12.0
        self.thread: threading.Thread | None = None

    def now(self) -> float:
        t = super().now()
        imu, self.armed = self.armed, None
        if imu is not None:
            self.thread = threading.Thread(target=imu.emit_until, args=(t + self.ahead_s,))
            self.thread.start()
            self.thread.join(0.5)  # unordered: it finishes now; ordered: it waits for the command's lock
        return t


def test_frames_timed_after_a_table_command_carry_its_rate():
    world = SimWorld(SimLabConfig(orientation="z_up"), start_t=0.0)
    clock = _RacingClock(start=0.0)
    table_port, imu_port = TcpSerialPort(), TcpSerialPort()
    srv = TableServer(world, clock, table_port, language="labrunner")
    imu = ImuStreamSim(world, clock, imu_port, rate_hz=50.0)
    seen: list[tuple[np.ndarray, np.ndarray]] = []
    inputs = world.imu_inputs

    def recording(times):
        out = inputs(times)
        seen.append((np.asarray(times, dtype=float).copy(), out.rate_dps[:, 2].copy()))
        return out

    world.imu_inputs = recording  # type: ignore[method-assign]
    try:
        clock.sleep(100.0)
        imu.emit_until(clock.now())  # frames up to the command, at rest
        clock.armed = imu
        assert srv.handle("JOG+50.0000") is not None
        assert clock.thread is not None
        clock.thread.join(5.0)
        assert not clock.thread.is_alive()
        command_t = 100.0
        times = np.concatenate([t for t, _ in seen])
        rate = np.concatenate([r for _, r in seen])
        after = times > command_t + 0.5  # the table accelerates: half a second past the command it moves
        assert after.sum() >= 500  # the 12 s the racing thread emitted
        expected = world.table.rate_at(times[after])
        assert np.allclose(rate[after], expected, atol=1e-9), \
            f"frames after the command carry {rate[after].min():.2f} deg/s, the table turns at {expected.min():.2f}"
        assert rate[after].max() > 1.0
    finally:
        imu.close()
        srv.close()
        table_port.close()
        imu_port.close()
