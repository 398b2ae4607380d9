"""The IMU frame codec and the campaign CSV format."""

import numpy as np
import pandas as pd
import pytest

from labrunner.campaign_csv import COLUMNS, CampaignDataError, read_campaign, write_campaign
from labrunner.drivers.imu_frames import FRAME_SIZE, FrameDecoder, crc16, encode_frames, unwrap_counter


def _frames(n=200, start=0):
    c = np.arange(start, start + n)
    accel = np.column_stack([np.full(n, 0.012), np.full(n, -0.003), np.full(n, 1.004)])
    gyro = np.column_stack([np.full(n, 0.5), np.full(n, -100.0), np.full(n, 3.0)])
    return encode_frames(c, accel, gyro, np.full(n, -24.87))


def test_crc_is_ccitt_false():
    assert crc16(b"123456789") == 0x29B1


def test_exact_bytes_of_one_frame():
    raw = encode_frames(np.array([0x1234]), np.array([[0.001, -0.002, 1.0]]), np.array([[0.00875, 0.0, -0.0175]]),
                        np.array([25.0]))
    assert raw[:2] == b"\xa5\x5a"
    assert raw[2:4] == b"\x34\x12"
    assert raw[4:10] == (1).to_bytes(2, "little", signed=True) + (-2).to_bytes(2, "little", signed=True) \
        + (1000).to_bytes(2, "little", signed=True)
    assert raw[10:16] == (1).to_bytes(2, "little", signed=True) + b"\x00\x00" + (-2).to_bytes(2, "little", signed=True)
    assert raw[16:18] == (2500).to_bytes(2, "little", signed=True)
    assert int.from_bytes(raw[18:20], "little") == crc16(raw[2:18])


def test_decoder_handles_split_reads_and_saturation():
    raw = _frames(500)
    dec = FrameDecoder()
    got = [dec.feed(raw[i:i + 7]) for i in range(0, len(raw), 7)]
    counters = np.concatenate([g.counter for g in got])
    assert counters.tolist() == list(range(500))
    gyro = np.concatenate([g.gyro for g in got])
    assert gyro[0].tolist() == [57, -11429, 343]
    sat = encode_frames(np.array([0]), np.array([[40.0, -40.0, 0]]), np.zeros((1, 3)), np.array([0.0]))
    assert FrameDecoder().feed(sat).accel[0].tolist() == [32767, -32768, 0]


def test_decoder_resynchronises_after_corruption_and_counts_it():
    raw = bytearray(_frames(100))
    # Edits from the end backwards so earlier offsets stay valid.
    raw[60 * FRAME_SIZE:60 * FRAME_SIZE] = b"garbage\xa5"  # junk inserted between frames
    del raw[40 * FRAME_SIZE + 2: 40 * FRAME_SIZE + 9]  # bytes lost mid-frame
    raw[20 * FRAME_SIZE + 4: 20 * FRAME_SIZE + 6] = b"\xa5\x5a"  # a false sync inside a corrupted frame
    raw[5 * FRAME_SIZE + 7] ^= 0x40  # a flipped bit: CRC fails
    dec = FrameDecoder()
    out = dec.feed(bytes(raw))
    lost = sorted(set(range(100)) - set(out.counter.tolist()))
    assert lost == [5, 20, 40]
    assert out.corrupt == 4 and dec.corrupt == 4
    assert out.skipped_bytes > 0


def test_counter_unwrap_across_wrap_and_gap():
    assert unwrap_counter(np.array([65534, 65535, 0, 3]), 65533).tolist() == [65534, 65535, 65536, 65539]
    assert unwrap_counter(np.array([7, 8]), None).tolist() == [7, 8]


def _campaign_frame(n=20):
    return pd.DataFrame({
        "t_s": np.arange(n, dtype=float), "run": 1, "orientation": "z_up", "chamber_c": 25.0, "imu_temp_c": 27.0,
        "table_rate_dps": 0.0, "ax_g": 0.0, "ay_g": 0.0, "az_g": 1.0, "gx_dps": 0.1, "gy_dps": 0.0, "gz_dps": 0.0,
    })


def test_campaign_csv_round_trip(tmp_path):
    frame = _campaign_frame()
    frame.loc[3, "chamber_c"] = np.nan  # allowed: no chamber reading
    path = tmp_path / "c.csv"
    write_campaign(frame, path)
    back = read_campaign(path)
    assert list(back.columns) == list(COLUMNS)
    assert np.isnan(back.chamber_c[3]) and back.az_g.tolist() == frame.az_g.tolist()


def _set(line: int, column: str, value: str):
    """A mutation of the CSV text: put `value` in `column` on file line `line` (1 = header)."""
    def mutate(text: str) -> str:
        lines = text.split("\n")
        cells = lines[line - 1].split(",")
        cells[COLUMNS.index(column)] = value
        lines[line - 1] = ",".join(cells)
        return "\n".join(lines)
    return mutate


@pytest.mark.parametrize("mutate, expect", [
    (lambda t: t.replace("gz_dps", "gz"), "missing column(s) gz_dps"),
    (_set(5, "orientation", "sideways"), ":5: column 'orientation': unknown orientation 'sideways'"),
    (_set(7, "imu_temp_c", "abc"), ":7: column 'imu_temp_c': 'abc' is not a number"),
    (_set(8, "imu_temp_c", ""), ":8: column 'imu_temp_c': value missing"),
    (_set(9, "gx_dps", "nan"), ":9: column 'gx_dps': value missing or not finite"),
    (_set(11, "t_s", "1"), ":11: column 't_s': time goes backwards within run 1"),
    (_set(6, "run", "1.5"), ":6: column 'run'"),
    (lambda t: t.split("\n")[0] + "\n", "no data rows"),
    (lambda t: "", "empty"),
])
def test_campaign_csv_errors_name_line_and_column(tmp_path, mutate, expect):
    path = tmp_path / "bad.csv"
    write_campaign(_campaign_frame(), path)
    path.write_text(mutate(path.read_text()))
    with pytest.raises(CampaignDataError) as info:
        read_campaign(path)
    assert expect in str(info.value)
    assert str(path) in str(info.value)
