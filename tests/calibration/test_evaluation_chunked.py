"""The evaluation of a campaign read in chunks equals `evaluate` of the whole frame, split by split and
number by number (issue 15): the same held-out draws, training records, PX4 reference, scored rows
and INS windows, with chunks small enough that records, draws and windows cross many cuts.

The campaign has four table rates, runs longer than three one-hour blocks (every split runs) and
more held-out and training rows than the limits, which are set low so that the row subsets are drawn.
"""

from __future__ import annotations

import json
from importlib.resources import files
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import labrunner
from labrunner.calibration import evaluation as ev
from labrunner.calibration.chunked_records import frame_chunks, segment_chunks
from labrunner.calibration.evaluation_chunked import evaluate_chunks
from labrunner.calibration.fit import FitOptions, fit_campaign, fit_models, json_clean
from labrunner.calibration.fit_rows import campaign_rows
from labrunner.calibration.records import Records, frame_arrays, segment_records
from labrunner.data_source import load_campaign_data
from labrunner.domain import OUTPUT_COLUMNS
from labrunner.procedure import triangular_rates

from calib_campaigns import make_campaign

OPTIONS = FitOptions(eval_max_rows=5000, rbf_variants=(), rbf_export="")


@pytest.fixture(scope="module")
def campaign() -> pd.DataFrame:
    return make_campaign(seed=4, record_s=300.0, rates_dps=triangular_rates(100.0, 25.0), average_s=1.0)


def _dicts(results: list[ev.SplitResult]) -> list[str]:
    return [json.dumps(json_clean(r.to_dict()), sort_keys=True) for r in results]


def _whole(frame: pd.DataFrame, opt: FitOptions) -> tuple[Records, list[ev.SplitResult]]:
    records = segment_records(frame, opt.records)
    steps = fit_models(records, opt).steps
    return records, ev.evaluate(frame_arrays(frame), records, steps, lambda tr: fit_models(tr, opt).compensators(),
                                opt.splits, opt.holdout_fraction, opt.eval_max_rows, opt.seed)


def test_every_split_equals_the_whole_frame_evaluation(campaign: pd.DataFrame, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ev, "OFFSET_MAX_ROWS", 3000)  # the per-run offsets drawn from the training rows
    _, whole = _whole(campaign, OPTIONS)
    assert [r.skipped for r in whole] == [None] * 5
    assert all(r.n_test_rows == OPTIONS.eval_max_rows for r in whole)
    assert sum(bool(r.ins) for r in whole) >= 2  # the INS windows are compared too
    records = segment_chunks(frame_chunks(campaign, 4099), OPTIONS.records)
    assert records.row_record.size == 0  # nothing per row of the campaign
    steps = fit_models(records, OPTIONS).steps
    chunked = evaluate_chunks(lambda: frame_chunks(campaign, 4099), len(campaign), records, steps,
                              lambda tr: fit_models(tr, OPTIONS).compensators(), OPTIONS.splits,
                              OPTIONS.holdout_fraction, OPTIONS.eval_max_rows, OPTIONS.seed)
    assert _dicts(chunked) == _dicts(whole)


