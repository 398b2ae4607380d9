"""Xsens MTi Xbus: exact bytes from the documented layout and a recorded MTi-300 payload, and the driver
against the simulated IMU over a socket and a pty."""

import math
import struct

import numpy as np
import pytest

from labrunner.drivers.xsens_mti import XBUS, XbusDecoder, XsensMtiImu
from labrunner.sims.imu_stream import ImuStreamSim
from labrunner.sims.links import PtyPort, TcpSerialPort

G = 9.80665

# MTData2 payload recorded from an MTi-300 ("XSens Golden Packets", packet example 4), 146 bytes:
# PacketCounter, SampleTimeFine, Quaternion, Acceleration, DeltaV, FreeAcceleration, RateOfTurn, DeltaQ,
# MagneticField, Temperature, BaroPressure, StatusWord. Decoded there as: counter 37261, SampleTimeFine
# 20332454, acc (-0.05550629, 9.81465530, 0.21842313) m/s^2, gyr (0.02131760, -0.00327826, -0.00163019)
# rad/s, temperature 37.625 C.
GOLDEN_PAYLOAD = bytes.fromhex(
    "10 20 02 91 8D 10 60 04 01 36 3F A6 20 10 10 3F 35 E0 42 3F 31 CD 15 BD 9F 49 DB BD A9 38 CF 40 20 0C"
    " BD 63 5A 90 41 1D 08 D4 3E 5F AA 50 40 10 0C B9 11 68 00 3C C9 01 00 3A 0F 7D 00 40 30 0C BC 3B 29 80"
    " 3C 35 FC 00 3C A4 6E 00 80 20 0C 3C AE A2 41 BB 56 D8 00 BA D5 AC 01 80 30 10 3F 80 00 00 37 DF 88 01"
    " B6 89 80 00 B6 08 C0 00 C0 20 0C BE FB FB F2 3F 33 C4 85 BF A0 A2 C1 08 10 04 42 16 80 00 30 10 04 00"
    " 01 86 E1 E0 20 04 00 40 00 03")
# Preamble, bus id, MID MTData2, LEN 0x92 (146); CS 0xDD makes 0xFF + 0x36 + 0x92 + sum(payload) + CS = 0 mod 256.
GOLDEN = bytes([0xFA, 0xFF, 0x36, 0x92]) + GOLDEN_PAYLOAD + bytes([0xDD])


def _message(payload: bytes, mid: int = 0x36) -> bytes:
    """One Xbus message by the documented rule (standard or extended length), independent of the codec."""
    head = bytes([0xFF, mid]) + (bytes([len(payload)]) if len(payload) < 255 else
                                 bytes([0xFF]) + struct.pack(">H", len(payload)))
    body = head + payload
    return b"\xfa" + body + bytes([(-sum(body)) & 0xFF])


def _sample(counter: int, acc=(0.0, 0.0, G), gyr=(0.0, 0.0, 0.0), temp: float | None = 25.0) -> bytes:
    p = b"\x10\x20\x02" + struct.pack(">H", counter)
    p += b"\x40\x20\x0c" + struct.pack(">3f", *acc)
    p += b"\x80\x20\x0c" + struct.pack(">3f", *gyr)
    if temp is not None:
        p += b"\x08\x10\x04" + struct.pack(">f", temp)
    return p


def test_the_recorded_mti300_message_decodes_to_its_documented_values():
    assert sum(GOLDEN[1:]) % 256 == 0
    dec = XbusDecoder()
    got = dec.feed(GOLDEN)
    assert len(got) == 1 and int(got.counter[0]) == 37261
    np.testing.assert_allclose(got.accel[0] * G, [-0.05550629, 9.81465530, 0.21842313], rtol=1e-6)
    np.testing.assert_allclose(np.radians(got.gyro[0]), [0.02131760, -0.00327826, -0.00163019], rtol=1e-5)
    assert got.temp[0] == 37.625
    # Quaternion, DeltaV, FreeAcceleration, DeltaQ, MagneticField, BaroPressure, StatusWord: skipped by size.
    assert dec.rejected.total() == 0 and dec.skipped_bytes == 0 and dec.corrupt == 0


def test_a_bad_checksum_is_counted_and_the_next_message_read():
    bad = bytearray(GOLDEN)
    bad[40] ^= 0x01  # one bit of the acceleration
    dec = XbusDecoder()
    got = dec.feed(bytes(bad) + _message(_sample(7)))
    assert got.counter.tolist() == [7]
    assert dec.rejected.bad_checksum == 1 and dec.skipped_bytes == len(GOLDEN)
    hit = bytearray(_message(_sample(8)))
    hit[-1] ^= 0xFF  # the checksum byte itself
    got = dec.feed(bytes(hit) + _message(_sample(9)))
    assert got.counter.tolist() == [9] and dec.rejected.bad_checksum == 2
    assert dec.corrupt == 1 + 3  # a stretch counts as frames of the last good size: 151 bytes are ~3 of 54


def test_extended_length_message():
    payload = _sample(300, acc=(1.0, -2.0, 3.0), gyr=(0.5, -0.25, 0.125), temp=-12.5) + b"\xa0\x10\xfa" + bytes(250)
    msg = _message(payload)
    assert msg[3] == 0xFF and msg[4:6] == struct.pack(">H", len(payload)) and len(payload) >= 255
    got = XbusDecoder().feed(msg)
    assert got.counter.tolist() == [300]
    np.testing.assert_allclose(got.accel[0], np.array([1.0, -2.0, 3.0]) / G)
    np.testing.assert_allclose(got.gyro[0], np.degrees([0.5, -0.25, 0.125]))
    assert got.temp[0] == -12.5


