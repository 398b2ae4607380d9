"""The IMU's binary frame format, and vectorised encoding and resynchronising decoding.

One frame, 20 bytes, little-endian:

    offset  size  field
    0       2     sync 0xA5 0x5A
    2       2     counter, uint16, +1 per frame, wraps
    4       6     accelerometer x y z, int16, 1 mg/LSB
    10      6     gyroscope x y z, int16, 8.75 mdeg/s/LSB
    16      2     temperature, int16, 0.01 degC/LSB
    18      2     CRC-16/CCITT-FALSE of bytes 2..17

The sims encode with `encode_frames`; the driver decodes with `FrameDecoder`, which
keeps the bytes of a frame split across reads and skips corrupt bytes.

`FrameCodec` is what the serial IMU reader (`drivers.imu_serial.SerialImu`) needs of a wire
format: a stream decoder, the scale from decoded values to g, deg/s and degC, and an encoder for
the simulator. `LABRUNNER_FRAME` is this 20-byte frame; `drivers.xsens_mti.XBUS` is the Xsens
MTi's Xbus MTData2 stream.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

SYNC = b"\xa5\x5a"
FRAME_SIZE = 20
ACCEL_LSB_G = 0.001
GYRO_LSB_DPS = 0.00875
TEMP_LSB_C = 0.01
COUNTER_MODULO = 1 << 16

FRAME_DTYPE = np.dtype(
    [("sync", "<u2"), ("counter", "<u2"), ("accel", "<i2", (3,)), ("gyro", "<i2", (3,)),
     ("temp", "<i2"), ("crc", "<u2")]
)
assert FRAME_DTYPE.itemsize == FRAME_SIZE
_SYNC_WORD = int.from_bytes(SYNC, "little")
_CRC_SPAN = slice(2, 18)


def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint16)
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table[i] = crc & 0xFFFF
    return table


_CRC_TABLE = _crc_table()


def _crc_table16() -> np.ndarray:
    """The register after 16 zero bits from each 16-bit value: two bytes per lookup (the register is 16 bits)."""
    v = np.arange(1 << 16, dtype=np.uint32)
    for _ in range(2):
        v = ((v << 8) & 0xFFFF) ^ _CRC_TABLE[(v >> 8) & 0xFF]
    return v.astype(np.uint16)


_CRC_TABLE16 = _crc_table16()


def _byteswap16(v: np.ndarray) -> np.ndarray:
    return ((v >> 8) | (v << 8)) & 0xFFFF


def _crc_table16_le() -> np.ndarray:
    """`_CRC_TABLE16` for a register kept byte-swapped, indexed by it xor a little-endian word: the bytes
    as they lie in memory, no swap per step. Kept uint16 (128 KB): in a dry run the table is cold at every
    chunk, and a wider one (an intp table needs no index conversion) measured slower there."""
    v = np.arange(1 << 16, dtype=np.int64)
    return _byteswap16(_CRC_TABLE16.astype(np.int64)[_byteswap16(v)]).astype(np.uint16)


_CRC_TABLE16_LE = _crc_table16_le()


def crc16_words(words: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of each row of a (N, K) array of little-endian 16-bit words (the row's 2K bytes
    in memory order, e.g. a frame's fields viewed as `<u2`), vectorised over rows, two bytes per lookup."""
    reg = np.full(words.shape[0], 0xFFFF, dtype=np.uint16)  # 0xFFFF is its own byte swap
    for j in range(words.shape[1]):
        np.bitwise_xor(reg, words[:, j], out=reg)
        reg = _CRC_TABLE16_LE.take(reg)  # the same lookup as indexing, ~20 % faster (the method: no wrapper)
    return (reg >> 8) | (reg << 8)  # uint16: the shift left drops the high byte


