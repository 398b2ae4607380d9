"""The dry run's fast paths give what the general code gives (issue 15): the frame decoder's aligned path
against its general path on the same bytes (clean, split anywhere, corrupted, junk, sync words inside
payloads), the two-bytes-per-step CRC against the byte-wise definition, the chamber plant integrated in
one call or in pieces, and the monitor's bin means against a plain per-bin mean."""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.drivers import imu_frames as F
from labrunner.drivers.imu_frames import FRAME_SIZE, FrameDecoder, crc16, encode_frames
from labrunner.drivers.protocols import ImuRecord
from labrunner.runner.monitor import average_block
from labrunner.sims.chamber_plant import ChamberParams, ChamberPlant


class GeneralDecoder(FrameDecoder):
    """The decoder with its aligned fast path switched off: every feed takes the general path."""

    def _feed_aligned(self, buf, starts):  # type: ignore[no-untyped-def]
        return None


def _stream(n: int, seed: int, sync_in_payload: bool = False) -> bytes:
    rng = np.random.default_rng(seed)
    accel = rng.normal(0, 1, (n, 3))
    gyro = rng.normal(0, 50, (n, 3))
    if sync_in_payload:  # int16 0x5AA5 is the bytes A5 5A: a sync word inside the payload
        accel[::7, 1] = 0x5AA5 * F.ACCEL_LSB_G
        gyro[::11, 2] = 0x5AA5 * F.GYRO_LSB_DPS
    counter = np.arange(n) + (0x5AA5 - 5 if sync_in_payload else 0)
    return encode_frames(counter, accel, gyro, rng.normal(25, 10, n))


def _decode_all(dec: FrameDecoder, data: bytes, cuts: list[int]) -> tuple:
    parts, prev = [], 0
    for cut in [*cuts, len(data)]:
        parts.append(dec.feed(data[prev:cut]))
        prev = cut

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in parts])

    return (cat("counter"), cat("accel"), cat("gyro"), cat("temp"), [p.corrupt for p in parts],
            [p.skipped_bytes for p in parts], dec.frames, dec.corrupt, dec.skipped_bytes,
            dec.rejected.bad_checksum, dec.rejected.bad_length, dec._tail.tobytes())


def _same(a: tuple, b: tuple) -> None:
    for x, y in zip(a, b, strict=True):
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y)
        else:
            assert x == y


def _cuts(rng: np.random.Generator, size: int, k: int) -> list[int]:
    return sorted(int(c) for c in rng.choice(np.arange(1, size), size=k, replace=False))


@pytest.mark.parametrize("sync_in_payload", [False, True])
@pytest.mark.parametrize("seed", range(4))
def test_aligned_path_equals_general_path_on_clean_streams(seed: int, sync_in_payload: bool) -> None:
    data = _stream(3000, seed, sync_in_payload)
    rng = np.random.default_rng(100 + seed)
    cuts = [FRAME_SIZE * 700, FRAME_SIZE * 1500] if seed == 0 else _cuts(rng, len(data), 9)
    fast = FrameDecoder()
    _same(_decode_all(fast, data, cuts), _decode_all(GeneralDecoder(), data, cuts))
    assert fast.frames == 3000
    if sync_in_payload:
        assert fast.rejected.bad_checksum > 0  # the payload's sync words were seen and rejected


@pytest.mark.parametrize("seed", range(6))
def test_aligned_path_equals_general_path_on_damaged_streams(seed: int) -> None:
    """Corrupt bytes, junk between frames, a frame cut short: the decoder resynchronises exactly as before."""
    rng = np.random.default_rng(seed)
    raw = bytearray(_stream(2000, seed, sync_in_payload=seed % 2 == 1))
    for pos in rng.integers(0, len(raw), size=5):  # flipped bytes (CRC failures, lost sync words)
        raw[pos] ^= int(rng.integers(1, 256))
    at = int(rng.integers(1, 1999)) * FRAME_SIZE
    raw[at:at] = bytes(rng.integers(0, 256, size=int(rng.integers(1, 60)), dtype=np.uint8))  # junk
    cut = int(rng.integers(1, 1999)) * FRAME_SIZE
    del raw[cut + 3:cut + 11]  # a frame cut short
    data = bytes(raw)
    cuts = _cuts(rng, len(data), 12)
    fast, general = FrameDecoder(), GeneralDecoder()
    _same(_decode_all(fast, data, cuts), _decode_all(general, data, cuts))
    assert fast.corrupt > 0 and fast.skipped_bytes > 0


