"""Records of a campaign read chunk by chunk equal `segment_records` of the whole frame, wherever the
chunks are cut (issue 15: the fit reads a store in chunks and must not change a number).

Cuts at every size from one row upwards cross every boundary case: a cut inside a segment, next to a
gap (whose decision needs the intervals on both sides), between runs, inside a drifting segment cut
into stable pieces, and one-row records of averaged rows. The store case reads a real recorded store
through `data_source.campaign_chunks` with chunks of one block.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import labrunner
from labrunner.calibration.chunked_records import frame_chunks, segment_chunks, typical_interval_of
from labrunner.calibration.records import Records, segment_records
from labrunner.data_source import campaign_chunks, load_campaign_data
from labrunner.domain import ORIENTATIONS, OUTPUT_COLUMNS

FIELDS = ("run", "orientation", "rate_dps", "temp_c", "temp_span_c", "t_start_s", "t_end_s", "n_rows",
          "row_interval_s", "mean", "sem", "reference", "row_start", "row_stop")


def _campaign(seed: int = 5, interval_s: float = 0.02) -> pd.DataFrame:
    """Segments in three orientations and two runs; gaps of several lengths (one a single long interval
    followed by a short one, one a slightly longer interval that is no gap), a rate step and a ramp."""
    rng = np.random.default_rng(seed)
    parts = []
    t = 0.0
    for k in range(18):
        n = int(rng.integers(260, 600))
        tt = t + np.arange(n) * interval_s
        if k == 7:
            tt[n // 2:] += 2.5 * interval_s  # an interval 3.5x its neighbours': a gap inside the segment
        if k == 8:
            tt[n // 3:] += 1.5 * interval_s  # 2.5x: no gap
        temp = 20.0 + 2 * k + 0.001 * rng.standard_normal(n)
        if k == 4:
            temp = temp + np.linspace(0, 3.0, n)  # a ramp: cut into pieces, the drifting ones dropped
        rate = np.where(np.arange(n) < n // 2, 0.0, 10.0) if k % 5 == 1 else np.full(n, 5.0 * (k % 3))
        y = rng.standard_normal((n, 6)) * 0.01 + np.array([0, 0, 1, 0, 0, 0.0])
        parts.append(pd.DataFrame({
            "t_s": tt, "run": 1 + k // 9, "orientation": ORIENTATIONS[(k // 2) % 3], "chamber_c": temp,
            "imu_temp_c": temp, "table_rate_dps": rate, **{c: y[:, j] for j, c in enumerate(OUTPUT_COLUMNS)},
        }))
        t = tt[-1] + (7.0 if k % 2 else interval_s)  # every other segment follows without a gap
    frame = pd.concat(parts, ignore_index=True)
    frame["orientation"] = pd.Categorical(frame["orientation"], categories=list(ORIENTATIONS))
    return frame


def _assert_equal(chunked: Records, whole: Records) -> None:
    assert len(chunked) == len(whole) > 0
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(chunked, f), getattr(whole, f), err_msg=f)
    # The ranges are the whole frame's labels, and no per-row array of the campaign is kept.
    np.testing.assert_array_equal(chunked.labels(whole.row_record.size), whole.row_record)
    assert chunked.row_record.size == 0


@pytest.mark.parametrize("chunk", [1, 2, 3, 7, 50, 333, 100_000])
def test_chunked_records_equal_the_whole_frame(chunk: int) -> None:
    frame = _campaign()
    whole = segment_records(frame)
    assert (np.diff(whole.row_start) > 0).all() and whole.n_rows.min() > 1
    _assert_equal(segment_chunks(frame_chunks(frame, chunk)), whole)


def test_cuts_of_irregular_sizes_do_not_move_a_record() -> None:
    frame = _campaign(seed=9)
    whole = segment_records(frame)
    rng = np.random.default_rng(0)
    cuts = np.unique(np.concatenate([[0], rng.integers(1, len(frame), 60), [len(frame)]]))
    _assert_equal(segment_chunks(frame.iloc[lo:hi] for lo, hi in zip(cuts[:-1], cuts[1:])), whole)


@pytest.mark.parametrize("chunk", [1, 4, 25])
def test_one_row_records_of_averaged_rows(chunk: int) -> None:
    """Rows 10 s apart: single rows between rate changes are records standing for the typical interval."""
    frame = _campaign(seed=2, interval_s=10.0)
    frame.loc[frame.index % 3 == 0, "table_rate_dps"] += 50.0  # every third row its own segment
    whole = segment_records(frame)
    assert (whole.n_rows == 1).any()
    chunked = segment_chunks(frame_chunks(frame, chunk), typical_interval=lambda: typical_interval_of(
        frame_chunks(frame, 97)))
    _assert_equal(chunked, whole)
    # Without the campaign's interval a one-row record cannot be weighed: dropped, the others unchanged.
    partial = segment_chunks(frame_chunks(frame, chunk))
    assert len(partial) == int((whole.n_rows > 1).sum())


def test_a_recorded_store_in_chunks_of_a_block(tmp_path: Path) -> None:
    db = tmp_path / "quick.db"
    result = labrunner.run(files("labrunner.procedures") / "quick.yaml", db=db, seed=1)
    assert result.state == "done"
    whole = segment_records(load_campaign_data(db).frame)
    _, chunks = campaign_chunks(db, max_rows=1)
    pieces = list(chunks)
    assert len(pieces) > 20
    _assert_equal(segment_chunks(pieces), whole)