def test_unknown_packets_and_float64_are_read_by_size_and_format():
    # An unknown data id 0x7777 of 5 bytes before the sample, and the acceleration as float64 (format bits 3).
    p = b"\x77\x77\x05" + b"\xfa\xff\x36\x00\x01" + b"\x10\x20\x02\x00\x2a"
    p += b"\x40\x23\x18" + struct.pack(">3d", 0.1, 0.2, G) + b"\x80\x20\x0c" + struct.pack(">3f", 0, 0, 1.0)
    dec = XbusDecoder()
    got = dec.feed(_message(p))
    assert got.counter.tolist() == [42] and got.accel[0, 2] == pytest.approx(1.0)
    assert got.gyro[0, 2] == pytest.approx(math.degrees(1.0), rel=1e-6)
    assert math.isnan(got.temp[0])  # no temperature yet
    got = dec.feed(_message(_sample(43, temp=30.0)) + _message(_sample(44, temp=None)))
    assert got.temp.tolist() == [30.0, 30.0]  # a message without temperature keeps the last one
    assert dec.rejected.total() == 0


def test_resync_after_garbage_however_the_bytes_are_split():
    garbage = b"\x00\xfa\xff\x36\x05\x01\x02\xfa\xfa\xff\xff\x13\x99" * 3
    stream = garbage + b"".join(_message(_sample(k)) for k in range(10)) + garbage + _message(_sample(10))
    for step in (1, 5, 17, 64, len(stream)):
        dec = XbusDecoder()
        counters = []
        for i in range(0, len(stream), step):
            counters += dec.feed(stream[i:i + step]).counter.tolist()
        assert counters == list(range(11)), step
        assert dec.corrupt == 2 and dec.skipped_bytes == 2 * len(garbage), step


def test_a_truncated_message_is_dropped_and_the_next_one_read():
    cut = _message(_sample(5))[:30]  # the line dropped mid-message
    dec = XbusDecoder()
    got = dec.feed(cut + _message(_sample(6)) + _message(_sample(7)))
    assert got.counter.tolist() == [6, 7]
    assert dec.skipped_bytes == 30


def test_impossible_lengths_and_a_payload_that_does_not_parse_are_counted():
    huge = b"\xfa\xff\x36\xff\x7f\xff" + bytes(20)  # 32767 bytes announced: not waited for
    broken = _message(b"\x10\x20\x02\x00")  # the counter's value is one byte short
    no_counter = _message(_sample(1)[5:])
    dec = XbusDecoder()
    got = dec.feed(huge + broken + no_counter + _message(_sample(9)))
    assert got.counter.tolist() == [9]
    assert dec.rejected.bad_length == 2 and dec.rejected.other == {"without packet counter": 1}


def test_codec_round_trip_is_float32():
    n = 5
    acc = np.tile([0.01, -0.02, 1.0], (n, 1))
    gyr = np.tile([0.5, 100.0, -3.0], (n, 1))
    raw = XBUS.encode(np.arange(65534, 65534 + n), acc, gyr, np.full(n, 21.5), t_s=np.arange(n) * 0.02)
    assert len(raw) == n * XBUS.frame_size and raw[:4] == b"\xfa\xff\x36\x31"
    got = XbusDecoder().feed(raw)
    assert got.counter.tolist() == [65534, 65535, 0, 1, 2]
    np.testing.assert_allclose(got.accel, acc, rtol=1e-6)
    np.testing.assert_allclose(got.gyro, gyr, rtol=1e-6)
    assert struct.unpack(">I", raw[12:16])[0] == 0 and struct.unpack(">I", raw[54 + 12:54 + 16])[0] == 200


@pytest.fixture(params=["tcp", "pty"])
def xsens_stream(request, world, clock):
    port = TcpSerialPort() if request.param == "tcp" else PtyPort()
    sim = ImuStreamSim(world, clock, port, rate_hz=50.0, seed=1, codec=XBUS)
    drv = XsensMtiImu(port.url, rate_hz=50.0)
    drv.connect()
    if isinstance(port, TcpSerialPort):
        assert port.wait_connected(2.0)
    clock.add_listener(sim.emit_until)
    clock.add_barrier(lambda: sim.last_sent_counter is None or drv.wait_counter16(sim.last_sent_counter, 5.0))
    yield drv, sim, clock
    drv.close()
    sim.close()
    port.close()


def test_driver_reads_the_simulated_mti(xsens_stream, world):
    drv, sim, clock = xsens_stream
    clock.sleep(10.0)
    start = drv.begin_record()
    sim.faults.corrupt_frames = 3
    clock.sleep(60.0)
    rec = drv.end_record(start, 3000, timeout_s=1.0)
    assert rec.lsb is None  # float32 on the wire: stored as floats
    assert rec.dropped == 3 and rec.corrupt == 3 and len(rec) == 2997
    assert np.all(np.diff(rec.counter) >= 1) and rec.counter[-1] == start + 3000
    assert rec.accel_g.mean(axis=0)[2] == pytest.approx(1.0, abs=0.05)  # z up, in g
    assert rec.temp_c.mean() == pytest.approx(world.imu_temperature_at(np.array([clock.now()]))[0], abs=0.5)
    assert drv._decoder.rejected.bad_checksum >= 1
