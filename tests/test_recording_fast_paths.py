"""The recording path's shortcuts give the bits of the formulas they stand for (issue 15): the frame encoder
against a field-by-field encoding, the table's newest-segment rate against the general piecewise formula,
the baseline error without its zero reference axes against the full sum, and a record cut as one slice of
the in-order chunks against masking every frame received."""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.drivers import imu_frames as F
from labrunner.drivers.imu_serial import SerialImu
from labrunner.imu.baseline import thermal_powers
from labrunner.imu.model import default_imu_model
from labrunner.sims.links import MemoryPort
from labrunner.sims.table_plant import TablePlant


def _encode_field_by_field(counter: np.ndarray, accel: np.ndarray, gyro: np.ndarray, temp: np.ndarray) -> bytes:
    """The frame as the structured dtype spells it, each field rounded and saturated on its own."""
    n = counter.size
    frames = np.zeros(n, dtype=F.FRAME_DTYPE)
    frames["sync"] = int.from_bytes(F.SYNC, "little")
    frames["counter"] = counter % F.COUNTER_MODULO
    frames["accel"] = F.to_counts(accel, F.ACCEL_LSB_G)
    frames["gyro"] = F.to_counts(gyro, F.GYRO_LSB_DPS)
    frames["temp"] = F.to_counts(temp, F.TEMP_LSB_C)
    raw = frames.view(np.uint8).reshape(n, F.FRAME_SIZE)
    frames["crc"] = [F.crc16(r[2:18].tobytes()) for r in raw]
    return frames.tobytes()


@pytest.mark.parametrize("n", [1, 2, 25, 1000])
def test_encoder_equals_a_field_by_field_encoding(n: int) -> None:
    rng = np.random.default_rng(n)
    accel = rng.normal(0, 2, (n, 3))
    gyro = rng.normal(0, 200, (n, 3))
    temp = rng.normal(25, 30, n)
    # Saturation both ways, halves that round to even, and a negative zero.
    edge = np.array([40.0, -40.0, 0.0005, -0.0015, -0.0, 32.7675])
    accel[:, 0] = np.resize(edge, n)
    gyro[:, 2] = np.resize(edge * 8.75, n)
    temp[::3] = 400.0
    counter = np.arange(n) + 65530
    assert F.encode_frames(counter, accel, gyro, temp) == _encode_field_by_field(counter, accel, gyro, temp)


def _general_rate(plant: TablePlant, times: np.ndarray, ripple: bool = True) -> np.ndarray:
    """The piecewise formula over every kept segment (the rate_at of before the shortcut)."""
    i = np.clip(np.searchsorted(plant._seg_t0, times, side="right") - 1, 0, None)
    t0, r0, r1, t1 = plant._seg_t0[i], plant._seg_r0[i], plant._seg_r1[i], plant._seg_t1[i]
    rate = r0 + (r1 - r0) * np.clip((times - t0) / np.maximum(t1 - t0, 1e-12), 0.0, 1.0)
    return rate * (1.0 + 0.5 * plant.p.rate_accuracy * np.sin(np.deg2rad(rate) * times)) if ripple else rate


def test_rate_in_the_newest_segment_equals_the_general_formula() -> None:
    plant = TablePlant(seed=3)
    rng = np.random.default_rng(8)
    t, seen_ramp, seen_rest = 0.0, 0, 0
    for rate in [10.0, -100.0, 0.0, 0.5, 0.0, 100.0, -0.25, 1000.0, 0.0]:
        plant.command(t, rate)
        for size in (1, 25, 250, 1000):  # chunks from the command on: through the ramp, then held
            times = t + rng.uniform(0.0, 0.05) + np.arange(size) / 50.0
            assert np.array_equal(plant.rate_at(times), _general_rate(plant, times))
            assert np.array_equal(plant.rate_at(times, ripple=False), _general_rate(plant, times, ripple=False))
            seen_ramp += int(times[0] < plant._seg_t1[-1])
            seen_rest += int(plant.commanded_dps == 0 and times[0] >= plant._seg_t1[-1])
            t = float(times[-1])
        back = np.linspace(t - 30.0, t, 400)  # reaching back over earlier segments: the general path
        assert np.array_equal(plant.rate_at(back), _general_rate(plant, back))
        t += 1.0
    assert seen_ramp and seen_rest


def test_baseline_without_its_zero_axes_equals_the_full_sum() -> None:
    model = default_imu_model()
    rng = np.random.default_rng(2)
    temp = rng.uniform(-30, 60, 700)
    for ref in (np.tile([0.0, 0.0, -1.0], (700, 1)), rng.normal(0, 100, (700, 1)) * [[0.0, 1.0, 0.0]],
                rng.normal(0, 1, (700, 3)), np.zeros((700, 3))):
        for triad in (model.accel, model.gyro):
            p = thermal_powers(temp)
            full = p @ triad.bias.T
            for j in range(3):
                full += (p @ triad.scale[:, j, :].T) * ref[:, j: j + 1]
            assert np.array_equal(triad.error(temp, ref), full)
    assert np.array_equal(thermal_powers(temp), np.stack([np.ones_like(temp), temp - 25.0, (temp - 25.0) ** 2,
                                                          (temp - 25.0) * (temp - 25.0) * (temp - 25.0)], axis=-1))


