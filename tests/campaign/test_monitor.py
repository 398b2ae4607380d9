"""Monitor rows: 1 s means of the IMU stream over a stretch of ramping or soaking."""

import numpy as np

from labrunner.clock import VirtualClock
from labrunner.drivers.protocols import ImuRecord
from labrunner.runner.monitor import ImuMonitor, average_block

from .fakes import FakeLab


def _record(counter, rate_hz=50.0):
    counter = np.asarray(counter, dtype=np.int64)
    n = counter.size
    accel = np.column_stack([counter * 1.0, np.zeros(n), np.ones(n)])
    return ImuRecord(counter=counter, accel_g=accel, gyro_dps=np.zeros((n, 3)), temp_c=counter / 100.0,
                     expected=n, dropped=0, corrupt=0)


def test_means_per_second_by_frame_counter():
    start = 99  # frames 100..249: three seconds at 50 Hz
    rec = _record(np.arange(100, 250))
    block = average_block(rec, start=start, t0_s=1000.0, rate_hz=50.0, average_s=1.0, run=2, orientation="y_up",
                          chamber=np.array([[1000.0, 20.0], [1003.0, 20.5]]))
    assert block is not None and block.kind == "monitor" and block.step_idx is None
    assert block.run == 2 and block.orientation == "y_up" and block.rate_hz == 1.0
    assert np.allclose(block.accel_g[:, 0], [124.5, 174.5, 224.5])  # mean counter of each second
    assert np.allclose(block.temp_c, [1.245, 1.745, 2.245])
    assert list(block.counter) == [0, 1, 2]
    # Row times are the mean times of their frames: frame 100 is at t0 + 1/50.
    assert block.t0_s == np.mean(1000.0 + np.arange(1, 51) / 50.0)
    assert block.chamber.shape == (2, 2) and block.table.tolist() == [[1000.0, 0.0]]


def test_missing_frames_make_fewer_rows_not_wrong_ones():
    rec = _record(np.r_[np.arange(100, 150), np.arange(200, 250)])  # the middle second is lost
    block = average_block(rec, start=99, t0_s=0.0, rate_hz=50.0, average_s=1.0, run=1, orientation="x_up",
                          chamber=np.zeros((0, 2)))
    assert block is not None and list(block.counter) == [0, 2]
    assert np.allclose(block.accel_g[:, 0], [124.5, 224.5])
    assert average_block(_record([]), start=99, t0_s=0.0, rate_hz=50.0, average_s=1.0, run=1,
                         orientation="x_up", chamber=np.zeros((0, 2))) is None


def test_imu_monitor_brackets_a_stretch_with_chamber_readings():
    lab = FakeLab(VirtualClock(start=100.0))
    lab.imu.connect()
    lab.imu.orientation = "z_down"
    mon = ImuMonitor(lab.imu, lab.chamber, lambda: lab.clock.now() - 100.0, average_s=2.0)
    lab.clock.sleep(5.0)
    w = mon.begin()
    lab.clock.sleep(10.0)
    block = mon.end(w, 10.0, timeout_s=0.5, run=1, orientation="z_down")
    assert block is not None and len(block) == 5  # 10 s in 2 s means
    assert np.allclose(block.accel_g, [0.0, 0.0, -1.0])
    assert block.chamber[:, 0].tolist() == [5.0, 15.0]
    assert [m for _, m, _ in lab.imu.calls] == ["connect", "begin_record", "end_record"]
    assert lab.imu.called("end_record")[0][1] == (w.start, 500)
