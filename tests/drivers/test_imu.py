"""The IMU stream driver against the simulated IMU, over TCP and a pty, with damaged streams."""

import numpy as np
import pytest

from labrunner.drivers.imu_frames import FRAME_SIZE, FrameDecoder
from labrunner.drivers.imu_serial import SerialImu
from labrunner.sims.imu_stream import ImuStreamSim
from labrunner.sims.links import PtyPort, TcpSerialPort


@pytest.fixture(params=["tcp", "pty"])
def stream(request, world, clock):
    port = TcpSerialPort() if request.param == "tcp" else PtyPort()
    sim = ImuStreamSim(world, clock, port, rate_hz=50.0, seed=1)
    drv = SerialImu(port.url, rate_hz=50.0)
    drv.connect()
    if isinstance(port, TcpSerialPort):
        assert port.wait_connected(2.0)
    clock.add_listener(sim.emit_until)
    clock.add_barrier(lambda: sim.last_sent_counter is None or drv.wait_counter16(sim.last_sent_counter, 1.0))
    yield drv, sim, port, clock
    drv.close()
    sim.close()
    port.close()


def test_records_are_consecutive_frames_in_physical_units(stream, world):
    drv, sim, port, clock = stream
    clock.sleep(10.0)
    start = drv.begin_record()
    clock.sleep(60.0)
    rec = drv.end_record(start, 3000, timeout_s=1.0)
    assert len(rec) == 3000 and rec.dropped == 0 and rec.corrupt == 0
    assert np.array_equal(rec.counter, np.arange(start + 1, start + 3001))
    assert rec.accel_g.mean(axis=0)[2] == pytest.approx(1.0, abs=0.05)  # z up: about +1 g
    assert rec.temp_c.mean() == pytest.approx(world.imu_temperature_at(np.array([clock.now()]))[0], abs=0.5)
    assert drv.latest().counter == start + 3000


def test_corrupt_and_missing_frames_are_counted_and_the_stream_resyncs(stream):
    drv, sim, port, clock = stream
    clock.sleep(1.0)
    start = drv.begin_record()
    sim.faults.corrupt_frames = 7
    sim.faults.skip_frames = 4
    clock.sleep(60.0)
    rec = drv.end_record(start, 3000, timeout_s=0.2)
    assert rec.dropped == 11 and len(rec) == 2989
    assert rec.corrupt == 7
    start = drv.begin_record()
    clock.sleep(10.0)
    assert drv.end_record(start, 500, timeout_s=0.2).dropped == 0  # back in step


def test_stream_stall_is_seen_as_dropped_frames(stream):
    drv, sim, port, clock = stream
    clock.sleep(1.0)
    start = drv.begin_record()
    sim.faults.stall_until = clock.now() + 20.0
    clock.sleep(60.0)
    rec = drv.end_record(start, 3000, timeout_s=0.2)
    assert rec.dropped == pytest.approx(1000, abs=1)


def test_counter_wraps_without_losing_order(stream):
    drv, sim, port, clock = stream
    clock.sleep(1400.0)  # 70 000 frames: past the 16-bit counter
    start = drv.begin_record()
    clock.sleep(2.0)
    rec = drv.end_record(start, 100, timeout_s=0.5)
    assert start > 65536 and np.array_equal(rec.counter, np.arange(start + 1, start + 101))


def test_link_that_disappears_comes_back():
    events = []
    port = TcpSerialPort()
    drv = SerialImu(port.url, rate_hz=50.0, reopen_s=0.05, on_event=lambda k, m: events.append(k))
    drv.connect()
    try:
        assert port.wait_connected(2.0)
        port.disconnect()
        import time
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and "imu_link_restored" not in events:
            time.sleep(0.05)
        assert events[:2] == ["imu_link_lost", "imu_link_restored"]
        assert port.wait_connected(2.0)
    finally:
        drv.close()
        port.close()


def test_decoder_counts_a_corrupt_stretch_once_however_bytes_arrive():
    from labrunner.drivers.imu_frames import encode_frames

    n = 50
    raw = bytearray(encode_frames(np.arange(n), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n)))
    raw[10 * FRAME_SIZE: 13 * FRAME_SIZE] = bytes(3 * FRAME_SIZE)  # three frames wiped
    for step in (1, 7, 64, len(raw)):
        dec = FrameDecoder()
        got = sum(len(dec.feed(bytes(raw[i:i + step]))) for i in range(0, len(raw), step))
        assert got == n - 3 and dec.corrupt == 3, step


@pytest.fixture
def raw_line():
    """A driver on a socket line the test writes exact bytes to."""
    port = TcpSerialPort()
    drv = SerialImu(port.url, rate_hz=50.0)
    drv.connect()
    assert port.wait_connected(2.0)
    yield drv, port
    drv.close()
    port.close()