def test_a_record_cut_from_in_order_chunks_equals_the_frames_masked() -> None:
    port = MemoryPort("imu")
    drv = SerialImu(port.url, rate_hz=50.0)
    drv.connect()
    try:
        rng = np.random.default_rng(4)
        sent = np.arange(1, 9001)
        sent = sent[rng.random(sent.size) > 0.02]  # frames lost here and there: counter gaps
        accel = rng.normal(0, 1, (sent.size, 3))
        gyro = rng.normal(0, 50, (sent.size, 3))
        temp = rng.normal(25, 5, sent.size)
        starts = [drv.begin_record()]
        for lo, hi in [(0, 25), (25, 300), (300, 1300), (1300, 2800), (2800, sent.size)]:
            port.write(F.encode_frames(sent[lo:hi], accel[lo:hi], gyro[lo:hi], temp[lo:hi]))
            starts.append(drv.begin_record())
        got_counter = np.concatenate([c[0] for c in drv._chunks])
        assert np.array_equal(got_counter, sent) and len(drv._chunks) >= 5  # windows across chunks
        for start, n in [(starts[0], 3000), (starts[1], 1), (starts[2], 2999), (starts[3], 1500), (37, 5000),
                         (int(sent[-1]) - 10, 3000)]:
            rec = drv.end_record(start, n, timeout_s=0.0)
            if start < 0:  # begun before any frame: the window starts at the first frame that came
                start = int(sent[0]) - 1
            sel = (sent > start) & (sent <= start + n)
            assert np.array_equal(rec.counter, sent[sel])
            assert np.array_equal(rec.accel_g, np.round(accel[sel] / F.ACCEL_LSB_G).astype(np.int16) * F.ACCEL_LSB_G)
            assert np.array_equal(rec.temp_c, np.round(temp[sel] / F.TEMP_LSB_C).astype(np.int16) * F.TEMP_LSB_C)
            assert rec.dropped == n - int(sel.sum())
    finally:
        drv.close()
        port.close()


def _dry_session(on_demand: bool) -> tuple[bytes, np.ndarray, list[np.ndarray]]:
    """A dry run's lab (memory links, virtual clock, the real drivers) through soaks, jogs, records at
    uneven times, a remount and then a fault: the IMU's bytes on the line, the model's outputs before
    rounding, and what the driver's records held."""
    import dataclasses

    from labrunner.clock import VirtualClock
    from labrunner.fault_kinds import FaultKind
    from labrunner.lab import build_drivers, lab_config_from_dict
    from labrunner.sims.lab import SimLab
    from labrunner.sims.world import SimLabConfig

    clock = VirtualClock(start=1000.0)
    sim = SimLab(dataclasses.replace(SimLabConfig(seed=7), orientation="x_up"), clock, link="memory",
                 imu_on_demand=on_demand)
    chamber, table, imu = build_drivers(lab_config_from_dict(sim.lab_config()), clock, max_rate_dps=150.0)
    clock.add_barrier(lambda: sim.settle_imu(imu))
    sent: list[bytes] = []
    write = sim.imu_port.write
    sim.imu_port.write = lambda data: (sent.append(bytes(data)), write(data))[1]  # type: ignore[method-assign]
    outs: list[np.ndarray] = []
    model = sim.world.model
    simulate = model.simulate

    def tap(*args, **kwargs):  # type: ignore[no-untyped-def]
        out, state = simulate(*args, **kwargs)
        outs.append(out.copy())
        return out, state

    model.simulate = tap  # type: ignore[method-assign]
    records = []
    try:
        for c in (chamber, table, imu):
            c.connect()
        chamber.set_setpoint(40.0)
        for k, rate in enumerate([0.0, 25.0, -60.0, 100.0]):
            for _ in range(3):  # a soak's polls, each a monitor stretch
                start = imu.begin_record()
                clock.sleep(30.0 + 0.37 * k)
                chamber.read_temperature()
                records.append(imu.end_record(start, 1500, 0.0).gyro_dps)
                imu.latest()
            table.jog(rate)
            for _ in range(7):
                table.status()
                clock.sleep(0.5)
            clock.sleep(5.0)
            start = imu.begin_record()
            for _ in range(3):
                clock.sleep(20.0 + 0.013 * k)
                chamber.read_temperature()
                table.velocity()
            records.append(imu.end_record(start, 3000, 0.0).accel_g)
            if k == 1:
                sim.power_off()
                clock.sleep(300.0)
                sim.remount("y_down")
                imu.restart_stream()
        sim.apply_fault(FaultKind.IMU_CORRUPT, count=40)
        start = imu.begin_record()
        clock.sleep(20.0)
        records.append(imu.end_record(start, 1000, 0.0).temp_c)
    finally:
        for c in (imu, table, chamber):
            c.close()
        sim.close()
    return b"".join(sent), np.concatenate(outs), records


def test_frames_made_on_demand_equal_frames_sent_at_every_advance() -> None:
    eager_bytes, eager_out, eager_records = _dry_session(on_demand=False)
    lazy_bytes, lazy_out, lazy_records = _dry_session(on_demand=True)
    assert len(eager_bytes) > 400_000 and eager_bytes == lazy_bytes
    assert np.array_equal(eager_out, lazy_out)  # the model's outputs, bit for bit, before rounding
    assert len(eager_records) == len(lazy_records) == 17
    for a, b in zip(eager_records, lazy_records, strict=True):
        assert np.array_equal(a, b)
