"""The campaign CSV writer (issue 15, target 3): `labrunner export` streams a store block by block and
writes what pandas' `to_csv(float_format="%.9g")` of the whole frame wrote, byte for byte; `write_campaign`
of a frame too. The reference in every comparison is pandas itself, run on the same data."""

from __future__ import annotations

import io
import re
import sqlite3
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from labrunner import campaign_csv
from labrunner.campaign_csv import export_campaign, read_campaign, write_campaign
from labrunner.cli import main
from labrunner.errors import UserError
from labrunner.procedure import parse_procedure
from labrunner.store import SampleBlock, Store
from tests.campaign.conftest import TINY

LSB = (0.001, 0.00875, 0.0078125)  # not all powers of two: counts x LSB is not a short decimal


def _record(step: int, t0: float, n: int, rng: np.random.Generator, **fields: object) -> SampleBlock:
    counts = rng.integers(-40, 40, size=(n, 7)) + rng.integers(-30000, 30000, size=7)  # few distinct per column
    counts[0, :] = [32767, -32768, 0, 1, -1, 32767, -32768]  # the int16 extremes
    block = SampleBlock(kind="record", step_idx=step, run=1 + step // 3, orientation="x_up", t0_s=t0, rate_hz=50.0,
                        counter=np.arange(n) + 7, accel_g=counts[:, :3] * LSB[0], gyro_dps=counts[:, 3:6] * LSB[1],
                        temp_c=counts[:, 6] * LSB[2],
                        chamber=np.array([[t0, 15.0], [t0 + n / 100, 15.37], [t0 + n / 50, 15.2]]),
                        table=np.array([[t0, -50.0], [t0 + 1, -50.0000013]]), lsb=LSB)
    for name, value in fields.items():
        setattr(block, name, value)
    return block


def _monitor(t0: float, n: int, rng: np.random.Generator, orientation: str = "x_up") -> SampleBlock:
    values = rng.normal(0, 1, size=(n, 7)).astype(np.float32)  # stored as float32: every value distinct
    values[0, :3] = [-0.0, 1e-5, 123456789.0]  # '%.9g' of these: '-0', '1.00000001e-05' (float32), '123456792'
    return SampleBlock(kind="monitor", step_idx=None, run=1, orientation=orientation, t0_s=t0, rate_hz=1.0,
                       counter=np.arange(n), accel_g=values[:, :3], gyro_dps=values[:, 3:6], temp_c=values[:, 6],
                       chamber=np.array([[t0, 20.0], [t0 + n, 21.0]]), table=np.zeros((0, 2)))


@pytest.fixture(scope="module")
def store_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Records (int16 counts) and monitor stretches (float32) that overlap them in time, with awkward cells."""
    db = tmp_path_factory.mktemp("export") / "awkward.db"
    p = parse_procedure(TINY, "tiny.yaml")
    rng = np.random.default_rng(15)
    with Store.create(db) as s:
        cid = s.new_campaign(name=p.name, procedure_text=p.text, procedure_path=None, procedure_sha256=p.sha256,
                             lab_config={}, mode="sim", sim_config={}, clock_t0=0.0, plan=p.steps())
        blocks = [
            _record(0, 100.0, 300, rng),
            _record(1, 200.0, 250, rng, chamber=np.zeros((0, 2))),  # no chamber: empty cells
            _record(2, 300.0, 200, rng, chamber=np.array([[300.0, 15.0], [302.0, np.nan], [304.0, 16.0]])),
            _record(3, 400.0, 120, rng, lsb=None, orientation="z_down"),  # a float32 record
            _record(4, 500.0, 150, rng, table=np.array([[500.0, 0.0]])),  # one reading: a constant column
        ]
        for b in blocks:
            s.commit_record(cid, b, dropped=0, corrupt=0, t_end=b.t0_s + 10, event_message="x")
        s.save_monitor(cid, _monitor(90.0, 30, rng))  # before the first record, ends inside it
        s.save_monitor(cid, _monitor(101.0, 4, rng, orientation='tilt, "50%"'))  # quoted, a '%' in the text
        s.save_monitor(cid, _monitor(303.0, 3, rng))  # inside a record: rows interleave, times tie (303, 304)
        s.save_monitor(cid, _monitor(700.0, 5, rng))
    return db


def _pandas_csv(store_path: Path, include_monitor: bool) -> str:
    """The writer before the stream: the whole frame, formatted by pandas."""
    with Store.open_existing(store_path) as s:
        frame = s.samples_frame(s.resolve(None), include_monitor=include_monitor)
    return frame.to_csv(index=False, float_format="%.9g", lineterminator="\n")


@pytest.mark.parametrize("include_monitor", [False, True])
@pytest.mark.parametrize("chunk_rows", [1 << 16, 7])  # 7: blocks split in chunks, merges across chunk ends
def test_the_stream_writes_what_pandas_wrote(store_path: Path, include_monitor: bool, chunk_rows: int,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    expected = _pandas_csv(store_path, include_monitor)
    # The awkward cells are there: empty (no chamber), and with the monitor rows a quoted label, -0 and
    # exponents.
    assert ",," in expected
    assert (',"tilt, ""50%""",' in expected) == include_monitor
    assert (",-0," in expected and "e-0" in expected and ",123456792," in expected) == include_monitor
    monkeypatch.setattr(campaign_csv, "CHUNK_ROWS", chunk_rows)
    out = io.StringIO()
    with Store.open_existing(store_path) as s:
        rows = export_campaign(s, s.resolve(None), out, include_monitor=include_monitor)
    assert out.getvalue() == expected
    assert rows == expected.count("\n") - 1


