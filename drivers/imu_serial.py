"""Serial client for an IMU's binary stream: the project's 20-byte frame or another `FrameCodec`.

A reader thread waits on the line, decodes frames (vectorised, resynchronising after
corrupt bytes) and keeps them with their counters unwrapped. A record is a window of
consecutive counters: `begin_record()` marks the last frame received, the caller
lets the recording time pass, and `end_record(start, n)` returns the n frames that
follow, counting the ones that never arrived (counter gaps) as dropped. Frames that
arrive out of order (a counter a little behind the newest) are put back in their place;
repeated ones are dropped and counted. The link is reopened automatically when it drops.
Reading and parsing happen under one lock, so `begin_record` sees every byte that has
reached the port. A stream whose bytes arrive but never make a valid frame is reported
as such (`stream_report`): bytes received, frames rejected and why, bytes skipped.
On a line whose pyserial object says `caller_fed` (a dry run's line inside the process, whose
bytes arrive only while this process writes them) there is no reader thread: every call reads
and parses what is there, and no wait waits.
"""

from __future__ import annotations

import logging
import select
import threading
import time
from collections.abc import Callable

import numpy as np
import serial

from labrunner.clock import io_timeouts

from .errors import InstrumentError, InstrumentProtocolError, InstrumentTimeout
from .imu_frames import COUNTER_MODULO, LABRUNNER_FRAME, FrameCodec
from .protocols import ImuRecord, ImuSample
from .serial_link import close_quietly, open_serial

READ_SIZE = 1 << 16
# A counter at most this many frames behind the newest is a late (or repeated) frame; further
# behind, it is the counter running on (a wrap past a long gap), as before reordering was handled.
REORDER_WINDOW = 1024
# Bytes of this many frames without one valid frame: the stream is not what the codec reads.
NO_FRAME_AFTER = 3

# Connects, link losses and resynchronisations are logged; single frames (50 Hz) never are:
# corrupt stretches and duplicates at DEBUG as they happen, each record's counts at DEBUG.
log = logging.getLogger(__name__)


Chunk = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # counter, accel, gyro, temp (codec units)


