"""Serial client for the IMU's binary frame stream.

A reader thread waits on the line, decodes frames (vectorised, resynchronising after
corrupt bytes) and keeps them with their counters unwrapped. A record is a window of
consecutive counters: `begin_record()` marks the last frame received, the caller
lets the recording time pass, and `end_record(start, n)` returns the n frames that
follow, counting the ones that never arrived (counter gaps) as dropped. The link is
reopened automatically when it drops. Reading and parsing happen under one lock, so
`begin_record` sees every byte that has reached the port.
"""

from __future__ import annotations

import logging
import select
import threading
import time
from collections.abc import Callable

import numpy as np
import serial

from .errors import InstrumentError
from .imu_frames import ACCEL_LSB_G, COUNTER_MODULO, GYRO_LSB_DPS, TEMP_LSB_C, FrameDecoder, unwrap_counter
from .protocols import ImuRecord, ImuSample
from .serial_link import close_quietly, open_serial

READ_SIZE = 1 << 16

# Connects, link losses and resynchronisations are logged; single frames (50 Hz) never are:
# corrupt stretches and duplicates at DEBUG as they happen, each record's counts at DEBUG.
log = logging.getLogger(__name__)


class SerialImu:
    """An IMU streaming frames on a serial line (implements `drivers.protocols.Imu`)."""

    def __init__(self, url: str, *, rate_hz: float = 50.0, baudrate: int = 921600, name: str = "imu",
                 keep_s: float = 600.0, reopen_s: float = 0.2,
                 on_event: Callable[[str, str], None] | None = None) -> None:
        self.name = name
        self.address = url
        self.rate_hz = float(rate_hz)
        self.baudrate = baudrate
        self.keep_frames = int(keep_s * rate_hz)
        self.reopen_s = reopen_s
        self.on_event = on_event  # (kind, message): link lost / restored, for the campaign's event log
        self._ser: serial.SerialBase | None = None
        self._cond = threading.Condition(threading.RLock())
        self._decoder = FrameDecoder()
        self._chunks: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._buffered = 0
        self._last: int | None = None
        self._open_records: dict[int, int] = {}  # record start counter -> corrupt count at its start
        self.bytes_received = 0
        self.frames_received = 0
        self.duplicates = 0
        self.link_drops = 0
        self._running = False
        self._thread: threading.Thread | None = None

    # --- connection ---------------------------------------------------------------------

    def connect(self) -> None:
        with self._cond:
            if self._ser is None:
                self._ser = open_serial(self.address, baudrate=self.baudrate, timeout_s=0.0, instrument=self.name)
                log.info("%s: stream open at %s (%g Hz expected)", self.name, self.address, self.rate_hz)
            if not self._running:
                self._running = True
                self._thread = threading.Thread(target=self._reader, name=f"{self.name}-reader", daemon=True)
                self._thread.start()

    def close(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        with self._cond:
            close_quietly(self._ser)
            self._ser = None
        log.debug("%s: closed: %d frames, %d bytes, %d corrupt stretch(es), %d duplicate(s), %d link drop(s)",
                  self.name, self.frames_received, self.bytes_received, self.corrupt, self.duplicates,
                  self.link_drops)

    @property
    def corrupt(self) -> int:
        return self._decoder.corrupt

    @property
    def link_up(self) -> bool:
        return self._ser is not None

    def _event(self, kind: str, message: str) -> None:
        if self.on_event:
            self.on_event(kind, message)

    def _lose_link(self, exc: BaseException) -> None:
        with self._cond:
            if self._ser is not None:
                close_quietly(self._ser)
                self._ser = None
                self.link_drops += 1
                self._decoder.drop_partial()  # a new connection starts mid-stream
                log.warning("%s at %s: link lost (%s); reopening", self.name, self.address, exc)
                self._event("imu_link_lost", f"{self.name} at {self.address}: link lost ({exc})")

    def _reader(self) -> None:
        while self._running:
            ser = self._ser
            if ser is None:
                try:
                    fresh = open_serial(self.address, baudrate=self.baudrate, timeout_s=0.0, instrument=self.name)
                except InstrumentError:
                    time.sleep(self.reopen_s)
                    continue
                with self._cond:
                    self._ser = fresh
                log.info("%s at %s: link restored", self.name, self.address)
                self._event("imu_link_restored", f"{self.name} at {self.address}: link restored")
                continue
            try:
                ready, _, _ = select.select([ser.fileno()], [], [], 0.05)
            except (OSError, ValueError, serial.SerialException) as exc:
                self._lose_link(exc)
                continue
            if ready:
                with self._cond:
                    self._drain_locked()

    def _drain_locked(self) -> None:
        """Read and parse whatever the port holds now (the port is non-blocking); a broken link is dropped."""
        ser = self._ser
        if ser is None:
            return
        while True:
            # pyserial's socket:// in_waiting is only 0 or 1, so read large instead of asking.
            try:
                data = ser.read(READ_SIZE)
            except (OSError, serial.SerialException) as exc:
                self._lose_link(exc)  # the reader thread reopens it
                return
            if not data:
                return
            self._ingest(data)
            if len(data) < READ_SIZE:
                return

    def _ingest(self, data: bytes) -> None:
        self.bytes_received += len(data)
        dec = self._decoder.feed(data)
        if dec.corrupt:
            log.debug("%s: resynchronised after %d corrupt stretch(es) (%d so far)", self.name, dec.corrupt,
                      self._decoder.corrupt)
        if len(dec):
            counters = unwrap_counter(dec.counter, self._last)
            fresh = counters > (self._last if self._last is not None else -1)
            stale = int((~fresh).sum())
            if stale:
                log.debug("%s: %d duplicate or stale frame(s) ignored", self.name, stale)
            self.duplicates += stale
            if fresh.any():
                counters = counters[fresh]
                self._chunks.append((counters, dec.accel[fresh], dec.gyro[fresh], dec.temp[fresh]))
                self._buffered += counters.size
                self._last = int(counters[-1])
                self.frames_received += counters.size
                self._trim()
        self._cond.notify_all()

    def _trim(self) -> None:
        oldest_needed = min(self._open_records, default=None)
        while len(self._chunks) > 1 and self._buffered - self._chunks[0][0].size >= self.keep_frames:
            if oldest_needed is not None and self._chunks[0][0][-1] > oldest_needed:
                break
            self._buffered -= self._chunks.pop(0)[0].size

    # --- the Imu interface ------------------------------------------------------------------

    def restart_stream(self) -> None:
        """Forget buffered frames and counter history (after the IMU was power-cycled)."""
        log.debug("%s: stream restarted (IMU power-cycled)", self.name)
        with self._cond:
            self._drain_locked()
            self._chunks.clear()
            self._buffered = 0
            self._last = None
            self._open_records.clear()

    def latest(self) -> ImuSample | None:
        with self._cond:
            if not self._chunks:
                return None
            c, a, g, t = self._chunks[-1]
            return ImuSample(counter=int(c[-1]), accel_g=tuple((a[-1] * ACCEL_LSB_G).tolist()),
                             gyro_dps=tuple((g[-1] * GYRO_LSB_DPS).tolist()), temp_c=float(t[-1]) * TEMP_LSB_C)

    def last_counter16(self) -> int | None:
        last = self._last
        return None if last is None else last % COUNTER_MODULO

    def wait_counter16(self, counter16: int, timeout_s: float) -> bool:
        """Wait until the frame with this 16-bit counter is the latest parsed (dry-run barrier)."""
        with self._cond:
            self._drain_locked()
            return self._cond.wait_for(lambda: self.last_counter16() == counter16, timeout_s)

    def begin_record(self) -> int:
        """Mark the start of a record: the counter of the last frame received (-1: none yet, the
        record then starts at the first frame that arrives)."""
        with self._cond:
            self._drain_locked()
            start = self._last if self._last is not None else -1
            self._open_records[start] = self._decoder.corrupt  # corrupt count so far, to report the record's own
            return start

    def end_record(self, start: int, n_frames: int, timeout_s: float) -> ImuRecord:
        """The n frames after `start`, waiting up to timeout_s (real seconds) for late ones."""
        with self._cond:
            self._drain_locked()
            corrupt_at_start = self._open_records.pop(start, self._decoder.corrupt)
            if start < 0:
                # Nothing had arrived at begin_record: the window starts at the first frame that did.
                self._cond.wait_for(lambda: bool(self._chunks), timeout_s)
                start = int(self._chunks[0][0][0]) - 1 if self._chunks else start
            end = start + n_frames
            self._cond.wait_for(lambda: self._last is not None and self._last >= end, timeout_s)
            corrupt = self._decoder.corrupt - corrupt_at_start
            parts = [ch for ch in self._chunks if ch[0][-1] > start and ch[0][0] <= end]
        if parts:
            counter = np.concatenate([p[0] for p in parts])
            sel = (counter > start) & (counter <= end)
            counter = counter[sel]
            accel = np.concatenate([p[1] for p in parts])[sel] * ACCEL_LSB_G
            gyro = np.concatenate([p[2] for p in parts])[sel] * GYRO_LSB_DPS
            temp = np.concatenate([p[3] for p in parts])[sel] * TEMP_LSB_C
        else:
            counter = np.zeros(0, np.int64)
            accel = gyro = np.zeros((0, 3))
            temp = np.zeros(0)
        log.debug("%s: record after counter %d: %d of %d frames, %d corrupt stretch(es)", self.name, start,
                  counter.size, n_frames, corrupt)
        return ImuRecord(counter=counter, accel_g=accel, gyro_dps=gyro, temp_c=temp, expected=n_frames,
                         dropped=n_frames - int(counter.size), corrupt=corrupt,
                         lsb=(ACCEL_LSB_G, GYRO_LSB_DPS, TEMP_LSB_C))