def test_the_command_writes_the_file_and_read_campaign_reads_it(store_path: Path, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    csv = tmp_path / "out.csv"
    assert main(["export", str(store_path), "--csv", str(csv)]) == 0
    assert "wrote 1,020 rows of campaign 1" in capsys.readouterr().err
    assert csv.read_text() == _pandas_csv(store_path, include_monitor=False)
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]  # the temporary file was renamed, none is left
    frame = read_campaign(csv)
    assert len(frame) == 1020 and frame["chamber_c"].isna().sum() > 250


def test_a_failed_export_leaves_the_old_file_and_no_partial_one(store_path: Path, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    db = tmp_path / "short.db"
    db.write_bytes(store_path.read_bytes())
    with sqlite3.connect(db) as conn:  # the last record's accelerometer blob cut short: read after 4 good blocks
        conn.execute("UPDATE sample_blocks SET accel_g = substr(accel_g, 1, 10) WHERE step_idx = 4")
    csv = tmp_path / "out.csv"
    csv.write_text("precious\n")
    assert main(["export", str(db), "--csv", str(csv), "--force"]) == 2
    assert "step 4" in capsys.readouterr().err
    assert csv.read_text() == "precious\n"
    assert {p.name for p in tmp_path.iterdir()} - {"short.db", "short.db-wal", "short.db-shm"} == {"out.csv"}


def test_a_campaign_without_samples_writes_nothing(tmp_path: Path) -> None:
    db = tmp_path / "empty.db"
    p = parse_procedure(TINY, "tiny.yaml")
    with Store.create(db) as s:
        cid = s.new_campaign(name=p.name, procedure_text=p.text, procedure_path=None, procedure_sha256=p.sha256,
                             lab_config={}, mode="sim", sim_config={}, clock_t0=0.0, plan=p.steps())
        with pytest.raises(UserError, match="campaign 1 has no recorded samples to export"):
            export_campaign(s, cid, tmp_path / "out.csv")
    assert not (tmp_path / "out.csv").exists()


def test_write_campaign_of_a_frame_writes_what_pandas_writes(tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(4)
    n = 50
    frame = pd.DataFrame({
        "t_s": np.arange(n) * 0.02 + 1e5, "run": np.repeat([1, 2], n // 2),
        "orientation": pd.Categorical(rng.choice(["x_up", "z_down", "a,b"], n)),
        "chamber_c": np.where(rng.random(n) < 0.3, np.nan, rng.normal(20, 5, n)),
        "imu_temp_c": rng.normal(20, 5, n).astype(np.float32), "table_rate_dps": np.full(n, -0.0),
        **{c: rng.normal(0, 1e-3, n) * 10.0 ** rng.integers(-8, 12, n) for c in campaign_csv.OUTPUT_COLUMNS},
        "power_on": (np.arange(n) % 25 == 0).astype(np.int8),
    })
    frame.loc[3, "ax_g"] = np.inf
    monkeypatch.setattr(campaign_csv, "CHUNK_ROWS", 16)
    for variant in (frame, frame.assign(orientation=frame["orientation"].astype(object)),
                    frame.assign(run=frame["run"].astype("Int64"))):  # nullable integers: written by pandas itself
        path = tmp_path / "w.csv"
        write_campaign(variant, path)
        assert path.read_text() == variant.to_csv(index=False, float_format="%.9g", lineterminator="\n")


def test_a_clean_csv_is_read_by_the_typed_reader_alone(store_path: Path, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    # The cell-by-cell text reader is ~4x slower: a file labrunner wrote, and one with spaces around its
    # cells (the reader no longer skips initial spaces), never need it.
    csv = tmp_path / "out.csv"
    with Store.open_existing(store_path) as s:
        export_campaign(s, s.resolve(None), csv)
    spaced = tmp_path / "spaced.csv"
    spaced.write_text(re.sub(r"([^,\n]+)", r" \1  ", csv.read_text()))  # every cell but the empty ones

    def no_text_reading(path: Path, label: str) -> pd.DataFrame:
        raise AssertionError(f"{path} was read as text")

    expected = read_campaign(csv)
    monkeypatch.setattr(campaign_csv, "_read_text", no_text_reading)
    pd.testing.assert_frame_equal(read_campaign(csv), expected)
    pd.testing.assert_frame_equal(read_campaign(spaced), expected)


def test_a_stored_block_decodes_slices_as_the_whole_block_decodes(store_path: Path) -> None:
    with Store.open_existing(store_path) as s:
        cid = s.resolve(None)
        kinds = ("record", "monitor")
        pairs = list(zip(s.blocks(cid, kinds), s.stored_blocks(cid, kinds), strict=True))
    assert {b.lsb is None for b, _ in pairs} == {True, False}  # int16 and float32 blocks
    for whole, stored in pairs:
        n = len(whole)
        assert (len(stored), stored.lsb, stored.t0_s, stored.orientation) == (n, whole.lsb, whole.t0_s,
                                                                              whole.orientation)
        np.testing.assert_array_equal(stored.chamber, whole.chamber)
        np.testing.assert_array_equal(stored.table, whole.table)
        for lo, hi in ((0, n), (3, min(n, 40)), (n - 1, n)):
            assert stored.times(lo, hi).tobytes() == whole.times()[lo:hi].tobytes()  # bit for bit
            for column in ("accel_g", "gyro_dps", "temp_c"):
                assert stored.values(column, lo, hi).tobytes() == getattr(whole, column)[lo:hi].tobytes()
                if whole.lsb is not None:
                    which = ("accel_g", "gyro_dps", "temp_c").index(column)
                    counts = stored.counts(column, lo, hi)
                    assert counts.dtype == np.int16
                    assert (counts * whole.lsb[which]).tobytes() == getattr(whole, column)[lo:hi].tobytes()


def test_the_export_s_memory_does_not_grow_with_the_length_of_a_block(tmp_path: Path) -> None:
    """A record step ten times as long holds ten times the samples in one block: the export decodes and
    formats it `CHUNK_ROWS` rows at a time (the blob itself, 18 bytes a sample, is what grows)."""
    import tracemalloc

    p = parse_procedure(TINY, "tiny.yaml")
    peaks = []
    for n in (20_000, 200_000):
        db = tmp_path / f"long{n}.db"
        with Store.create(db) as s:
            cid = s.new_campaign(name=p.name, procedure_text=p.text, procedure_path=None, procedure_sha256=p.sha256,
                                 lab_config={}, mode="sim", sim_config={}, clock_t0=0.0, plan=p.steps())
            b = _record(0, 100.0, n, np.random.default_rng(3))
            s.commit_record(cid, b, dropped=0, corrupt=0, t_end=b.t0_s + n / 50, event_message="x")
        with Store.open_existing(db) as s:
            tracemalloc.start()
            try:
                assert export_campaign(s, cid, _Discard()) == n
                peaks.append(tracemalloc.get_traced_memory()[1])
            finally:
                tracemalloc.stop()
    # Per sample the whole block decoded and formatted at once took ~500 bytes (~100 MB here); what grows
    # now is the row's blobs (18 bytes a sample: 3.2 MB more).
    assert peaks[1] - peaks[0] < 8_000_000, peaks


class _Discard(io.TextIOBase):
    def write(self, text: str) -> int:
        return len(text)
