"""Records summed in chunks equal the plain per-record statistics of the same rows (issue 15: the fit in
bounded memory must not change a number).

The reference is computed here from the rows directly (pandas groupby over the labels), not with the
module's code; chunk sizes small enough that every record boundary case (a cut inside a record, rows
in no record, one-row records, a masked training part) is crossed on a campaign of a few thousand rows.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from labrunner.calibration import records as rec
from labrunner.calibration.evaluation import _draw
from labrunner.calibration.records import frame_arrays, records_from_labels, segment_records
from labrunner.domain import ORIENTATIONS, OUTPUT_COLUMNS


def _campaign(seed: int = 3) -> pd.DataFrame:
    """Segments of 50 Hz rows in three orientations and two runs, with gaps, a rate step and a drift."""
    rng = np.random.default_rng(seed)
    parts = []
    t = 0.0
    for k in range(24):
        n = int(rng.integers(300, 900))
        tt = t + np.arange(n) / 50.0
        temp = 20.0 + k + 0.001 * rng.standard_normal(n)
        if k == 5:
            temp = temp + np.linspace(0, 3.0, n)  # a ramp: cut into pieces, the drifting ones dropped
        rate = np.where(np.arange(n) < n // 2, 0.0, 10.0) if k % 4 == 1 else np.full(n, 5.0 * (k % 3))
        y = rng.standard_normal((n, 6)) * 0.01 + np.array([0, 0, 1, 0, 0, 0.0])
        parts.append(pd.DataFrame({
            "t_s": tt, "run": 1 + k // 12, "orientation": ORIENTATIONS[k % 3], "chamber_c": temp,
            "imu_temp_c": temp, "table_rate_dps": rate, **{c: y[:, j] for j, c in enumerate(OUTPUT_COLUMNS)},
        }))
        t = tt[-1] + 7.0  # a gap
    frame = pd.concat(parts, ignore_index=True)
    frame["orientation"] = pd.Categorical(frame["orientation"], categories=list(ORIENTATIONS))
    return frame


def _reference(frame: pd.DataFrame, labels: np.ndarray) -> pd.DataFrame:
    g = frame.assign(label=labels)[labels >= 0].groupby("label", sort=True)
    out = g[list(OUTPUT_COLUMNS)].mean()
    out["temp"] = g["imu_temp_c"].mean()
    out["span"] = g["imu_temp_c"].max() - g["imu_temp_c"].min()
    out["t0"] = g["t_s"].first()
    out["t1"] = g["t_s"].last()
    out["n"] = g.size()
    for c in OUTPUT_COLUMNS:
        out[f"sem_{c}"] = g[c].std(ddof=1) / np.sqrt(g.size())
    return out


def _check(records: rec.Records, ref: pd.DataFrame) -> None:
    assert len(records) == len(ref)
    np.testing.assert_allclose(records.mean, ref[list(OUTPUT_COLUMNS)].to_numpy(), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(records.temp_c, ref["temp"].to_numpy(), rtol=1e-12)
    np.testing.assert_allclose(records.temp_span_c, ref["span"].to_numpy(), atol=1e-12)
    np.testing.assert_array_equal(records.t_start_s, ref["t0"].to_numpy())
    np.testing.assert_array_equal(records.t_end_s, ref["t1"].to_numpy())
    np.testing.assert_array_equal(records.n_rows, ref["n"].to_numpy())
    sem_ref = ref[[f"sem_{c}" for c in OUTPUT_COLUMNS]].to_numpy()
    one = records.n_rows <= 1
    np.testing.assert_allclose(records.sem[~one], sem_ref[~one], rtol=1e-9)
    assert np.isnan(records.sem[one]).all()


@pytest.mark.parametrize("chunk", [97, 1000, 1 << 20])
def test_chunked_records_equal_the_rows_statistics(monkeypatch: pytest.MonkeyPatch, chunk: int) -> None:
    frame = _campaign()
    monkeypatch.setattr(rec, "CHUNK_ROWS", chunk)
    records = segment_records(frame)
    assert (records.row_record < 0).any() and len(records) >= 20  # gaps and ramp rows lie outside records
    _check(records, _reference(frame, records.row_record))
    # The segmentation itself does not depend on the chunking.
    monkeypatch.setattr(rec, "CHUNK_ROWS", 1 << 30)
    whole = segment_records(frame)
    np.testing.assert_array_equal(whole.row_record, records.row_record)
    for name in ("mean", "sem", "temp_c", "temp_span_c", "n_rows", "row_interval_s"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(records, name))


@pytest.mark.parametrize("chunk", [97, 1 << 20])
def test_masked_training_part_equals_its_rows_statistics(monkeypatch: pytest.MonkeyPatch, chunk: int) -> None:
    frame = _campaign(seed=7)
    records = segment_records(frame)
    monkeypatch.setattr(rec, "CHUNK_ROWS", chunk)
    mask = _draw(np.random.default_rng(0), len(frame), 0.8, chunk=333)
    train = records_from_labels(frame_arrays(frame), records.row_record, records.row_interval_s, mask)
    _check(train, _reference(frame, np.where(mask, records.row_record, -1)))
    bare = records_from_labels(frame_arrays(frame), records.row_record, records.row_interval_s, mask,
                               with_labels=False)
    assert bare.row_record.size == 0
    np.testing.assert_array_equal(bare.mean, train.mean)


def test_interleaved_labels_are_summed_whole(monkeypatch: pytest.MonkeyPatch) -> None:
    """Labels whose records are not one run of rows (no safe cut): one pass, still the right sums."""
    frame = _campaign(seed=11)
    monkeypatch.setattr(rec, "CHUNK_ROWS", 50)
    labels = np.arange(len(frame)) % 7
    labels[::13] = -1
    out = records_from_labels(frame_arrays(frame), labels, np.full(7, 0.02))
    _check(out, _reference(frame, labels))


def test_counts_held_as_counts_give_the_records_of_their_float_values(monkeypatch: pytest.MonkeyPatch) -> None:
    """A store's outputs stay int16 counts (`ScaledColumn`): summed from counts converted a chunk at a time,
    the records are bit for bit those of the float64 columns (counts x scale)."""
    frame = _campaign(seed=5)
    records = segment_records(frame)
    monkeypatch.setattr(rec, "CHUNK_ROWS", 700)
    rng = np.random.default_rng(2)
    counts = [rng.integers(-3000, 3000, len(frame)).astype(np.int16) for _ in range(6)]
    scales = [1 / 2048, 1 / 4096, 1 / 8192, 0.07, 0.035, 1 / 16.4]
    a = frame_arrays(frame)
    held = dict(a, y=rec.Outputs([rec.ScaledColumn(c, s) for c, s in zip(counts, scales)]))
    plain = dict(a, y=rec.Outputs([c * s for c, s in zip(counts, scales)]))
    mask = _draw(np.random.default_rng(1), len(frame), 0.8, chunk=333)
    for m in (None, mask):
        got = records_from_labels(held, records.row_record, records.row_interval_s, m)
        want = records_from_labels(plain, records.row_record, records.row_interval_s, m)
        for name in ("mean", "sem", "temp_c", "temp_span_c", "n_rows", "t_start_s", "t_end_s", "row_start"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))


def test_draws_in_chunks_are_the_generators_stream() -> None:
    a, b = np.random.default_rng(42), np.random.default_rng(42)
    np.testing.assert_array_equal(_draw(a, 10_001, 0.3, chunk=64), b.random(10_001) < 0.3)
    assert a.random() == b.random()  # the generator is left where one draw of all rows leaves it
