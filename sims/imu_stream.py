"""The simulated IMU: a stream of binary frames at its output rate, in the project's 20-byte frame
(drivers.imu_frames) or the Xsens MTi's Xbus MTData2 messages (drivers.xsens_mti): `IMU_FORMATS`.

Frames exist for every sample time t_on + k / rate up to the clock's time while the
IMU is powered; `emit_until(t)` sends the ones not sent yet. With a virtual clock it
is a clock listener (`on_clock`, called in the sleeping thread, so a dry run is deterministic);
with a wall or scaled clock a ticker thread calls it. Faults: stalls, corrupt bursts,
frame-counter gaps, and the link dropping (see `ImuFaults`).

On demand (`make_on_demand`, a dry run's line inside the process that only the driver's own reads
empty): the listener only notes the time the frames are due up to, and they are made and sent when the
driver reads the line (`flush`), or before anything changes what they would be (a table command, a
remount, a fault: `SimLab` flushes first). The bytes are the same, sent in fewer, larger chunks (a
record is one chunk, not one per poll: each chunk has a fixed cost of ~0.3 ms).
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass

import numpy as np

from labrunner.clock import Clock
from labrunner.drivers.imu_frames import LABRUNNER_FRAME, FrameCodec
from labrunner.drivers.xsens_mti import XBUS
from labrunner.imu.model import ModelState

from .links import SimPort
from .world import SimWorld

log = logging.getLogger(__name__)

MAX_CHUNK_S = 60.0  # generate long sleeps in pieces to bound memory
ON_DEMAND_MAX_CHUNK_S = 600.0  # frames made on demand: pieces of up to this (a few MB)
# Wire formats a sim configuration may ask for (`imu_format`), and the lab driver that reads each.
IMU_FORMATS: dict[str, FrameCodec] = {"labrunner_frame": LABRUNNER_FRAME, "xsens_mti": XBUS}
IMU_DRIVERS = {"labrunner_frame": None, "xsens_mti": "xsens_mti"}  # None: the lab's default IMU driver


@dataclass
class ImuFaults:
    stall_from: float | None = None  # send nothing for frames timed in [stall_from, stall_until)
    stall_until: float | None = None
    corrupt_frames: int = 0  # corrupt this many of the next frames (a burst)
    skip_frames: int = 0  # drop this many of the next frames (counter gap)


class ImuStreamSim:
    def __init__(self, world: SimWorld, clock: Clock, port: SimPort, rate_hz: float = 50.0, seed: int = 0,
                 codec: FrameCodec = LABRUNNER_FRAME) -> None:
        self.world = world
        self.clock = clock
        self.port = port
        self.rate_hz = float(rate_hz)
        self.codec = codec
        self.faults = ImuFaults()
        self.state = ModelState()
        self._rng = np.random.default_rng([seed, 0x1A2B])
        self._fault_rng = np.random.default_rng([seed, 0xFA17])
        self._run = world.run
        self._next_k = 0
        self.frames_sent = 0
        self.last_sent_counter: int | None = None  # counter of the last intact frame put on the line
        self._lock = threading.Lock()
        self._ticker: threading.Thread | None = None
        self._stop = threading.Event()
        self.on_demand = False
        self._dues: list[float] = []  # on demand: the clock's advances since frames were last made

    def on_clock(self, t: float) -> None:
        """The clock's listener: send the frames up to t, or (on demand) note that they are due."""
        if self.on_demand:
            self._dues.append(t)
        else:
            self.emit_until(t)

    def make_on_demand(self) -> None:
        """Make frames when the driver reads the line (the port's `on_read`), not at each clock advance."""
        self.on_demand = True
        self.port.on_read = self.flush  # type: ignore[attr-defined]  # a MemoryPort

    def flush(self) -> None:
        """Make and send the frames due so far (on demand; nothing if none is due): those the listener would
        have sent at the advances since the last flush, with what it would have seen then (`_horizons`)."""
        dues, self._dues = self._dues, []
        if not dues:
            return
        with self._lock:
            while True:
                chunk = self._next_chunk(dues[-1], dues)
                if chunk is None:
                    return
                self._send(*chunk)

    def stop_on_demand(self) -> None:
        """Send what is due, then send at every clock advance again (before a fault changes the stream)."""
        if self.on_demand:
            self.flush()
            self.on_demand = False
            self.port.on_read = None  # type: ignore[attr-defined]

    def _horizons(self, ks: np.ndarray, dues: list[float]) -> np.ndarray:
        """For frames `ks` made on demand, the sample time of the last frame of the chunk the listener would
        have sent each in (one per advance in `dues`, split at MAX_CHUNK_S): the world's temperature history
        then ended at the grid step at or before it, and the frames after that step held its value."""
        w = self.world
        per = int(MAX_CHUNK_S * self.rate_hz)
        ends = np.empty(ks.size, dtype=np.int64)
        pos, first, last = int(ks[0]), int(ks[0]), int(ks[-1])
        for d in dues:
            kd = min(math.floor((d - w.t_on) * self.rate_hz + 1e-9), last)
            while pos <= kd:
                end = min(kd, pos + per - 1)
                ends[pos - first:end - first + 1] = end
                pos = end + 1
        return w.t_on + ends / self.rate_hz

    def emit_until(self, t: float) -> None:
        """Send all frames with sample time <= t that have not been sent."""
        with self._lock:
            while True:
                chunk = self._next_chunk(t)
                if chunk is None:
                    return
                self._send(*chunk)

    def _next_chunk(self, t: float, dues: list[float] | None = None) -> tuple[np.ndarray, bytes] | None:
        w = self.world
        with w.lock:
            if w.run != self._run:  # power-cycled: the counter starts again
                log.debug("imu sim: run %d starts (power-on), counter from 0", w.run)
                self._run = w.run
                self._next_k = 0
                self.last_sent_counter = None
            if not w.powered:
                return None
            k_last = math.floor((t - w.t_on) * self.rate_hz + 1e-9)
            if k_last < self._next_k:
                return None
            per = int((ON_DEMAND_MAX_CHUNK_S if dues is not None else MAX_CHUNK_S) * self.rate_hz)
            k_last = min(k_last, self._next_k + per - 1)
            ks = np.arange(self._next_k, k_last + 1)
            times = w.t_on + ks / self.rate_hz
            w.advance(float(times[-1]))
            inputs = w.imu_inputs(times) if dues is None else \
                w.imu_inputs(times, history_until=self._horizons(ks, dues))
            out, self.state = w.model.simulate(inputs, self.rate_hz, self._rng, self.state)
            self._next_k = k_last + 1
        return ks, self.codec.encode(ks, out[:, :3], out[:, 3:], inputs.temp_c, t_s=inputs.t_on_s)

    def _send(self, ks: np.ndarray, data: bytes) -> None:
        f = self.faults
        keep = np.ones(ks.size, dtype=bool)
        if f.stall_until is not None:
            times = self.world.t_on + ks / self.rate_hz
            lo = f.stall_from if f.stall_from is not None else -np.inf
            keep &= (times < lo) | (times >= f.stall_until)  # stalled: these frames never leave the IMU
            if times[-1] >= f.stall_until:
                f.stall_from = f.stall_until = None
        if f.skip_frames:
            n = min(f.skip_frames, ks.size)
            keep[:n] = False
            f.skip_frames -= n
            log.debug("imu sim: %d frame(s) not sent (counter gap)", n)
        size = self.codec.frame_size
        if not f.corrupt_frames and keep.all():  # the usual chunk: sent as encoded, no copy
            if data and self.port.write(data) == len(data):
                self.last_sent_counter = int(ks[-1]) % 65536
            self.frames_sent += ks.size
            return
        raw = np.frombuffer(data, dtype=np.uint8).reshape(ks.size, size).copy()
        intact = keep.copy()
        if f.corrupt_frames:
            n = min(f.corrupt_frames, int(keep.sum()))
            idx = np.flatnonzero(keep)[:n]
            pos = self._fault_rng.integers(2, size, size=n)  # after the sync bytes: found, then rejected
            raw[idx, pos] ^= self._fault_rng.integers(1, 256, size=n).astype(np.uint8)
            intact[idx] = False
            f.corrupt_frames -= n
            log.debug("imu sim: %d frame(s) corrupted on the line", n)
        if not keep.all() or not intact.all():
            payload = raw[keep].tobytes()
        else:
            payload = data
        if payload and self.port.write(payload) == len(payload) and intact.any():
            self.last_sent_counter = int(ks[np.flatnonzero(intact)[-1]]) % 65536
        self.frames_sent += int(keep.sum())

    # --- real-time operation (wall or scaled clock) -------------------------------------------

    def start_ticker(self, period_s: float = 0.02) -> None:
        def tick() -> None:
            while not self._stop.wait(period_s):
                self.emit_until(self.clock.now())

        self._ticker = threading.Thread(target=tick, name="sim-imu", daemon=True)
        self._ticker.start()

    def close(self) -> None:
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join(timeout=2)