def test_aligned_path_is_taken_on_a_clean_stream() -> None:
    """The fast path is what decodes an intact stream (else the tests above compare the general path with itself)."""
    data = _stream(500, 9)
    taken = []

    class Spy(FrameDecoder):
        def _feed_aligned(self, buf, starts):  # type: ignore[no-untyped-def]
            out = super()._feed_aligned(buf, starts)
            taken.append(out is not None)
            return out

    dec = Spy()
    dec.feed(data[:FRAME_SIZE * 200 + 7])
    dec.feed(data[FRAME_SIZE * 200 + 7:])
    assert taken == [True, True]
    assert dec.frames == 500


def test_crc_two_bytes_per_step_equals_the_bytewise_definition() -> None:
    def bytewise(data: bytes) -> int:
        crc = 0xFFFF
        for b in data:
            crc ^= b << 8
            for _ in range(8):
                crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        return crc

    rng = np.random.default_rng(3)
    for width in (1, 2, 15, 16, 17, 52):
        rows = rng.integers(0, 256, size=(40, width), dtype=np.uint8)
        assert F.crc16_rows(rows).tolist() == [bytewise(r.tobytes()) for r in rows]
    assert crc16(b"123456789") == 0x29B1


def test_chamber_plant_in_one_call_or_step_by_step_is_the_same_to_the_bit() -> None:
    """The plant's state does not depend on how its integration is split (dry runs advance it in
    pieces of any length), through saturation, anti-windup and a failed compressor."""
    one, steps = ChamberPlant(ChamberParams(), seed=4), ChamberPlant(ChamberParams(), seed=4)
    for plant in (one, steps):
        plant.set_setpoint(-30.0)
    rows = one.run_steps(2500, 1.0)
    by_step = [steps.run_steps(1, 1.0)[0] for _ in range(2500)]
    assert rows == by_step
    for plant in (one, steps):
        plant.compressor_failed = True
        plant.set_setpoint(60.0)
    one.advance_to(one.t + 1200.0)
    for _ in range(1200):
        steps._step(1.0)
    assert (one.t, one.air_c, one.integral, one.output_pct) == (steps.t, steps.air_c, steps.integral,
                                                                 steps.output_pct)
    assert min(a for _, a in rows) < -25.0  # it did cool down: the comparison covered the whole dynamics


def test_monitor_bin_means_equal_plain_means_with_gaps() -> None:
    rng = np.random.default_rng(5)
    n = 1500
    counter = np.arange(1, n + 1)
    keep = rng.random(n) > 0.1  # frames lost here and there
    counter = counter[keep]
    accel, gyro, temp = rng.normal(size=(counter.size, 3)), rng.normal(size=(counter.size, 3)), rng.normal(
        size=counter.size)
    rec = ImuRecord(counter=counter, accel_g=accel, gyro_dps=gyro, temp_c=temp, expected=n,
                    dropped=n - counter.size, corrupt=0, lsb=None)
    block = average_block(rec, start=0, t0_s=100.0, rate_hz=50.0, average_s=1.0, run=1, orientation="z_up",
                          chamber=np.zeros((2, 2)))
    assert block is not None
    bins = (counter - 1) // 50
    for i, b in enumerate(np.unique(bins)):
        sel = bins == b
        np.testing.assert_allclose(block.accel_g[i], accel[sel].mean(axis=0), rtol=0, atol=1e-12)
        np.testing.assert_allclose(block.temp_c[i], temp[sel].mean(), rtol=0, atol=1e-12)
    assert block.counter.size == np.unique(bins).size
