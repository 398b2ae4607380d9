"""A campaign read a bounded number of rows at a time (issue 15, target 2): `Store.frames` and
`data_source.campaign_chunks` give, chunk by chunk, what `samples_frame` and `load_campaign_data` give
whole, cut only between blocks (and only at gaps longer than `min_gap_s` when asked), with the whole
read's validation messages naming the rows by their place in the campaign."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import labrunner
from labrunner.campaign_csv import CampaignDataError
from labrunner.data_source import campaign_chunks, load_campaign_data
from labrunner.discrepancy.summary import read_store_summary
from labrunner.procedure import parse_procedure
from labrunner.store import SampleBlock, Store
from tests.campaign.conftest import TINY

LSB = (0.001, 0.00875, 0.01)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """A real store: the tiny procedure run to the end on the simulated lab (records and monitor blocks)."""
    folder = tmp_path_factory.mktemp("chunks")
    procedure = folder / "tiny.yaml"
    procedure.write_text(TINY)
    db = folder / "tiny.db"
    assert labrunner.run(procedure, db=db).state == "done"
    return db


def _block(kind: str, step: int | None, t0: float, n: int, *, run: int = 1, orientation: str = "x_up",
           seed: int = 0) -> SampleBlock:
    counts = np.random.default_rng(seed).integers(-2000, 2000, size=(n, 7))
    return SampleBlock(kind=kind, step_idx=step, run=run, orientation=orientation, t0_s=t0, rate_hz=10.0,
                       counter=np.arange(n) + 7, accel_g=counts[:, :3] * LSB[0], gyro_dps=counts[:, 3:6] * LSB[1],
                       temp_c=2000 + counts[:, 6] * LSB[2], chamber=np.array([[t0, 15.0], [t0 + n / 10, 15.5]]),
                       table=np.array([[t0, 50.0]]), lsb=LSB)


def _store(tmp_path: Path, blocks: list[SampleBlock]) -> tuple[Path, int]:
    p = parse_procedure(TINY, "tiny.yaml")
    db = tmp_path / "made.db"
    s = Store.create(db)
    cid = s.new_campaign(name=p.name, procedure_text=p.text, procedure_path=None, procedure_sha256=p.sha256,
                         lab_config={}, mode="sim", sim_config={}, clock_t0=0.0, plan=p.steps())
    for b in blocks:
        if b.kind == "record":
            s.commit_record(cid, b, dropped=0, corrupt=0, t_end=b.t0_s + len(b) / b.rate_hz, event_message="step")
        else:
            s.save_monitor(cid, b)
    s.event(cid, 0.0, "info", "powered on (run 1)")
    s.close()
    return db, cid


def _check_chunks(db: Path, include_monitor: bool, max_rows: int, min_gap_s: float | None = None) -> list[pd.DataFrame]:
    """The chunks concatenate to the whole read, each starts at a block's first sample, and each
    exceeds max_rows by at most its last block."""
    with Store.open_existing(db) as s:
        cid = s.resolve(None)
        whole = s.samples_frame(cid, include_monitor=include_monitor, categorical=True, counts=True)
        kinds = ("record", "monitor") if include_monitor else ("record",)
        blocks = [b for b in s.blocks(cid, kinds) if len(b)]
        chunks = list(s.frames(cid, max_rows=max_rows, include_monitor=include_monitor, min_gap_s=min_gap_s))
    pd.testing.assert_frame_equal(pd.concat(chunks), whole)
    starts = {b.t0_s for b in blocks}
    biggest = max(len(b) for b in blocks)
    for c in chunks:
        assert c["t_s"].iat[0] in starts
        if min_gap_s is None and not include_monitor:
            assert len(c) < max_rows + biggest
    return chunks


@pytest.mark.parametrize("include_monitor", [False, True])
def test_chunks_of_a_recorded_store_are_its_frame(recorded, include_monitor):
    counts = [len(_check_chunks(recorded, include_monitor, max_rows)) for max_rows in (1, 500, 3000, 10**9)]
    assert counts == sorted(counts, reverse=True) and counts[0] > counts[2] and counts[3] == 1
    if not include_monitor:  # one record block a chunk
        with Store.open_existing(recorded) as s:
            assert counts[0] == len(list(s.blocks(s.resolve(None))))


@pytest.mark.parametrize("include_monitor", [False, True])
def test_campaign_chunks_are_load_campaign_data(recorded, include_monitor):
    data = load_campaign_data(recorded, include_monitor=include_monitor)
    provenance, chunks = campaign_chunks(recorded, max_rows=100, include_monitor=include_monitor)
    assert provenance == data.provenance
    parts = list(chunks)
    assert len(parts) > 3
    pd.testing.assert_frame_equal(pd.concat(parts), data.frame)
    assert data.frame["power_on"].sum() >= 1


def test_monitor_rows_among_the_records_are_not_cut(tmp_path):
    """A monitor stretch that overlaps a record interleaves with it in the time-ordered read: no chunk
    boundary falls inside that overlap, and the chunks are the whole sorted read."""
    blocks = [_block("monitor", None, 0.0, 50, seed=1),
              _block("record", 0, 3.0, 40, seed=2),  # inside the monitor stretch (0..4.9 s)
              _block("monitor", None, 20.0, 30, seed=3),
              _block("record", 1, 30.0, 40, seed=4),
              _block("record", 2, 34.5, 40, seed=5)]  # 0.6 s after the previous one's last sample
    db, _ = _store(tmp_path, blocks)
    chunks = _check_chunks(db, True, max_rows=1)
    assert [len(c) for c in chunks] == [90, 30, 40, 40]  # the first two blocks overlap: one chunk
    gapped = _check_chunks(db, True, max_rows=1, min_gap_s=1.0)
    assert [len(c) for c in gapped] == [90, 30, 80]  # 0.6 s is no gap longer than 1 s
    assert [len(c) for c in _check_chunks(db, False, max_rows=1, min_gap_s=5.0)] == [40, 80]


def test_a_chunk_names_bad_rows_by_their_place_in_the_campaign(tmp_path):
    """The chunked read raises what the whole read raises: an unknown orientation in the third block,
    and time going backwards across a chunk boundary."""
    blocks = [_block("record", 0, 0.0, 30), _block("record", 1, 10.0, 30),
              _block("record", 2, 20.0, 30, orientation="sideways")]
    db, _ = _store(tmp_path, blocks)
    with pytest.raises(CampaignDataError) as whole:
        load_campaign_data(db)
    assert ":60: column 'orientation'" in str(whole.value)
    _, chunks = campaign_chunks(db, max_rows=1)
    with pytest.raises(CampaignDataError) as chunked:
        list(chunks)
    assert str(chunked.value) == str(whole.value)

    folder = tmp_path / "back"
    folder.mkdir()
    db, _ = _store(folder, [_block("record", 0, 0.0, 30), _block("record", 1, 2.0, 30)])  # starts before 2.9 s
    with pytest.raises(CampaignDataError) as whole:
        load_campaign_data(db)
    assert "time goes backwards within run 1" in str(whole.value)
    _, chunks = campaign_chunks(db, max_rows=1)
    with pytest.raises(CampaignDataError) as chunked:
        list(chunks)
    assert str(chunked.value) == str(whole.value)


def test_a_campaign_csv_is_one_chunk(recorded, tmp_path):
    from labrunner.campaign_csv import write_campaign

    csv = tmp_path / "c.csv"
    write_campaign(load_campaign_data(recorded).frame, csv)
    provenance, chunks = campaign_chunks(csv, max_rows=10)
    data = load_campaign_data(csv)
    assert provenance == data.provenance
    (only,) = list(chunks)
    pd.testing.assert_frame_equal(only, data.frame)


def test_max_rows_must_be_positive(recorded):
    with Store.open_existing(recorded) as s, pytest.raises(ValueError, match="max_rows"):
        next(s.frames(s.resolve(None), max_rows=0))


def _garble_sample_page(db: Path) -> None:
    """Overwrite the middle of one of sample_blocks' interior (b-tree) pages, the kind of damage SQLite
    refuses on reading."""
    import sqlite3

    with sqlite3.connect(db) as conn:
        size = conn.execute("PRAGMA page_size").fetchone()[0]
        pages = [r[0] for r in conn.execute("SELECT pageno FROM dbstat WHERE name = 'sample_blocks' "
                                            "AND pagetype IN ('leaf', 'internal') ORDER BY pageno")]
    with db.open("r+b") as f:
        f.seek((pages[len(pages) // 2] - 1) * size + 100)
        f.write(b"\xa5" * (size - 200))


def test_damage_in_the_sample_pages_is_named_as_the_open_names_it(recorded, tmp_path):
    """load_campaign_data and campaign_chunks leave sample_blocks out of the open's check (they read its
    pages anyway): a damaged sample page still gives the StoreDamage line the full check gives."""
    from labrunner.store import StoreDamage

    db = tmp_path / "garbled.db"
    db.write_bytes(recorded.read_bytes())
    _garble_sample_page(db)
    with pytest.raises(StoreDamage) as opened:
        Store.open_existing(db)
    assert "the database is damaged" in str(opened.value) and "quick_check" in str(opened.value)
    with pytest.raises(StoreDamage) as loaded:
        load_campaign_data(db)
    assert str(loaded.value) == str(opened.value)
    with pytest.raises(StoreDamage) as chunked:  # at the call (the block rows counted) or in the chunks
        list(campaign_chunks(db, max_rows=1)[1])
    assert str(chunked.value) == str(opened.value)
    with pytest.raises(StoreDamage) as summarised:  # labrunner diagnose DB's read
        read_store_summary(db)
    assert str(summarised.value) == str(opened.value)


def test_the_diagnosis_read_leaves_the_sample_pages_to_the_reads(recorded, monkeypatch):
    """`labrunner diagnose DB` reads every sample block anyway: the open's quick_check skips their pages
    (on the 10x store 0.8 s of CPU), as load_campaign_data's does."""
    checked: list = []
    check = Store._pragma_check

    def spy(self, pragma, tables=None):
        checked.append(tables)
        return check(self, pragma, tables)

    monkeypatch.setattr(Store, "_pragma_check", spy)
    stored = read_store_summary(recorded)
    assert stored.summary.total_samples == stored.provenance["rows"] > 0
    assert checked and all(tables is not None and "sample_blocks" not in tables for tables in checked)
