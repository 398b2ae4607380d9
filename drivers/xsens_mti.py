"""Xsens MTi over Xbus: the MT low-level protocol's MTData2 stream, decoded vectorised, and its encoder.

One Xbus message (every multi-byte field big-endian):

    PRE 0xFA | BID 0xFF | MID | LEN | [EXT_LEN hi lo, when LEN = 0xFF] | DATA (LEN bytes) | CS

The checksum makes the sum of every byte after the preamble (BID .. CS) 0 modulo 256. A LEN of
0xFF means the length is the 16-bit EXT_LEN that follows (payloads of 255 bytes or more).
MTData2 (MID 0x36) data is a sequence of packets: data id (2 bytes), size (1 byte), value. The
data id's top bits name the quantity, its lowest two bits the number format (0 float32, 1 fixed
point 12.20, 2 fixed point 16.32, 3 float64). This driver reads:

    0x1020  PacketCounter   uint16, +1 per sample, wraps
    0x1060  SampleTimeFine  uint32, 10 kHz ticks
    0x4020  Acceleration    3 x float, m/s^2 (converted to g: / 9.80665)
    0x8020  RateOfTurn      3 x float, rad/s (converted to deg/s)
    0x0810  Temperature     float, degC (a message without it keeps the last one read)

Packets of any other data id are skipped by their size. Messages other than MTData2 (acks,
errors) are consumed and counted. Bad checksums and impossible lengths are counted and the
decoder resynchronises on the next 0xFA 0xFF; a message cut off by a link drop is dropped.

Sources: Xsens "MT Low Level Communication Protocol Documentation" (message structure, extended
length, checksum, MTData2 data identifiers); ethz-asl/ethzasl_xsens_driver `nodes/mtdef.py`
(MID.MTData2 = 0x36, XDIGroup values) and `nodes/mtdevice.py` (`read_msg`: 0xFA 0xFF, LEN 255 then
a big-endian 16-bit length, `0xFF & sum(...)` over BID..CS; `parse_MTData2`: data id, size,
precision bits `data_id & 0x0003`, big-endian values). The tests decode a message built around
the MTData2 payload recorded from an MTi-300 (a public "XSens Golden Packets" note, its packet
example 4: counter 37261, temperature 37.625 C).

`XBUS` is the codec behind `XsensMtiImu`, the same reader as the project's own frame
(`drivers.imu_serial.SerialImu`); the simulated IMU encodes with it when a sim configuration says
`imu_format: xsens_mti`. The driver only listens: the MTi is configured (MT Manager or
SetOutputConfiguration) to stream these packets in measurement mode.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from labrunner.clock import Clock

from .builtin import LabrunnerImuSection
from .imu_frames import DecodedFrames, Rejections
from .imu_serial import SerialImu
from .registry import Driver, DriverOptions

log = logging.getLogger(__name__)

PREAMBLE = 0xFA
BUS_ID = 0xFF  # the master device
MID_MTDATA2 = 0x36
MID_ERROR = 0x42
EXTENDED = 0xFF  # LEN value announcing a 16-bit length
MAX_PAYLOAD = 2048  # longer announced payloads are garbage: waiting for them would stall the stream
STANDARD_GRAVITY = 9.80665  # m/s^2 per g
TICKS_PER_S = 10_000  # SampleTimeFine

XDI_PACKET_COUNTER = 0x1020
XDI_SAMPLE_TIME_FINE = 0x1060
XDI_ACCELERATION = 0x4020
XDI_RATE_OF_TURN = 0x8020
XDI_TEMPERATURE = 0x0810
XDI_TYPE_MASK = 0xFFF0  # what the packet holds; the low bits are coordinate system and number format
XDI_FORMAT_MASK = 0x0003
FLOAT32, FP1220, FP1632, FLOAT64 = 0, 1, 2, 3
FORMAT_WIDTH = {FLOAT32: 4, FP1220: 4, FP1632: 6, FLOAT64: 8}
# The packets the sim sends, in this order: 49 bytes of data, a 54-byte message.
SIM_LAYOUT = ((XDI_PACKET_COUNTER, 2), (XDI_SAMPLE_TIME_FINE, 4), (XDI_ACCELERATION, 12),
              (XDI_RATE_OF_TURN, 12), (XDI_TEMPERATURE, 4))
SIM_PAYLOAD = sum(3 + size for _, size in SIM_LAYOUT)
SIM_MESSAGE = 4 + SIM_PAYLOAD + 1


def checksum(body: bytes) -> int:
    """The CS byte for BID .. last data byte (`body`): the whole sum, CS included, is 0 mod 256."""
    return (-sum(body)) & 0xFF


def _be_uint(cols: np.ndarray) -> np.ndarray:
    """Big-endian unsigned integers from (M, k) bytes."""
    out = np.zeros(cols.shape[0], dtype=np.uint64)
    for j in range(cols.shape[1]):
        out = (out << np.uint64(8)) | cols[:, j].astype(np.uint64)
    return out


def _values(cols: np.ndarray, fmt: int, count: int) -> np.ndarray:
    """`count` numbers per row from (M, count * width) big-endian bytes in Xbus number format `fmt`."""
    m = cols.shape[0]
    width = FORMAT_WIDTH[fmt]
    cols = np.ascontiguousarray(cols).reshape(m * count, width)
    if fmt == FLOAT32:
        vals = cols.copy().view(">f4").astype(np.float64)
    elif fmt == FLOAT64:
        vals = cols.copy().view(">f8").astype(np.float64)
    elif fmt == FP1220:  # signed 32-bit, 20 fraction bits
        vals = cols.copy().view(">i4").astype(np.float64) / float(1 << 20)
    else:  # FP16.32: 32-bit fraction then signed 16-bit integer part
        frac = _be_uint(cols[:, :4]).astype(np.float64) / float(1 << 32)
        whole = cols[:, 4:6].copy().view(">i2").astype(np.float64)
        vals = whole[:, 0] + frac
    return vals.reshape(m, count)


@dataclass(frozen=True)
class _Packet:
    data_id: int
    offset: int  # in the payload, of the value (after id and size)
    size: int


def _layout(payload: np.ndarray) -> list[_Packet] | None:
    """The packets of one MTData2 payload; None when a packet runs past the end."""
    packets = []
    i, n = 0, payload.size
    while i < n:
        if i + 3 > n:
            return None
        did = (int(payload[i]) << 8) | int(payload[i + 1])
        size = int(payload[i + 2])
        if i + 3 + size > n:
            return None
        packets.append(_Packet(did, i + 3, size))
        i += 3 + size
    return packets


class XbusDecoder:
    """Stateful Xbus stream decoder (a `drivers.imu_frames.StreamDecoder`): MTData2 samples in g, deg/s, degC."""

    def __init__(self) -> None:
        self._tail = np.zeros(0, dtype=np.uint8)
        self._junk = 0  # junk bytes since the last good message, not yet counted as a corrupt stretch
        self._last_temp = math.nan
        self._typical = SIM_MESSAGE  # bytes of a good message: a junk stretch counts as this many frames
        self.frames = 0
        self.corrupt = 0
        self.skipped_bytes = 0
        self.other_messages = 0  # valid messages that are not MTData2
        self.rejected = Rejections()

    def drop_partial(self) -> None:
        self._tail = np.zeros(0, dtype=np.uint8)
        self._junk = 0

    def feed(self, data: bytes) -> DecodedFrames:
        new = np.frombuffer(data, dtype=np.uint8)
        buf = np.concatenate((self._tail, new)) if self._tail.size else new
        starts, lengths, header, keep_from = self._messages(buf)
        self._tail = buf[keep_from:].copy()

        # Junk: bytes before keep_from in no accepted message; a stretch counts once, when a good
        # message ends it, however the bytes were split across reads.
        skipped = int(keep_from - lengths.sum())
        corrupt = 0
        if starts.size:
            prev_end = np.concatenate(([0], starts[:-1] + lengths[:-1]))
            gaps = (starts - prev_end).astype(np.int64)
            gaps[0] += self._junk
            closed = gaps[gaps > 0]
            self._typical = int(lengths[-1])
            corrupt = int(np.maximum(1, np.rint(closed / self._typical)).sum())
            self._junk = int(keep_from - (starts[-1] + lengths[-1]))
        else:
            self._junk += skipped
        self.corrupt += corrupt
        self.skipped_bytes += skipped

        mids = buf[starts + 2] if starts.size else np.zeros(0, np.uint8)
        data_msgs = mids == MID_MTDATA2
        self.other_messages += int((~data_msgs).sum())
        if (mids == MID_ERROR).any():
            log.warning("xsens: the MTi sent %d error message(s)", int((mids == MID_ERROR).sum()))
        out = self._samples(buf, starts[data_msgs], lengths[data_msgs], header[data_msgs])
        counter, accel, gyro, temp = out
        self.frames += int(counter.size)
        return DecodedFrames(counter=counter, accel=accel, gyro=gyro, temp=temp, corrupt=corrupt,
                             skipped_bytes=skipped)

    def _messages(self, buf: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Accepted messages (start, total length, header length) in order, and where the kept tail begins."""
        n = int(buf.size)
        none = np.zeros(0, np.int64)
        if n < 2:
            return none, none, none, 0
        cand = np.flatnonzero((buf[:-1] == PREAMBLE) & (buf[1:] == BUS_ID)).astype(np.int64)
        # Header: LEN at +3; extended: EXT_LEN at +4, +5.
        has_len = cand + 4 <= n
        length_byte = np.full(cand.size, -1, np.int64)
        length_byte[has_len] = buf[cand[has_len] + 3]
        ext = length_byte == EXTENDED
        has_ext = ext & (cand + 6 <= n)
        payload = np.where(ext, -1, length_byte)
        payload[has_ext] = (buf[cand[has_ext] + 4].astype(np.int64) << 8) | buf[cand[has_ext] + 5]
        header = np.where(ext, 6, 4)
        total = header + payload + 1
        known = payload >= 0  # the whole header has arrived
        too_long = known & (payload > MAX_PAYLOAD)
        complete = known & ~too_long & (cand + total <= n)
        sums = np.concatenate(([0], np.cumsum(buf, dtype=np.int64)))
        ok = np.zeros(cand.size, bool)
        c = cand[complete]
        ok[complete] = (sums[c + total[complete]] - sums[c + 1]) % 256 == 0
        # Greedy in order: a valid message is taken when it begins after the previous one ended.
        idx = np.flatnonzero(ok)
        taken: list[int] = []
        end = 0
        if idx.size and np.all(cand[idx[1:]] >= cand[idx[:-1]] + total[idx[:-1]]):
            taken = idx.tolist()
            end = int(cand[idx[-1]] + total[idx[-1]])
        else:
            for i in idx.tolist():
                if cand[i] >= end:
                    taken.append(i)
                    end = int(cand[i] + total[i])
        t = np.asarray(taken, dtype=np.int64)
        # Count each rejected candidate once: complete ones here; incomplete ones stay in the tail.
        beyond = cand >= end
        pending = beyond & ~complete & ~too_long  # may still become a message: keep from the first
        keep_from = int(cand[pending][0]) if pending.any() else n
        if buf[-1] == PREAMBLE:
            keep_from = min(keep_from, n - 1)  # a preamble whose bus id has not arrived yet
        keep_from = max(keep_from, end)
        # A candidate inside a taken message is payload that happens to read 0xFA 0xFF, not a rejection.
        evaluated = cand < keep_from
        if t.size:
            j = np.searchsorted(cand[t], cand, side="right") - 1
            evaluated &= ~((j >= 0) & (cand < cand[t][np.maximum(j, 0)] + total[t][np.maximum(j, 0)]))
        self.rejected.bad_checksum += int((complete & ~ok & evaluated).sum())
        self.rejected.bad_length += int((too_long & evaluated).sum())
        if t.size == 0:
            return none, none, none, keep_from
        return cand[t], total[t], header[t], keep_from

    def _samples(self, buf: np.ndarray, starts: np.ndarray, totals: np.ndarray, headers: np.ndarray,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Decode MTData2 messages, grouped by packet layout (one template walked in Python per layout)."""
        m = starts.size
        counter = np.zeros(m, np.uint16)
        accel = np.zeros((m, 3))
        gyro = np.zeros((m, 3))
        temp = np.full(m, np.nan)
        good = np.zeros(m, bool)
        lengths = totals - headers - 1
        todo = np.ones(m, bool)
        while todo.any():
            first = int(np.flatnonzero(todo)[0])
            plen = int(lengths[first])
            same_len = todo & (lengths == plen)
            rows_idx = np.flatnonzero(same_len)
            rows = buf[(starts[rows_idx] + headers[rows_idx])[:, None] + np.arange(plen)]
            layout = _layout(rows[0])
            if layout is None:
                # The template's packets do not fit its length: every message whose bytes match it is bad.
                todo[first] = False
                self.rejected.bad_length += 1
                continue
            # The messages with exactly the template's ids and sizes share its layout.
            match = np.ones(rows_idx.size, bool)
            for p in layout:
                for k in (p.offset - 3, p.offset - 2, p.offset - 1):
                    match &= rows[:, k] == rows[0, k]
            sel, rows = rows_idx[match], rows[match]
            todo[sel] = False
            problem = self._fill(layout, rows, sel, counter, accel, gyro, temp)
            if problem:
                self.rejected.other[problem] = self.rejected.other.get(problem, 0) + sel.size
            else:
                good[sel] = True
        counter, accel, gyro, temp = counter[good], accel[good], gyro[good], temp[good]
        if temp.size:  # a message without temperature keeps the last one read
            filled = np.isfinite(temp)
            last = np.maximum.accumulate(np.where(filled, np.arange(temp.size), -1))
            prior = np.concatenate(([self._last_temp], temp))
            temp = prior[last + 1]
            self._last_temp = float(temp[-1])
        return counter, accel, gyro, temp

    def _fill(self, layout: list[_Packet], rows: np.ndarray, sel: np.ndarray, counter: np.ndarray,
              accel: np.ndarray, gyro: np.ndarray, temp: np.ndarray) -> str | None:
        """Decode one layout's rows into the outputs; a reason when these messages cannot be used."""
        found = set()
        for p in layout:
            kind, fmt = p.data_id & XDI_TYPE_MASK, p.data_id & XDI_FORMAT_MASK
            cols = rows[:, p.offset:p.offset + p.size]
            if kind == XDI_PACKET_COUNTER:
                if p.size != 2:
                    return "bad packet counter size"
                counter[sel] = _be_uint(cols).astype(np.uint16)
            elif kind in (XDI_ACCELERATION, XDI_RATE_OF_TURN, XDI_TEMPERATURE):
                count = 1 if kind == XDI_TEMPERATURE else 3
                if p.size != count * FORMAT_WIDTH[fmt]:
                    return f"bad size of packet 0x{p.data_id:04X}"
                vals = _values(cols, fmt, count)
                if kind == XDI_ACCELERATION:
                    accel[sel] = vals / STANDARD_GRAVITY
                elif kind == XDI_RATE_OF_TURN:
                    gyro[sel] = np.degrees(vals)
                else:
                    temp[sel] = vals[:, 0]
            else:
                continue  # SampleTimeFine, orientation, status...: skipped by size
            found.add(kind)
        for kind, what in ((XDI_PACKET_COUNTER, "packet counter"), (XDI_ACCELERATION, "acceleration"),
                           (XDI_RATE_OF_TURN, "rate of turn")):
            if kind not in found:
                return f"without {what}"
        return None


class XbusCodec:
    """The Xsens MTData2 stream as a `drivers.imu_frames.FrameCodec` (values already in g, deg/s, degC)."""

    name = "xsens_mti"
    frame_size = SIM_MESSAGE
    scale = (1.0, 1.0, 1.0)
    lsb: tuple[float, float, float] | None = None  # float32 on the wire: stored as float32

    def decoder(self) -> XbusDecoder:
        return XbusDecoder()

    def encode(self, counter: np.ndarray, accel_g: np.ndarray, gyro_dps: np.ndarray, temp_c: np.ndarray,
               t_s: np.ndarray | None = None) -> bytes:
        """MTData2 messages with `SIM_LAYOUT` for N samples (`t_s`: seconds since power-on, for SampleTimeFine)."""
        counter = np.asarray(counter, dtype=np.int64)
        n = int(counter.size)
        t = np.asarray(t_s, dtype=float) if t_s is not None else np.zeros(n)
        dtype = np.dtype([("head", "u1", (4,)),
                          ("pc_id", ">u2"), ("pc_n", "u1"), ("pc", ">u2"),
                          ("stf_id", ">u2"), ("stf_n", "u1"), ("stf", ">u4"),
                          ("acc_id", ">u2"), ("acc_n", "u1"), ("acc", ">f4", (3,)),
                          ("gyr_id", ">u2"), ("gyr_n", "u1"), ("gyr", ">f4", (3,)),
                          ("tmp_id", ">u2"), ("tmp_n", "u1"), ("tmp", ">f4"),
                          ("cs", "u1")])
        assert dtype.itemsize == SIM_MESSAGE
        msg = np.zeros(n, dtype=dtype)
        msg["head"] = (PREAMBLE, BUS_ID, MID_MTDATA2, SIM_PAYLOAD)
        for name, (did, size) in zip(("pc", "stf", "acc", "gyr", "tmp"), SIM_LAYOUT):
            msg[f"{name}_id"], msg[f"{name}_n"] = did, size
        msg["pc"] = counter % (1 << 16)
        msg["stf"] = np.rint(t * TICKS_PER_S).astype(np.int64) % (1 << 32)
        msg["acc"] = np.asarray(accel_g, dtype=float) * STANDARD_GRAVITY
        msg["gyr"] = np.radians(np.asarray(gyro_dps, dtype=float))
        msg["tmp"] = np.asarray(temp_c, dtype=float)
        raw = msg.view(np.uint8).reshape(n, SIM_MESSAGE)
        msg["cs"] = (-raw[:, 1:-1].sum(axis=1, dtype=np.int64)) % 256
        return msg.tobytes()


XBUS = XbusCodec()


class XsensMtiImu(SerialImu):
    """An Xsens MTi streaming MTData2 over a serial line (implements `drivers.protocols.Imu`)."""

    def __init__(self, url: str, *, rate_hz: float = 100.0, baudrate: int = 115200, name: str = "imu",
                 keep_s: float = 600.0, reopen_s: float = 0.2,
                 on_event: Callable[[str, str], None] | None = None) -> None:
        super().__init__(url, rate_hz=rate_hz, baudrate=baudrate, name=name, keep_s=keep_s, reopen_s=reopen_s,
                         on_event=on_event, codec=XBUS)


class XsensMtiSection(LabrunnerImuSection):
    """A lab configuration's `imu:` section for `driver: xsens_mti` (the MTi's factory baud rate)."""

    baudrate: int = Field(115200, gt=0)
    rate_hz: float = Field(100.0, gt=0, le=10000)


def make_xsens_mti(section: XsensMtiSection, clock: Clock, options: DriverOptions) -> XsensMtiImu:
    return XsensMtiImu(section.port, rate_hz=section.rate_hz, baudrate=section.baudrate, name=options.name,
                       on_event=options.on_event)


#: The `labrunner.drivers` entry point `xsens_mti` (pyproject.toml).
XSENS_MTI = Driver("imu", make_xsens_mti, XsensMtiSection, "Xsens MTi, Xbus MTData2 (acceleration, rate of turn, "
                   "temperature, packet counter)")