def _frames(counters):
    from labrunner.drivers.imu_frames import encode_frames

    n = len(counters)
    return encode_frames(np.asarray(counters), np.tile([0.0, 0.0, 1.0], (n, 1)), np.zeros((n, 3)), np.full(n, 25.0))


def test_a_stream_of_only_bad_frames_says_what_arrived(raw_line):
    import time

    from labrunner.drivers.errors import InstrumentProtocolError

    drv, port = raw_line
    bad = bytearray(_frames(range(40)))
    for k in range(40):
        bad[k * FRAME_SIZE + 18] ^= 0x5A  # every CRC wrong
    data = bytes(bad) + b"\x00\x11\x22" * 50  # and line noise
    port.write(data)
    deadline = time.monotonic() + 5.0
    while drv.bytes_received < len(data) and time.monotonic() < deadline:
        time.sleep(0.01)
    with pytest.raises(InstrumentProtocolError) as err:
        drv.latest()
    message = str(err.value)
    assert f"{len(data)} bytes received, 0 valid labrunner_frame frame(s)" in message
    # The last 19 bytes may still begin a frame: not skipped yet.
    assert "rejected: 40 bad checksum" in message and f"skipped {len(data) - (FRAME_SIZE - 1)} byte(s)" in message
    start = drv.begin_record()
    with pytest.raises(InstrumentProtocolError, match="no valid frame"):
        drv.end_record(start, 10, timeout_s=0.1)


def test_out_of_order_and_repeated_frames_do_not_cost_the_record(raw_line):
    drv, port = raw_line
    port.write(_frames([0]))
    assert drv.wait_counter16(0, 2.0)
    start = drv.begin_record()
    order = list(range(1, 201))
    for i in range(3, 200, 20):  # 5 % of the frames one place late
        order[i], order[i + 1] = order[i + 1], order[i]
    order.insert(50, order[49])  # and one repeat
    order.insert(120, 117)  # and one from further back, already received
    port.write(_frames(order))
    assert drv.wait_counter16(order[-1], 2.0)
    rec = drv.end_record(start, 200, timeout_s=0.5)
    assert len(rec) == 200 and rec.dropped == 0
    assert np.array_equal(rec.counter, np.arange(1, 201))
    assert drv.reordered == 10 and drv.duplicates == 2
    assert drv.latest().counter == 200


def test_a_counter_far_behind_is_the_stream_running_on_not_a_late_frame(raw_line):
    drv, port = raw_line
    port.write(_frames([30000, 30001]))
    assert drv.wait_counter16(30001, 2.0)
    start = drv.begin_record()
    port.write(_frames([5, 6, 7]))  # an IMU reset without a restart_stream: read as a jump forward
    assert drv.wait_counter16(7, 2.0)
    assert drv.latest().counter > start and drv.duplicates == 0


def test_a_port_closed_under_the_reader_is_a_lost_link_not_a_dead_thread():
    # Another thread (a read that failed there) closed the port while the reader waited on it: pyserial's
    # socket:// then has no socket and `fileno()` raises AttributeError; the reader must carry on.
    import time

    events = []
    port = TcpSerialPort()
    drv = SerialImu(port.url, rate_hz=50.0, reopen_s=0.05, on_event=lambda k, m: events.append(k))
    drv.connect()
    try:
        assert port.wait_connected(2.0)
        drv._ser.close()  # behind the driver's back, as the failing read's cleanup did
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and "imu_link_restored" not in events:
            time.sleep(0.02)
        assert events[:2] == ["imu_link_lost", "imu_link_restored"]
        assert drv._thread is not None and drv._thread.is_alive()
        # Frames reach the driver again (once the port has taken the new connection).
        assert any(port.write(_frames([k])) and drv.wait_counter16(k, 0.1) for k in range(1, 40))
    finally:
        drv.close()
        port.close()


def test_a_simulated_imu_sending_only_corrupt_frames_is_reported_as_such():
    from labrunner.drivers.errors import InstrumentProtocolError
    from labrunner.fault_kinds import FaultKind
    from labrunner.lab import simulated_lab

    lab = simulated_lab(max_rate_dps=150.0)
    try:
        assert lab.sim is not None
        lab.sim.apply_fault(FaultKind.IMU_CORRUPT, count=10_000)
        lab.imu.connect()
        lab.clock.sleep(2.0)  # 100 frames, every one corrupted on the line
        with pytest.raises(InstrumentProtocolError) as err:
            lab.imu.latest()
        message = str(err.value)
        assert "no valid frame" in message and "bytes received, 0 valid labrunner_frame frame(s)" in message
        assert "bad checksum" in message and "resynchronisation skipped" in message
    finally:
        lab.close()