class SerialImu:
    """An IMU streaming frames on a serial line (implements `drivers.protocols.Imu`)."""

    def __init__(self, url: str, *, rate_hz: float = 50.0, baudrate: int = 921600, name: str = "imu",
                 keep_s: float = 600.0, reopen_s: float = 0.2,
                 on_event: Callable[[str, str], None] | None = None, codec: FrameCodec = LABRUNNER_FRAME) -> None:
        self.name = name
        self.address = url
        self.rate_hz = float(rate_hz)
        self.baudrate = baudrate
        self.codec = codec
        self.keep_frames = int(keep_s * rate_hz)
        self.reopen_s = reopen_s
        self.on_event = on_event  # (kind, message): link lost / restored, for the campaign's event log
        self._ser: serial.SerialBase | None = None
        self._cond = threading.Condition(threading.RLock())
        self._decoder = codec.decoder()
        self._chunks: list[Chunk] = []  # frames in counter order
        self._late: list[Chunk] = []  # frames that arrived after a newer one, until a record takes them
        self._buffered = 0
        self._last: int | None = None  # newest (unwrapped) counter
        self._last_arrived16: int | None = None  # counter of the frame parsed last, in arrival order
        self._open_records: dict[int, int] = {}  # record start counter -> corrupt count at its start
        self._since_restart = (0, 0)  # (bytes, frames) when the stream last (re)started
        self.bytes_received = 0
        self.frames_received = 0
        self.duplicates = 0
        self.reordered = 0
        self.link_drops = 0
        self._reopening = False  # the reader thread is opening the line again
        # A line whose bytes arrive only while this process writes them (a dry run's line inside the process,
        # `caller_fed` on the pyserial object): no reader thread; every call reads what is there, nobody waits.
        self._caller_fed = False
        self._running = False
        self._thread: threading.Thread | None = None

    # --- connection ---------------------------------------------------------------------

    def connect(self) -> None:
        with self._cond:
            if self._ser is None and self.link_drops == 0:
                self._ser = open_serial(self.address, baudrate=self.baudrate, timeout_s=0.0, instrument=self.name)
                log.info("%s: %s stream open at %s (%g Hz expected)", self.name, self.codec.name, self.address,
                         self.rate_hz)
            elif self._ser is None and not self._reopen_locked():  # lost before: reopened, and said so
                raise InstrumentTimeout(self.name, self.address, "the link was lost and the line cannot be opened "
                                      "again")
            if self._ser is not None:
                self._caller_fed = bool(getattr(self._ser, "caller_fed", False))
                self._watch_line()
            if not self._running:
                self._running = True
                if not self._caller_fed:
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
        log.debug("%s: closed: %d frames, %d bytes, %d corrupt stretch(es), %d duplicate(s), %d reordered, "
                  "%d link drop(s)", self.name, self.frames_received, self.bytes_received, self.corrupt,
                  self.duplicates, self.reordered, self.link_drops)

    @property
    def corrupt(self) -> int:
        return self._decoder.corrupt

    @property
    def link_up(self) -> bool:
        """The line is open or being opened again (what is sent now will be read).

        On a link a simulator serves on a virtual clock (`labrunner.clock.io_timeouts`) the reader
        thread does not reopen a lost line by itself: the dry run's barrier (`wait_received`) and
        `connect` do, so a reconnect and its event happen at one moment of virtual time.
        """
        return self._ser is not None or self._reopening

    @property
    def streaming(self) -> bool:
        """Connected and not closed: the reader keeps (re)opening the line."""
        return self._running

    def stream_report(self) -> str:
        """What arrived since the stream (re)started: bytes, frames, and the frames rejected and why."""
        d = self._decoder
        got_bytes = self.bytes_received - self._since_restart[0]
        got_frames = self.frames_received - self._since_restart[1]
        return (f"{got_bytes} bytes received, {got_frames} valid {self.codec.name} frame(s); rejected: "
                f"{d.rejected.describe()}; resynchronisation skipped {d.skipped_bytes} byte(s)")

    def _check_stream(self) -> None:
        """Bytes arrive but no frame is valid: say so (instead of 'no frames')."""
        got_bytes = self.bytes_received - self._since_restart[0]
        if self.frames_received == self._since_restart[1] and got_bytes >= NO_FRAME_AFTER * self.codec.frame_size:
            raise InstrumentProtocolError(self.name, self.address, f"no valid frame: {self.stream_report()} "
                                          f"(wrong format, baud rate or a damaged line?)")

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

    def _reopen_locked(self) -> bool:
        """Open a lost line again (under the lock); True and the 'restored' event when it opened."""
        try:
            fresh = open_serial(self.address, baudrate=self.baudrate, timeout_s=0.0, instrument=self.name)
        except InstrumentError:
            return False
        self._ser = fresh
        self._watch_line()
        log.info("%s at %s: link restored", self.name, self.address)
        self._event("imu_link_restored", f"{self.name} at {self.address}: link restored")
        self._cond.notify_all()
        return True

    def _watch_line(self) -> None:
        """On a caller-fed line, be told when it is lost: no reader thread is there to find it."""
        if self._caller_fed and self._ser is not None:
            self._ser.on_lost = self._line_lost

    def _line_lost(self) -> None:
        """The line was lost: read what it still held, then find it lost (what the reader thread does)."""
        with self._cond:
            ser = self._ser
            for _ in range(2):  # the rest of what was sent, then the read that fails
                if ser is None or self._ser is not ser:
                    return
                self._drain_locked()

    def _reader(self) -> None:
        while self._running:
            ser = self._ser
            if ser is None:
                if io_timeouts.is_virtual(self.address):
                    time.sleep(0.02)  # a dry run's barrier reopens it, in virtual time
                    continue
                self._reopening = True
                with self._cond:
                    opened = self._ser is not None or self._reopen_locked()
                    self._reopening = False
                if not opened:
                    time.sleep(self.reopen_s)
                continue
            try:
                # The port may be closed by another thread (a read there failed) between the two
                # lines: pyserial's socket:// then has no socket (AttributeError on fileno).
                ready, _, _ = select.select([ser.fileno()], [], [], 0.05)
            except (OSError, ValueError, AttributeError, TypeError, serial.SerialException) as exc:
                if ser is self._ser:
                    self._lose_link(exc)
                continue
            if ready:
                with self._cond:
                    if ser is self._ser:
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
            except (OSError, AttributeError, TypeError, serial.SerialException) as exc:
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
            self._last_arrived16 = int(dec.counter[-1])
            counters, late = self._unwrap(dec.counter)
            if late is None:  # all in order (the usual batch): kept as decoded, no selection copies
                self._chunks.append((counters, dec.accel, dec.gyro, dec.temp))
                self._buffered += counters.size
                self._last = int(counters[-1])
                self.frames_received += counters.size
                self._trim()
                self._cond.notify_all()
                return
            fresh = ~late
            if fresh.any():
                self._chunks.append((counters[fresh], dec.accel[fresh], dec.gyro[fresh], dec.temp[fresh]))
                self._buffered += int(fresh.sum())
                self._last = int(counters[fresh][-1])
                self.frames_received += int(fresh.sum())
            if late.any():  # after the batch's own frames: a repeat of one of them is found
                self._keep_late(counters[late], dec.accel[late], dec.gyro[late], dec.temp[late])
            if fresh.any():
                self._trim()
        self._cond.notify_all()

    def _unwrap(self, counter16: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Unwrapped counters of a batch, relative to the newest so far, and which frames are late (or
        repeated); None for none late (the usual batch)."""
        c = counter16.astype(np.int64)
        prev = np.empty_like(c)
        prev[0] = (self._last % COUNTER_MODULO) if self._last is not None else c[0] - 1
        prev[1:] = c[:-1]
        delta = np.subtract(c, prev, out=prev)
        delta %= COUNTER_MODULO
        base = self._last if self._last is not None else int(c[0]) - 1
        # In order (gaps allowed) when every step is in 1 .. COUNTER_MODULO - REORDER_WINDOW - 1.
        if delta.size and int(delta.min()) > 0 and int(delta.max()) < COUNTER_MODULO - REORDER_WINDOW:
            np.cumsum(delta, out=delta)
            delta += base
            return delta, None
        out = np.empty_like(c)
        late = np.zeros(c.size, bool)
        newest = base
        for i, value in enumerate(c.tolist()):
            d = (value - newest) % COUNTER_MODULO
            if 0 < d < COUNTER_MODULO - REORDER_WINDOW:
                newest += d
                out[i] = newest
            else:  # d == 0 (a repeat of the newest) or a little behind it
                out[i] = newest - ((COUNTER_MODULO - d) % COUNTER_MODULO)
                late[i] = True
        return out, late

    def _keep_late(self, counters: np.ndarray, accel: np.ndarray, gyro: np.ndarray, temp: np.ndarray) -> None:
        """Late frames go back in their place unless they are repeats of frames already here."""
        seen = np.zeros(counters.size, bool)
        lo = int(counters.min())
        for ch in reversed(self._chunks):
            seen |= np.isin(counters, ch[0])
            if ch[0][0] <= lo:
                break
        for ch in self._late:
            seen |= np.isin(counters, ch[0])
        _, first = np.unique(counters, return_index=True)  # a frame repeated within the batch counts once
        once = np.zeros(counters.size, bool)
        once[first] = True
        keep = ~seen & once
        dup = int((~keep).sum())
        if dup:
            self.duplicates += dup
            log.debug("%s: %d repeated frame(s) dropped", self.name, dup)
        if keep.any():
            self._late.append((counters[keep], accel[keep], gyro[keep], temp[keep]))
            self.reordered += int(keep.sum())
            self.frames_received += int(keep.sum())
            log.debug("%s: %d frame(s) arrived out of order, put back in place", self.name, int(keep.sum()))

    def _trim(self) -> None:
        oldest_needed = min(self._open_records, default=None)
        while len(self._chunks) > 1 and self._buffered - self._chunks[0][0].size >= self.keep_frames:
            if oldest_needed is not None and self._chunks[0][0][-1] > oldest_needed:
                break
            self._buffered -= self._chunks.pop(0)[0].size
        if self._late:
            first = self._chunks[0][0][0]
            self._late = [ch for ch in self._late if ch[0].max() >= first]

    # --- the Imu interface ------------------------------------------------------------------

    def restart_stream(self) -> None:
        """Forget buffered frames and counter history (after the IMU was power-cycled)."""
        log.debug("%s: stream restarted (IMU power-cycled)", self.name)
        with self._cond:
            self._drain_locked()
            self._chunks.clear()
            self._late.clear()
            self._buffered = 0
            self._last = None
            self._last_arrived16 = None
            self._open_records.clear()
            self._since_restart = (self.bytes_received, self.frames_received)

    def latest(self) -> ImuSample | None:
        """The newest frame; None when none has arrived yet. Bytes without a valid frame raise
        InstrumentProtocolError saying what arrived."""
        with self._cond:
            if self._caller_fed:
                self._drain_locked()  # no reader thread has parsed what is there
            if not self._chunks:
                self._check_stream()
                return None
            c, a, g, t = self._chunks[-1]
            ka, kg, kt = self.codec.scale
            return ImuSample(counter=int(c[-1]), accel_g=tuple((a[-1] * ka).tolist()),
                             gyro_dps=tuple((g[-1] * kg).tolist()), temp_c=float(t[-1]) * kt)

    def last_counter16(self) -> int | None:
        last = self._last
        return None if last is None else last % COUNTER_MODULO

    def _wait_s(self, timeout_s: float) -> float:
        """Real seconds a wait for frames may last: none on a caller-fed line (what is not there after a read
        cannot come while this thread waits), else the policy's (a dry run's frames come, however slow)."""
        return 0.0 if self._caller_fed else io_timeouts.wall_timeout(self.address, timeout_s)

    def wait_counter16(self, counter16: int, timeout_s: float) -> bool:
        """Wait until the frame with this 16-bit counter is the last parsed, in arrival order (dry-run barrier)."""
        wait_s = self._wait_s(timeout_s)
        with self._cond:
            if self._ser is None and self._running:
                self._reopen_locked()  # a dry run's lost line: reopened now, or at a later barrier
            self._drain_locked()
            return self._cond.wait_for(lambda: self._last_arrived16 == counter16, wait_s)

    def wait_received(self, n_bytes: int, timeout_s: float) -> bool:
        """Wait until `n_bytes` have arrived since this driver was made, all parsed (a dry run's barrier:
        the simulated IMU says how many it put on the line, frames or not)."""
        wait_s = self._wait_s(timeout_s)
        with self._cond:
            if self._ser is None and self._running:
                self._reopen_locked()  # a dry run's lost line: reopened now, or at a later barrier
            self._drain_locked()
            return self._cond.wait_for(lambda: self.bytes_received >= n_bytes, wait_s)

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
        if self._caller_fed:
            timeout_s = 0.0  # everything sent is read by the drain below: a missing frame stays missing
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
            parts = _chunks_between(self._chunks, start, end)
            late = [ch for ch in self._late if ch[0].max() > start and ch[0].min() <= end]
            if not parts and not late and self.bytes_received > self._since_restart[0]:
                self._check_stream()
        ka, kg, kt = self.codec.scale
        if parts and not late:
            # Chunks in counter order, counters ascending: the window is one slice of them.
            counter = np.concatenate([p[0] for p in parts]) if len(parts) > 1 else parts[0][0]
            lo, hi = (int(i) for i in np.searchsorted(counter, (start, end), side="right"))
            counter = counter[lo:hi].copy()
            accel = _window([p[1] for p in parts], lo, hi) * ka
            gyro = _window([p[2] for p in parts], lo, hi) * kg
            temp = _window([p[3] for p in parts], lo, hi) * kt
        elif parts or late:
            counter = np.concatenate([p[0] for p in parts + late])
            sel = (counter > start) & (counter <= end)
            counter = counter[sel]
            accel = np.concatenate([p[1] for p in parts + late])[sel] * ka
            gyro = np.concatenate([p[2] for p in parts + late])[sel] * kg
            temp = np.concatenate([p[3] for p in parts + late])[sel] * kt
            if late:  # late frames were kept apart: back in counter order
                order = np.argsort(counter, kind="stable")
                counter, accel, gyro, temp = counter[order], accel[order], gyro[order], temp[order]
        else:
            counter = np.zeros(0, np.int64)
            accel = gyro = np.zeros((0, 3))
            temp = np.zeros(0)
        log.debug("%s: record after counter %d: %d of %d frames, %d corrupt stretch(es)", self.name, start,
                  counter.size, n_frames, corrupt)
        return ImuRecord(counter=counter, accel_g=accel, gyro_dps=gyro, temp_c=temp, expected=n_frames,
                         dropped=n_frames - int(counter.size), corrupt=corrupt,
                         lsb=self.codec.lsb)


def _chunks_between(chunks: list[Chunk], start: int, end: int) -> list[Chunk]:
    """The chunks (in counter order, counters ascending in each) holding a counter in start+1 .. end: looked
    for from the newest back, stopping at the first that ends at or before `start` (the ones before it end
    earlier still), instead of testing all of the ~10 minutes kept."""
    found = []
    for ch in reversed(chunks):
        c = ch[0]
        if int(c[-1]) <= start:
            break
        if int(c[0]) <= end:
            found.append(ch)
    found.reverse()
    return found


def _window(arrays: list[np.ndarray], lo: int, hi: int) -> np.ndarray:
    """Rows lo:hi of the arrays stacked (only the chunks that hold them are joined)."""
    if len(arrays) == 1:
        return arrays[0][lo:hi]
    return np.concatenate(arrays)[lo:hi]