def crc16_rows(rows: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of each row of a (N, L) uint8 array, vectorised over rows (two bytes per step)."""
    n, width = rows.shape
    even = width - width % 2
    if even:
        r = rows[:, :even]
        if r.strides[1] != 1:
            r = np.ascontiguousarray(r)
        crc = crc16_words(r.view("<u2"))  # the words in memory order: byte j low, j+1 high
    else:
        crc = np.full(n, 0xFFFF, dtype=np.uint16)
    if width % 2:
        idx = ((crc >> 8) ^ rows[:, -1]) & 0xFF
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE[idx]
    return crc


def crc16(data: bytes) -> int:
    return int(crc16_rows(np.frombuffer(data, dtype=np.uint8)[None, :])[0])


def to_counts(values: np.ndarray, lsb: float) -> np.ndarray:
    """Round physical values to int16 counts, saturating like the sensor does."""
    return np.clip(np.rint(np.asarray(values, dtype=float) / lsb), -32768, 32767).astype(np.int16)


# The frame as ten little-endian 16-bit words: sync, counter, accel x y z, gyro x y z, temp, crc.
_WORDS = FRAME_SIZE // 2
_VALUE_WORDS = slice(2, 9)  # accel, gyro, temp: int16 counts
_CRC_WORDS = slice(1, 9)  # bytes 2..17
_VALUE_LSB = np.array([ACCEL_LSB_G] * 3 + [GYRO_LSB_DPS] * 3 + [TEMP_LSB_C])


def encode_frames(counter: np.ndarray, accel_g: np.ndarray, gyro_dps: np.ndarray, temp_c: np.ndarray) -> bytes:
    """Frames for N samples: counter (N,), accel (N,3) g, gyro (N,3) deg/s, temp (N,) degC."""
    n = int(np.asarray(counter).size)
    words = np.empty((n, _WORDS), dtype="<u2")  # the frame layout (FRAME_DTYPE), one row per frame
    words[:, 0] = _SYNC_WORD
    words[:, 1] = np.asarray(counter, dtype=np.int64) & (COUNTER_MODULO - 1)  # x mod 2**16, negatives too
    # The seven values as `to_counts` makes them, all at once: value / lsb, rounded, saturated, int16.
    # One row per value (7, n): an (n, 7) or (n, 3) block is a loop of 3 or 7 per frame in numpy, slow.
    counts = np.empty((7, n))
    counts[0:3] = np.asarray(accel_g, dtype=float).reshape(n, 3).T
    counts[3:6] = np.asarray(gyro_dps, dtype=float).reshape(n, 3).T
    counts[6] = np.asarray(temp_c, dtype=float).reshape(n)
    counts /= _VALUE_LSB[:, None]
    np.rint(counts, out=counts)
    np.clip(counts, -32768, 32767, out=counts)  # maximum then minimum, in one call
    values = words[:, _VALUE_WORDS].view("<i2")
    for j in range(7):
        np.copyto(values[:, j], counts[j], casting="unsafe")  # in range: the int16 itself
    words[:, 9] = crc16_words(words[:, _CRC_WORDS])
    return words.tobytes()


@dataclass
class DecodedFrames:
    """Frames decoded from one chunk of bytes (in the codec's units: `FrameCodec.scale` makes them physical)."""

    counter: np.ndarray  # uint16 as sent
    accel: np.ndarray  # (N, 3): int16 counts for this frame
    gyro: np.ndarray  # (N, 3)
    temp: np.ndarray  # (N,)
    corrupt: int  # corrupted stretches skipped (each at least one frame)
    skipped_bytes: int

    def __len__(self) -> int:
        return int(self.counter.size)


@dataclass
class Rejections:
    """Why bytes did not become frames, counted over a stream's life (for the message that says so)."""

    bad_checksum: int = 0  # a complete frame or message whose checksum did not match
    bad_length: int = 0  # a length field no valid message has, or a payload that does not parse
    other: dict[str, int] = field(default_factory=dict)  # codec-specific reasons (e.g. a message id)

    def total(self) -> int:
        return self.bad_checksum + self.bad_length + sum(self.other.values())

    def describe(self) -> str:
        parts = [f"{n} bad checksum" for n in [self.bad_checksum] if n]
        parts += [f"{n} bad length" for n in [self.bad_length] if n]
        parts += [f"{n} {why}" for why, n in sorted(self.other.items()) if n]
        return ", ".join(parts) or "none"


class StreamDecoder(Protocol):
    """Feed bytes as they arrive, get whole valid frames; bad bytes are skipped and counted."""

    frames: int
    corrupt: int
    skipped_bytes: int
    rejected: Rejections

    def feed(self, data: bytes) -> DecodedFrames: ...
    def drop_partial(self) -> None: ...


class FrameCodec(Protocol):
    """A wire format for `SerialImu`: how its bytes decode, what its values mean, how a sim encodes them."""

    name: str
    frame_size: int  # bytes of one encoded frame as the sim sends it (fault injection corrupts inside one)
    scale: tuple[float, float, float]  # decoded accel, gyro, temp times this: g, deg/s, degC
    lsb: tuple[float, float, float] | None  # the same when values are whole counts (stored as int16), else None

    def decoder(self) -> StreamDecoder: ...
    def encode(self, counter: np.ndarray, accel_g: np.ndarray, gyro_dps: np.ndarray, temp_c: np.ndarray,
               t_s: np.ndarray | None = None) -> bytes:
        """Frames for N samples: counter (N,), accel (N, 3) g, gyro (N, 3) deg/s, temp (N,) degC, and their
        times since power-on (N,) s for formats that carry a timestamp."""
        ...


class FrameDecoder:
    """Stateful stream decoder: feed bytes, get whole valid frames."""

    def __init__(self) -> None:
        self._tail = np.zeros(0, dtype=np.uint8)
        self._junk = 0  # junk bytes since the last good frame, not yet counted as a corrupt stretch
        self.frames = 0
        self.corrupt = 0
        self.skipped_bytes = 0
        self.rejected = Rejections()

    def drop_partial(self) -> None:
        """Forget a partial frame (the stream restarts mid-frame, e.g. after the link dropped)."""
        self._tail = np.zeros(0, dtype=np.uint8)
        self._junk = 0

    def feed(self, data: bytes) -> DecodedFrames:
        buf = np.concatenate((self._tail, np.frombuffer(data, dtype=np.uint8))) if self._tail.size else \
            np.frombuffer(data, dtype=np.uint8)
        n = buf.size
        aligned = self._feed_aligned(buf, None)
        if aligned is not None:
            return aligned
        starts = _sync_positions(buf)
        complete = starts[starts + FRAME_SIZE <= n]
        if complete.size:
            rows = buf[complete[:, None] + np.arange(FRAME_SIZE)]
            crc = rows[:, 18].astype(np.uint16) | (rows[:, 19].astype(np.uint16) << 8)
            ok = crc16_rows(rows[:, _CRC_SPAN]) == crc
            self.rejected.bad_checksum += int((~ok).sum())
            accepted = _non_overlapping(complete[ok])
            rows = rows[ok][np.isin(complete[ok], accepted)] if accepted.size != ok.sum() else rows[ok]
        else:
            accepted = np.zeros(0, dtype=np.int64)
            rows = np.zeros((0, FRAME_SIZE), dtype=np.uint8)

        # Keep what may be the start of a frame not yet complete.
        end_used = int(accepted[-1]) + FRAME_SIZE if accepted.size else 0
        keep_from = max(end_used, n - (FRAME_SIZE - 1))
        partial = starts[(starts >= end_used) & (starts + FRAME_SIZE > n)]
        if partial.size:
            keep_from = min(keep_from, int(partial[0]))
        keep_from = max(keep_from, end_used)
        self._tail = buf[keep_from:].copy()

        # Bytes between accepted frames, and before keep_from, were junk. A junk stretch is
        # counted once, when a good frame ends it, however the bytes were split across reads.
        covered = np.zeros(keep_from, dtype=bool)
        if accepted.size:
            idx = (accepted[:, None] + np.arange(FRAME_SIZE)).ravel()
            covered[idx[idx < keep_from]] = True
        skipped = int(keep_from - covered.sum())
        corrupt = 0
        pending = self._junk
        if skipped or (pending and accepted.size):
            starts_at = accepted if accepted.size else np.zeros(0, np.int64)
            prev_end = np.concatenate(([0], starts_at[:-1] + FRAME_SIZE)) if starts_at.size else np.zeros(0, np.int64)
            gaps = starts_at - prev_end  # junk bytes just before each accepted frame
            if gaps.size:
                gaps = gaps.astype(np.int64)
                gaps[0] += pending
                closed = gaps[gaps > 0]
                corrupt = int(np.maximum(1, np.rint(closed / FRAME_SIZE)).sum())
                pending = int(keep_from - (starts_at[-1] + FRAME_SIZE))
            else:
                pending += skipped
        self._junk = pending
        frames = np.frombuffer(rows.tobytes(), dtype=FRAME_DTYPE) if len(rows) else np.zeros(0, FRAME_DTYPE)
        self.frames += len(frames)
        self.corrupt += corrupt
        self.skipped_bytes += skipped
        return DecodedFrames(
            counter=frames["counter"].copy(), accel=frames["accel"].copy(), gyro=frames["gyro"].copy(),
            temp=frames["temp"].copy(), corrupt=corrupt, skipped_bytes=skipped,
        )


    def _feed_aligned(self, buf: np.ndarray, starts: np.ndarray | None) -> DecodedFrames | None:
        """The usual case at a glance: whole valid frames back to back from the first byte, then at
        most a partial one. Their bytes are read as the frame layout in place (no gather per frame);
        the sync words found inside payloads are checked as the general path checks them, so the
        result and every count are the general path's. None when anything else is there (a corrupt
        or misaligned frame, junk pending from the last read, a payload that happens to hold a
        valid frame): the general path decides."""
        m = buf.size // FRAME_SIZE
        if m == 0 or self._junk:
            return None
        frames = buf[:m * FRAME_SIZE].view(FRAME_DTYPE)
        words = buf[:m * FRAME_SIZE].view("<u2").reshape(m, _WORDS)
        if not np.all(words[:, 0] == _SYNC_WORD):
            return None
        if not np.array_equal(crc16_words(words[:, _CRC_WORDS]), words[:, 9]):
            return None
        # Sync bytes inside payloads (or in the partial frame after the last whole one): candidate
        # frames the general path checks and rejects; one that passed would need its judgement.
        # The m frame starts are sync positions, and so is the partial frame's start when it has its
        # sync word: any more, and some lie inside (the usual stream has none: nothing to sift).
        end = m * FRAME_SIZE
        at_starts = m + int(buf.size >= end + 2 and buf[end] == SYNC[0] and buf[end + 1] == SYNC[1])
        # The sync positions (`starts`, found here when not given) are only needed when there are more than
        # at the frames' starts: counted first, located only then.
        if (starts.size if starts is not None else _count_syncs(buf)) == at_starts:
            inner = np.zeros(0, dtype=np.int64)
        else:
            starts = _sync_positions(buf) if starts is None else starts
            inner = starts[(starts % FRAME_SIZE != 0) & (starts + FRAME_SIZE <= buf.size)]
        if inner.size:
            cand = buf[inner[:, None] + np.arange(FRAME_SIZE)]
            crc = cand[:, 18].astype(np.uint16) | (cand[:, 19].astype(np.uint16) << 8)
            if np.any(crc16_rows(cand[:, _CRC_SPAN]) == crc):
                return None
            self.rejected.bad_checksum += int(inner.size)
        self._tail = buf[m * FRAME_SIZE:].copy()
        self.frames += m
        return DecodedFrames(counter=frames["counter"].copy(), accel=frames["accel"].copy(),
                             gyro=frames["gyro"].copy(), temp=frames["temp"].copy(), corrupt=0, skipped_bytes=0)


class LabrunnerFrameCodec:
    """The project's own 20-byte frame (this module) as a `FrameCodec`."""

    name = "labrunner_frame"
    frame_size = FRAME_SIZE
    scale = (ACCEL_LSB_G, GYRO_LSB_DPS, TEMP_LSB_C)
    lsb: tuple[float, float, float] | None = (ACCEL_LSB_G, GYRO_LSB_DPS, TEMP_LSB_C)

    def decoder(self) -> FrameDecoder:
        return FrameDecoder()

    def encode(self, counter: np.ndarray, accel_g: np.ndarray, gyro_dps: np.ndarray, temp_c: np.ndarray,
               t_s: np.ndarray | None = None) -> bytes:
        return encode_frames(counter, accel_g, gyro_dps, temp_c)  # the frame has no timestamp


LABRUNNER_FRAME = LabrunnerFrameCodec()


def _sync_positions(buf: np.ndarray) -> np.ndarray:
    """Offsets i where buf[i], buf[i+1] are the sync bytes, ascending: the first byte's positions (one pass
    over the buffer), then the second byte checked there."""
    first = np.flatnonzero(buf[:-1] == SYNC[0]) if buf.size >= 2 else np.zeros(0, np.int64)
    return first[buf[first + 1] == SYNC[1]]


def _count_syncs(buf: np.ndarray) -> int:
    """How many offsets `_sync_positions` finds: the sync word among the 16-bit words at even offsets, then
    at odd ones (two compares of half the bytes' count each, no positions made)."""
    even = buf.size // 2
    odd = (buf.size - 1) // 2
    return int(np.count_nonzero(buf[:2 * even].view("<u2") == _SYNC_WORD)
               + np.count_nonzero(buf[1:1 + 2 * odd].view("<u2") == _SYNC_WORD))


def _non_overlapping(starts: np.ndarray) -> np.ndarray:
    """Greedy in order: keep a frame start only if it begins after the previous kept frame."""
    if starts.size <= 1 or np.all(np.diff(starts) >= FRAME_SIZE):
        return starts
    kept = [int(starts[0])]
    for s in starts[1:]:
        if s >= kept[-1] + FRAME_SIZE:
            kept.append(int(s))
    return np.asarray(kept, dtype=np.int64)


def unwrap_counter(counter16: np.ndarray, last: int | None) -> np.ndarray:
    """Unwrap uint16 counters into an increasing int64 sequence continuing from `last`.

    A repeated counter (delta 0) maps to the same value, so the caller can drop it.
    """
    c = np.asarray(counter16, dtype=np.int64)
    if c.size == 0:
        return c
    prev = np.empty_like(c)
    prev[0] = (last % COUNTER_MODULO) if last is not None else c[0] - 1
    prev[1:] = c[:-1]
    delta = (c - prev) % COUNTER_MODULO
    base = (last if last is not None else c[0] - 1)
    return base + np.cumsum(delta)
