"""A campaign read for the analyses keeps the IMU channels as the stored int16 counts (issue 15, target 4).

`Store.campaign_data` gives the accelerometer, gyro and temperature columns as `ScaledFloatArray`s
(counts x LSB): the same float64 values bit for bit as the decoding path (`samples_frame`), a fit of
them gives the same model, and a damaged blob is still named in one line."""

from __future__ import annotations

import io
import sqlite3
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import labrunner
from labrunner.calibration.fit import FitOptions, fit_campaign
from labrunner.calibration.records import ScaledColumn, frame_arrays, segment_records
from labrunner.campaign_csv import read_campaign
from labrunner.data_source import ScaledFloatArray, load_campaign_data, mark_power_ons
from labrunner.domain import CSV_COLUMNS, OUTPUT_COLUMNS
from labrunner.procedure import parse_procedure
from labrunner.store import SampleBlock, Store, StoreDamage
from tests.campaign.conftest import TINY

LSB = (0.001, 0.00875, 0.01)  # not powers of two: float32 would not hold counts x LSB exactly
IMU = ("imu_temp_c", *OUTPUT_COLUMNS)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """A real store: the tiny procedure run to the end on the simulated lab."""
    folder = tmp_path_factory.mktemp("counts")
    procedure = folder / "tiny.yaml"
    # Three temperatures and 8 s records: enough for segment_records (5 s records and up) and a fit.
    procedure.write_text(TINY.replace("list_c: [15, 35]", "list_c: [5, 25, 45]").replace("record_s: 4", "record_s: 8"))
    db = folder / "tiny.db"
    assert labrunner.run(procedure, db=db).state == "done"
    return db


def _float_frame(db: Path) -> pd.DataFrame:
    """The campaign as the float64 decoding path reads it, validated and marked as `load_campaign_data` does."""
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        frame = read_campaign(store.samples_frame(cid, categorical=True))
        return mark_power_ons(frame, store.events_frame(cid))


def test_counts_read_equals_the_float_read(recorded):
    data = load_campaign_data(recorded)
    floats = _float_frame(recorded)
    frame = data.frame
    assert list(frame.columns) == list(floats.columns) == [*CSV_COLUMNS, "power_on"]
    for c in IMU:
        values = frame[c].array
        assert isinstance(values, ScaledFloatArray) and values.counts.dtype == np.int16, c
        assert frame[c].to_numpy().dtype == np.float64
    for c in frame.columns:
        ours, theirs = frame[c].to_numpy(), floats[c].to_numpy()
        assert ours.dtype == theirs.dtype, c
        assert np.array_equal(ours, theirs), c  # bit for bit, not approximately
    # The six outputs and the temperature: 2 bytes a row instead of 8.
    imu_bytes = sum(frame[c].array.nbytes for c in IMU)
    assert imu_bytes == 2 * len(IMU) * len(frame)
    assert frame.memory_usage().sum() < floats.memory_usage().sum() - 5 * len(IMU) * len(frame)


def test_frame_arrays_convert_the_rows_asked_for(recorded):
    frame = load_campaign_data(recorded).frame
    a, b = frame_arrays(frame), frame_arrays(_float_frame(recorded))
    assert all(isinstance(col, ScaledColumn) for col in a["y"].columns)
    assert a["y"].shape == b["y"].shape
    rows = np.random.default_rng(3).choice(len(frame), size=500, replace=False)
    assert np.array_equal(a["y"][rows], b["y"][rows])
    assert np.array_equal(a["y"][10:2000, 4], b["y"][10:2000, 4])
    assert np.array_equal(np.asarray(a["y"]), np.asarray(b["y"]))
    for key in ("t", "run", "orientation", "temp", "rate"):
        assert isinstance(a[key], np.ndarray) and np.array_equal(a[key], b[key]), key


def test_a_fit_of_the_counts_is_the_fit_of_the_floats(recorded):
    frame, floats = load_campaign_data(recorded).frame, _float_frame(recorded)
    ra, rb = segment_records(frame), segment_records(floats)
    assert len(ra) > 0
    assert np.array_equal(ra.row_record, rb.row_record) and np.array_equal(ra.mean, rb.mean)
    assert np.array_equal(ra.sem, rb.sem, equal_nan=True)
    opt = FitOptions(poly_order=2, rbf_variants=("hybrid",), splits=("random", "between_rates"), eval_max_rows=5000)
    fa, fb = fit_campaign(frame, opt), fit_campaign(floats, opt)
    da, db = fa.to_dict(), fb.to_dict()
    for d in (da, db):
        d.get("provenance", {}).pop("fitted_at", None)
        d.pop("timings_s", None)
    assert da == db


def _store_with(tmp_path: Path, blocks: list[SampleBlock]) -> tuple[Path, int]:
    p = parse_procedure(TINY, "tiny.yaml")
    db = tmp_path / "made.db"
    s = Store.create(db)
    cid = s.new_campaign(name=p.name, procedure_text=p.text, procedure_path=None, procedure_sha256=p.sha256,
                         lab_config={}, mode="sim", sim_config={}, clock_t0=0.0, plan=p.steps())
    for b in blocks:
        s.commit_record(cid, b, dropped=0, corrupt=0, t_end=b.t0_s + len(b) / b.rate_hz, event_message="step")
    s.close()
    return db, cid