def test_a_store_fitted_in_chunks_equals_its_whole_frame(tmp_path: Path) -> None:
    """The quick campaign's store read a block at a time: records, models, evaluation, gains and the
    figures' rows as the fit of the loaded frame has them."""
    db = tmp_path / "quick.db"
    assert labrunner.run(files("labrunner.procedures") / "quick.yaml", db=db, seed=1).state == "done"
    data = load_campaign_data(db)
    opt = FitOptions()
    whole = fit_campaign(data.frame, opt, provenance=data.provenance)
    prov, rows = campaign_rows(db, max_rows=1)
    assert prov == data.provenance
    assert len(list(rows.chunks())) > 20
    chunked = fit_campaign(rows, opt, provenance=prov)
    a, b = whole.to_dict(), chunked.to_dict()
    for d in (a, b):
        d.pop("timings_s")
        d["provenance"].pop("fitted_at")
    assert a == b
    # ... and as the whole-frame code computes them: segment_records, evaluate.
    ref_records, ref_eval = _whole(data.frame, opt)
    assert _dicts(chunked.evaluation) == _dicts(ref_eval)
    for f in ("mean", "sem", "temp_c", "n_rows", "row_start", "row_stop", "run", "orientation", "rate_dps"):
        np.testing.assert_array_equal(getattr(chunked.records, f), getattr(ref_records, f))
    assert chunked.records.row_record.size == 0 and whole.records.row_record.size == len(data.frame)
    # The figures' rows: every k-th row of the static records, the first rows of the longest ones.
    static = np.abs(ref_records.rate_dps) < ev.STATIC_RATE_DPS
    rows = np.flatnonzero(np.append(static, False)[ref_records.row_record])
    every = max(1, -(-rows.size // 6000))
    y = data.frame[list(OUTPUT_COLUMNS)]
    sw, sc = whole.samples, chunked.samples
    assert sw is not None and sc is not None and sc.norm is not None and sw.norm is not None
    np.testing.assert_array_equal(np.asarray(sc.norm["y"]), np.asarray(sw.norm["y"]))
    np.testing.assert_array_equal(np.asarray(sc.norm["y"]), y.iloc[rows[::every]].to_numpy(dtype=float))
    assert sc.every == every
    assert sorted(sc.allan) == sorted(sw.allan) and sc.allan
    for r in sc.allan:
        np.testing.assert_array_equal(np.asarray(sc.allan[r]["y"]), np.asarray(sw.allan[r]["y"]))
        np.testing.assert_array_equal(np.asarray(sc.allan[r]["y"]),
                                      y.iloc[np.flatnonzero(ref_records.row_record == r)].to_numpy(dtype=float))


def test_a_field_log_with_px4_fitted_equals_the_whole_frame_evaluation() -> None:
    """A static 1 Hz log of slow ramps (no soaks): PX4's reference is fitted on every split's static
    training rows, streamed chunk by chunk (`Px4Stream`); time_blocks runs with its per-run offsets."""
    from field_logs import field_log

    frame, _ = field_log(seed=1, hours_per_run=4.0)
    _, whole = _whole(frame, OPTIONS)
    assert any("px4" in r.samples for r in whole)
    records = segment_chunks(frame_chunks(frame, 3001), OPTIONS.records)
    steps = fit_models(records, OPTIONS).steps
    passes: list[int] = []
    chunked = evaluate_chunks(_counted(frame, 3001, passes), len(frame), records, steps,
                              lambda tr: fit_models(tr, OPTIONS).compensators(), OPTIONS.splits,
                              OPTIONS.holdout_fraction, OPTIONS.eval_max_rows, OPTIONS.seed)
    assert len(passes) == 4  # PX4's sweeps: their filtered outputs' median, then their bins
    assert _dicts(chunked) == _dicts(whole)


def _counted(frame: pd.DataFrame, rows: int, passes: list[int]):
    def source():
        passes.append(1)
        return frame_chunks(frame, rows)
    return source


def test_the_splits_share_two_passes_and_score_in_the_batches_score_takes(campaign: pd.DataFrame,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 15: every split's models' data in one pass, every split's scores in a second (PX4 finds no
    sweep in soaks); the held-out rows scored as they stream past in batches of SCORE_CHUNK (here cut
    anywhere within the chunks), the same sums as `score` of the rows gathered whole."""
    from labrunner.calibration import evaluation_chunked as ec

    monkeypatch.setattr(ev, "OFFSET_MAX_ROWS", 3000)
    monkeypatch.setattr(ev, "SCORE_CHUNK", 1237)
    monkeypatch.setattr(ec, "DRAW_CHUNK", 1009)  # the random split's held-out rows counted in chunks cutting records
    _, whole = _whole(campaign, OPTIONS)
    assert all(r.px4_skipped for r in whole)
    records = segment_chunks(frame_chunks(campaign, 4099), OPTIONS.records)
    steps = fit_models(records, OPTIONS).steps
    passes: list[int] = []
    chunked = evaluate_chunks(_counted(campaign, 4099, passes), len(campaign), records, steps,
                              lambda tr: fit_models(tr, OPTIONS).compensators(), OPTIONS.splits,
                              OPTIONS.holdout_fraction, OPTIONS.eval_max_rows, OPTIONS.seed)
    assert len(passes) == 2
    assert _dicts(chunked) == _dicts(whole)


def test_ins_windows_from_the_rows_when_the_pieces_cannot_tell(campaign: pd.DataFrame,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The fallback: INS candidates whose pieces cannot tell where a gap is are gathered in a further pass
    and `windows` chooses from them: the same windows and errors."""
    from labrunner.calibration.ins import RowRuns

    _, whole = _whole(campaign, OPTIONS)
    monkeypatch.setattr(RowRuns, "window_positions", lambda self, *args: None)
    records = segment_chunks(frame_chunks(campaign, 4099), OPTIONS.records)
    steps = fit_models(records, OPTIONS).steps
    passes: list[int] = []
    chunked = evaluate_chunks(_counted(campaign, 4099, passes), len(campaign), records, steps,
                              lambda tr: fit_models(tr, OPTIONS).compensators(), OPTIONS.splits,
                              OPTIONS.holdout_fraction, OPTIONS.eval_max_rows, OPTIONS.seed)
    assert len(passes) == 3
    assert sum(bool(r.ins) for r in chunked) >= 2
    assert _dicts(chunked) == _dicts(whole)


def test_a_blocked_draw_beyond_the_shuffle_bound_is_distinct_sorted_and_uniform() -> None:
    from labrunner.calibration.evaluation_chunked import CHOICE_BLOCK, _blocked_choice

    rng = np.random.default_rng(3)
    pop, size = 5 * CHOICE_BLOCK + 12345, 400_000
    x = _blocked_choice(pop, size, rng)
    assert x.size == size and np.all(np.diff(x) > 0) and x[0] >= 0 and x[-1] < pop
    # Each block holds its share of the subset within a few standard deviations (hypergeometric).
    share = np.bincount(x // CHOICE_BLOCK) / size
    expected = np.append(np.full(5, CHOICE_BLOCK), 12345) / pop
    assert np.all(np.abs(share - expected) < 5 * np.sqrt(expected / size) + 1e-9)


def test_beyond_the_shuffle_bound_every_split_still_scores_its_limit(campaign: pd.DataFrame,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    from labrunner.calibration import evaluation_chunked as ec

    monkeypatch.setattr(ec, "CHOICE_MAX_POP", 6000)
    monkeypatch.setattr(ec, "CHOICE_BLOCK", 1000)
    records = segment_chunks(frame_chunks(campaign, 4099), OPTIONS.records)
    steps = fit_models(records, OPTIONS).steps
    out = evaluate_chunks(lambda: frame_chunks(campaign, 4099), len(campaign), records, steps,
                          lambda tr: fit_models(tr, OPTIONS).compensators(), OPTIONS.splits,
                          OPTIONS.holdout_fraction, OPTIONS.eval_max_rows, OPTIONS.seed)
    assert [r.n_test_rows for r in out] == [OPTIONS.eval_max_rows] * 5
    assert all(np.isfinite(r.samples["polynomial"].rms).all() for r in out)


def test_a_campaign_still_being_recorded_is_fitted_as_it_was_at_the_first_pass(tmp_path: Path) -> None:
    """`labrunner fit DB` while the campaign records: every pass reads the rows the first one counted, so a
    block committed between passes (here: during the evaluation's first split) changes nothing. Before, the
    random split's second pass read the new block too and the fit failed (96,500 rows read, 96,000 expected)."""
    import sqlite3

    db = tmp_path / "quick.db"
    assert labrunner.run(files("labrunner.procedures") / "quick.yaml", db=db, seed=2).state == "done"
    opt = FitOptions(splits=("random", "between_temperatures"))
    prov, rows = campaign_rows(db)
    before = fit_campaign(rows, opt, provenance=prov).to_dict()
    inserted: list[str] = []

    def append_a_block(message: str) -> None:  # what a running campaign's next commit_record does
        if not message.startswith("evaluation") or inserted:
            return
        with sqlite3.connect(db) as conn:
            cols = [r[1] for r in conn.execute("PRAGMA table_info(sample_blocks)")]
            last = dict(zip(cols, conn.execute(
                "SELECT * FROM sample_blocks WHERE kind = 'record' ORDER BY t0_s DESC LIMIT 1").fetchone()))
            last.update(id=None, step_idx=100_000, t0_s=last["t0_s"] + 1000.0)
            conn.execute(f"INSERT INTO sample_blocks ({', '.join(f'{chr(34)}{c}{chr(34)}' for c in cols)}) "
                         f"VALUES ({', '.join('?' * len(cols))})", [last[c] for c in cols])
        inserted.append(message)

    prov, rows = campaign_rows(db)
    during = fit_campaign(rows, opt, provenance=prov, progress=append_a_block).to_dict()
    assert inserted == ["evaluation: random"]
    assert load_campaign_data(db).provenance["rows"] == prov["rows"] + 500  # the block is there ...
    for d in (before, during):
        d.pop("timings_s")
        d["provenance"].pop("fitted_at")
    assert during == before  # ... and no pass read it
