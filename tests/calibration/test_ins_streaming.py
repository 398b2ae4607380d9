"""Issue 15, target 3: the chunked evaluation's INS test compensates and navigates its windows' rows as the
scoring pass meets them, INS_CHUNK rows at a time, instead of holding every window's rows (up to 400
minutes per split) until the pass ends: the same groups compensated, the same numbers."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pandas as pd
import pytest

from labrunner.calibration import evaluation as ev
from labrunner.calibration import evaluation_chunked as ec
from labrunner.calibration.chunked_records import frame_chunks, segment_chunks, take_rows
from labrunner.calibration.evaluation import SplitResult
from labrunner.calibration.fit import FitOptions, fit_models, json_clean
from labrunner.calibration.ins import NAV_WINDOWS, NavigationStream, ins_errors
from labrunner.calibration.records import Outputs, ScaledColumn, frame_arrays, reference_values, segment_records
from labrunner.errors import UserError
from labrunner.procedure import triangular_rates

from calib_campaigns import make_campaign


def _arrays(rng: np.random.Generator, rows: int) -> dict[str, Any]:
    """Campaign arrays as a store's chunks hold them (outputs as int16 counts)."""
    counts = [rng.integers(-3000, 3000, rows).astype(np.int16) for _ in range(6)]
    return {"t": np.arange(rows) * 0.02, "orientation": rng.integers(0, 6, rows).astype(np.int8),
            "temp": rng.uniform(-20, 60, rows), "rate": rng.choice([0.0, 0.0, 5.0], rows),
            "y": Outputs([ScaledColumn(c, 1e-4 if j < 3 else 1e-2) for j, c in enumerate(counts)])}