def _block(step: int, lsb: tuple[float, float, float] | None, n: int = 300) -> SampleBlock:
    counts = np.random.default_rng(step).integers(-2000, 2000, size=(n, 7))
    scale = lsb or (0.3, 0.7, 0.9)
    return SampleBlock(kind="record", step_idx=step, run=1, orientation="x_up", t0_s=100.0 * step, rate_hz=50.0,
                       counter=np.arange(n) + 10 * step, accel_g=counts[:, :3] * scale[0],
                       gyro_dps=counts[:, 3:6] * scale[1], temp_c=2000 + counts[:, 6] * scale[2],
                       chamber=np.array([[100.0 * step, 15.0], [100.0 * step + 4, 15.2]]),
                       table=np.array([[100.0 * step, -50.0]]), lsb=None if lsb is None else (scale[0], scale[1],
                                                                                                  scale[2]))


def test_blocks_of_other_lsb_sizes_or_floats_are_read_as_float64(tmp_path):
    """One LSB for every block is what keeps counts; otherwise the columns are decoded (same values)."""
    cases = (("one", [_block(0, LSB), _block(1, LSB)], True),
             ("mixed", [_block(0, LSB), _block(1, (0.002, 0.00875, 0.01)), _block(2, None)], False))
    for name, blocks, counted in cases:
        folder = tmp_path / name
        folder.mkdir()
        db, cid = _store_with(folder, blocks)
        frame = load_campaign_data(db).frame
        assert [isinstance(frame[c].array, ScaledFloatArray) for c in IMU] == [counted] * len(IMU), name
        with Store.open_existing(db) as s:
            decoded = list(s.blocks(cid))
        assert np.array_equal(frame["ay_g"].to_numpy(), np.concatenate([b.accel_g[:, 1] for b in decoded])), name
        assert np.array_equal(frame["gz_dps"].to_numpy(), np.concatenate([b.gyro_dps[:, 2] for b in decoded])), name
        assert np.array_equal(frame["imu_temp_c"].to_numpy(), np.concatenate([b.temp_c for b in decoded])), name


def test_a_short_blob_is_named_by_the_counts_read(recorded, tmp_path):
    db = tmp_path / "short.db"
    db.write_bytes(recorded.read_bytes())
    with sqlite3.connect(db) as conn:
        block, n = conn.execute("SELECT id, n FROM sample_blocks WHERE kind = 'record' AND step_idx = 5").fetchone()
        conn.execute("UPDATE sample_blocks SET gyro_dps = substr(gyro_dps, 1, 100) WHERE id = ?", (block,))
    where = (f"{db}: campaign 1, table sample_blocks, step 5 (block {block}): column gyro_dps holds 100 bytes, "
             f"{n} samples need {6 * n}; the store is damaged")
    with pytest.raises(StoreDamage) as counted:
        load_campaign_data(db)
    with Store.open_existing(db) as s, pytest.raises(StoreDamage) as decoded:
        list(s.blocks(1))
    assert str(counted.value) == str(decoded.value) == where


def test_a_scaled_column_behaves_as_its_float64_values():
    counts = np.random.default_rng(5).integers(-32768, 32767, size=1000).astype(np.int16)
    ours = pd.Series(ScaledFloatArray(counts, 0.00875), name="g")
    theirs = pd.Series(counts * 0.00875, name="g")
    assert ours.dtype.kind == "f" and pd.api.types.is_float_dtype(ours.dtype)
    for name in ("sum", "mean", "std", "min", "max", "median"):
        assert getattr(ours, name)() == getattr(theirs, name)(), name
    assert ours.quantile(0.9) == theirs.quantile(0.9)
    mask = theirs.to_numpy() > 0
    assert np.array_equal(ours[mask].to_numpy(), theirs[mask].to_numpy())
    assert isinstance(ours.iloc[[5, 1, 7]].array, ScaledFloatArray)  # rows taken as counts
    assert np.array_equal(ours.iloc[[5, 1, 7]].to_numpy(), theirs.iloc[[5, 1, 7]].to_numpy())
    assert ours.iloc[3] == theirs.iloc[3]
    key = np.arange(1000) % 7
    assert np.array_equal(ours.groupby(key).mean().to_numpy(dtype=float), theirs.groupby(key).mean().to_numpy())
    assert np.array_equal((ours * 2 - 1).to_numpy(), (theirs * 2 - 1).to_numpy())
    assert np.array_equal(np.abs(ours).to_numpy(dtype=float), np.abs(theirs).to_numpy())
    assert ((ours > 0) == (theirs > 0)).all()
    both = pd.concat([ours, ours])
    assert isinstance(both.array, ScaledFloatArray) and both.array.counts.dtype == np.int16
    a, b = io.StringIO(), io.StringIO()
    ours.to_frame().to_csv(a, index=False, float_format="%.9g")
    theirs.to_frame().to_csv(b, index=False, float_format="%.9g")
    assert a.getvalue() == b.getvalue()
    edited = ours.copy()
    edited.iloc[2] = 0.5  # not a whole count: the copy becomes float64 values, the original stays
    assert edited.iloc[2] == 0.5 and edited.iloc[3] == theirs.iloc[3] and ours.iloc[2] == theirs.iloc[2]
