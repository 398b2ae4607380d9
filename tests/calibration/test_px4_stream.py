"""PX4's reference fitted on rows met chunk by chunk (`Px4Stream`, issue 15) equals `fit_px4` on the
concatenated rows bit for bit: the same orientations fitted or skipped (with the same occupancy), the
same ranges and cubics, with chunks from one row upwards, float outputs or a store's int16 counts, and
rows masked out or rotating in between."""

from __future__ import annotations

import numpy as np
import pytest
from field_logs import field_log

from labrunner.calibration.chunked_records import take_rows
from labrunner.calibration.px4_reference import MEDIAN_WINDOW, Px4Reference, Px4Stream, ValueCounts, fit_px4
from labrunner.calibration.records import Outputs, ScaledColumn, frame_arrays

LSB = (0.001, 0.001, 0.001, 0.00875, 0.00875, 0.00875)  # the paper store's accel and gyro LSBs


def _log(hours: float, counts: bool) -> dict:
    frame, _ = field_log(seed=3, hours_per_run=hours)
    a = frame_arrays(frame)
    n = a["t"].size
    rng = np.random.default_rng(5)
    a["rate"] = np.where(rng.random(n) < 0.05, 30.0, 0.0)  # some rows rotate: not static, not PX4's
    if counts:
        a["y"] = Outputs([ScaledColumn(np.rint(np.asarray(a["y"][:, k]) / s).astype(np.int16), s)
                          for k, s in enumerate(LSB)])
        a["temp"] = np.rint(a["temp"] / 0.01) * 0.01
    return a


def _stream(a: dict, rows: np.ndarray, size: int) -> tuple[Px4Reference, int]:
    px4, passes, n = Px4Stream(), 0, a["t"].size
    while px4.needs_pass:
        for lo in range(0, n, size):
            px4.add(take_rows(a, slice(lo, lo + size), ("orientation", "temp", "rate")), rows[lo:lo + size])
        px4.end_pass()
        passes += 1
    return px4.result(), passes


def _assert_same(got: Px4Reference, want: Px4Reference) -> None:
    assert list(got.skipped.items()) == list(want.skipped.items())
    assert list(got.fits) == list(want.fits)
    for o, f in want.fits.items():
        g = got.fits[o]
        assert (g.t_ref_c, g.t_min_c, g.t_max_c) == (f.t_ref_c, f.t_min_c, f.t_max_c)
        np.testing.assert_array_equal(g.coef, f.coef)


@pytest.mark.parametrize("counts", [False, True])
def test_a_sweep_streamed_in_chunks_of_any_size_is_fit_px4_bit_for_bit(counts: bool) -> None:
    a = _log(0.4, counts)
    n = a["t"].size
    rows = np.random.default_rng(1).random(n) < 0.8  # a training part: rows of every orientation missing
    want = fit_px4(a, rows)
    assert len(want.fits) == 3 and not want.skipped
    for size in (1, 2, MEDIAN_WINDOW - 1, MEDIAN_WINDOW, MEDIAN_WINDOW + 1, 997, n):
        got, passes = _stream(a, rows, size)
        assert passes == 3  # the range, the filtered outputs' median, the bins
        _assert_same(got, want)


def test_soaks_and_short_logs_are_skipped_after_one_pass_with_fit_px4s_occupancy() -> None:
    a = _log(0.4, counts=True)
    n = a["t"].size
    orient = a["orientation"]
    first = orient == orient[0]
    # the first orientation at two soak temperatures (gaps in the sweep); another with too few rows
    a["temp"] = np.where(first, np.where(np.arange(n) % 2 == 0, 20.0, 40.0) + 0.01 * (np.arange(n) % 7), a["temp"])
    second = np.flatnonzero(orient == np.unique(orient)[1])
    rows = np.ones(n, dtype=bool)
    rows[second[MEDIAN_WINDOW - 1:]] = False
    want = fit_px4(a, rows)
    assert set(want.skipped) == {int(orient[0]), int(np.unique(orient)[1])} and len(want.fits) == 1
    assert 0 < want.skipped[int(orient[0])] < 0.5
    for size in (1, 64, n):
        got, _ = _stream(a, rows, size)
        _assert_same(got, want)
    only_soaks = rows & first
    got, passes = _stream(a, only_soaks, 500)
    assert passes == 1 and not got.fits  # nothing is a sweep: no further pass
    _assert_same(got, fit_px4(a, only_soaks))


def test_value_counts_median_is_numpys() -> None:
    rng = np.random.default_rng(2)
    for n in (1, 2, 3, 10, 1001, 1000):
        x = np.rint(rng.normal(0, 5, n)) * 0.00875
        vc = ValueCounts()
        for part in np.array_split(x, 7):
            vc.add(part)
        assert vc.n == n and vc.median() == np.median(x)