def _windows(rng: np.random.Generator, rows: int, w: int, n: int) -> np.ndarray:
    """(w, n) increasing campaign positions of disjoint windows of consecutive rows."""
    starts = np.sort(rng.choice(rows // n, size=w, replace=False)) * n
    return starts[:, None] + np.arange(n)


def test_a_navigation_stream_fed_in_pieces_gives_ins_errors_numbers() -> None:
    """Reference and output rows in pieces of any size (the outputs lagging the reference): the errors
    of every window navigated at once (`ins_errors`), bit for bit."""
    rng = np.random.default_rng(7)
    w, n = 2 * NAV_WINDOWS + 3, 200
    a = {"orientation": rng.integers(0, 6, w * n).astype(np.int8), "rate": rng.choice([0.0, 3.0], w * n)}
    win = np.arange(w * n).reshape(w, n)
    values = reference_values(a["orientation"], a["rate"]) + rng.normal(0, 1e-3, (w * n, 6))
    want = ins_errors(a, win, {"m": values, "r": values[::-1].copy()})
    for size in (1, 997, n, 5 * n + 3, w * n):
        nav = NavigationStream(w, n)
        for lo in range(0, w * n, size):
            nav.reference(a["orientation"][lo:lo + size], a["rate"][lo:lo + size])
            if lo >= size:  # the outputs one piece behind
                nav.add("m", values[lo - size:lo])
                nav.add("r", values[::-1][lo - size:lo])
        last = (w * n - 1) // size * size
        nav.add("m", values[last:])
        nav.add("r", values[::-1][last:])
        assert (nav.errors("m"), nav.errors("r")) == (want["m"], want["r"]), size


def test_a_navigation_stream_refuses_missing_rows() -> None:
    nav = NavigationStream(2, 10)
    nav.reference(np.zeros(20, dtype=np.int8), np.zeros(20))
    nav.add("m", np.zeros((15, 6)))
    with pytest.raises(ValueError, match="outputs of 15 rows given for 2 windows of 10 rows"):
        nav.errors("m")
    nav = NavigationStream(2, 10)
    nav.reference(np.zeros(10, dtype=np.int8), np.zeros(10))
    nav.add("m", np.zeros((20, 6)))
    with pytest.raises(ValueError, match="reference of 10 rows given for 2 windows of 10 rows"):
        nav.errors("m")


def test_the_ins_windows_rows_are_compensated_in_the_groups_of_ins_chunk_rows_as_they_stream_past(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The windows' rows met chunk by chunk (chunks cutting windows and groups): every model compensates
    the groups of INS_CHUNK rows in `win.ravel()` order (the groups the code compensated when it held
    every window's rows), the raw outputs included, and at most INS_CHUNK rows wait."""
    rng = np.random.default_rng(3)
    rows, w, n = 40_000, 37, 300
    a = _arrays(rng, rows)
    win = _windows(rng, rows, w, n)
    monkeypatch.setattr(ec, "INS_CHUNK", 1000)
    groups: list[tuple[str, np.ndarray]] = []

    # A stand-in model whose outputs depend on the group of rows compensated at once (as an RBF network's
    # float32 outputs do at the last bit): each row's raw outputs plus its group's mean temperature.
    def apply(model: Any, sub: dict[str, Any], done: Any = None) -> tuple[np.ndarray, np.ndarray]:
        y = np.asarray(sub["y"], dtype=float)
        groups.append(("raw" if model is None else "m", sub["temp"].copy()))
        if model is None:
            return y, np.zeros(y.shape[0], dtype=bool)
        return y + sub["temp"].mean(), np.zeros(y.shape[0], dtype=bool)

    monkeypatch.setattr(ec, "_apply", apply)
    flat = win.ravel()
    want_groups = [flat[lo:lo + 1000] for lo in range(0, flat.size, 1000)]
    y = np.asarray(a["y"], dtype=float)
    values = {"raw": y[flat], "m": np.concatenate([y[g] + a["temp"][g].mean() for g in want_groups])}
    want = ins_errors(a, win, values)
    for size in (4099, 777, rows):
        groups.clear()
        rows_of = ec._WindowRows.of(win)
        assert rows_of is not None and rows_of.first.size < 2 * w  # runs of consecutive rows, not rows
        stream = ec._InsStream({"m": object()}, rows_of)  # type: ignore[dict-item]
        for g0 in range(0, rows, size):
            stream.add(g0, take_rows(a, slice(g0, g0 + size), ("t", "orientation", "temp", "rate")))
            assert stream.held < 1000
        res = SplitResult(name="between_temperatures", description="")
        stream.close(res)
        assert res.ins == want
        got = [t for name, t in groups if name == "m"]
        assert len(got) == len(want_groups)
        for t, g in zip(got, want_groups):
            np.testing.assert_array_equal(t, a["temp"][g])
        assert len([1 for name, _ in groups if name == "raw"]) == len(want_groups)


def test_ins_windows_not_all_read_are_refused() -> None:
    rng = np.random.default_rng(5)
    a = _arrays(rng, 5000)
    win = ec._WindowRows.of(_windows(rng, 5000, 4, 300))
    assert win is not None
    stream = ec._InsStream({}, win)
    stream.add(0, take_rows(a, slice(0, 2000), ("t", "orientation", "temp", "rate")))
    with pytest.raises(UserError, match="the INS windows' rows were not all read"):
        stream.close(SplitResult(name="between_rates", description=""))


def test_the_chunked_evaluation_with_small_ins_groups_still_equals_the_whole_frame(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Polynomial and PX4 models compensate row by row: with groups of 1009 rows (several per split, groups
    and chunks cutting windows) the INS errors stay the whole frame's."""
    opt = FitOptions(eval_max_rows=5000, rbf_variants=(), rbf_export="",
                     splits=("between_temperatures", "beyond_temperatures", "time_blocks"))
    frame: pd.DataFrame = make_campaign(seed=4, record_s=300.0, rates_dps=triangular_rates(100.0, 25.0),
                                        average_s=1.0)
    monkeypatch.setattr(ev, "OFFSET_MAX_ROWS", 3000)
    records = segment_records(frame, opt.records)
    steps = fit_models(records, opt).steps
    whole = ev.evaluate(frame_arrays(frame), records, steps, lambda tr: fit_models(tr, opt).compensators(),
                        opt.splits, opt.holdout_fraction, opt.eval_max_rows, opt.seed)
    assert sum(bool(r.ins) for r in whole) >= 2
    monkeypatch.setattr(ec, "INS_CHUNK", 1009)
    sizes: list[int] = []
    group = ec._InsStream._group
    monkeypatch.setattr(ec._InsStream, "_group", lambda self, m: (sizes.append(m), group(self, m))[1])
    chunk_records = segment_chunks(frame_chunks(frame, 4099), opt.records)
    chunk_steps = fit_models(chunk_records, opt).steps
    chunked = ec.evaluate_chunks(lambda: frame_chunks(frame, 4099), len(frame), chunk_records, chunk_steps,
                                 lambda tr: fit_models(tr, opt).compensators(), opt.splits,
                                 opt.holdout_fraction, opt.eval_max_rows, opt.seed)

    def dicts(results: list[SplitResult]) -> list[str]:
        return [json.dumps(json_clean(r.to_dict()), sort_keys=True) for r in results]

    assert dicts(chunked) == dicts(whole)
    assert sizes.count(1009) >= 4 and len(sizes) > sizes.count(1009)  # full groups, and each split's last


def test_window_rows_held_as_runs_give_the_windows_positions() -> None:
    """`_WindowRows`: the windows' rows as runs of consecutive positions (rows dropped within windows cut
    them): `positions` and `below` as the (W, n) array's."""
    rng = np.random.default_rng(11)
    pos = np.cumsum(rng.choice([1, 1, 1, 1, 2, 7, 3000], size=50 * 120))
    win = pos.reshape(50, 120)
    rows = ec._WindowRows.of(win)
    assert rows is not None and rows.shape == (50, 120) and rows.first.size < pos.size / 2
    flat = win.ravel()
    for lo, hi in ((0, flat.size), (0, 1), (17, 4000), (flat.size - 1, flat.size), (5, 5)):
        np.testing.assert_array_equal(rows.positions(lo, hi), flat[lo:hi])
    for g in (0, int(flat[0]), int(flat[0]) + 1, *rng.integers(0, int(flat[-1]) + 2, 500).tolist()):
        assert rows.below(g) == int(np.searchsorted(flat, g)), g
    assert ec._WindowRows.of(np.zeros((0, 0), dtype=np.int64)) is None
