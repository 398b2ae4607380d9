"""The fit's scoring of its splits and its figures, shared among processes (`labrunner.forked`), give
the same evaluation, files and figures (byte for byte) as in one process."""

from __future__ import annotations

from pathlib import Path

import pytest

from labrunner.forked import ENV, can_fork

from calib_campaigns import make_campaign

needs_fork = pytest.mark.skipif(not can_fork(), reason="no fork here")


@needs_fork
def test_the_fit_scores_and_draws_the_same_in_one_process_or_several(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from labrunner.calibration.fit import FitOptions, fit_campaign
    from labrunner.calibration.outputs import write_fit_files
    from labrunner.calibration.report import evaluation_csv
    from labrunner.procedure import triangular_rates

    frame = make_campaign(seed=3, record_s=120.0, rates_dps=triangular_rates(100.0, 50.0), average_s=1.0)
    results = {}
    for n in ("1", "2"):
        monkeypatch.setenv(ENV, n)
        res = fit_campaign(frame, FitOptions(rbf_variants=("triad",), rbf_export="triad"))
        written, _ = write_fit_files(res, tmp_path / n)
        results[n] = (evaluation_csv(res), written)
    assert results["1"] == results["2"]
    assert len(results["2"][1]) > 5
    for name in results["2"][1]:
        if name.endswith(".png"):
            assert (tmp_path / "1" / name).read_bytes() == (tmp_path / "2" / name).read_bytes(), name


@needs_fork
@pytest.mark.timeout(300)
def test_the_scoring_processes_fork_only_once_the_worker_thread_is_done(monkeypatch: pytest.MonkeyPatch) -> None:
    """The worker thread beside the evaluation still busy when the scoring pass starts (its figure rows slow
    here): the pass waits for it before forking, so no child waits for a thread it does not have (a fit that
    hung for ever, seen once in CI on PostgreSQL). The chunked fit (rows from a source) is the path that forks."""
    import time

    from labrunner.calibration import fit as fit_module
    from labrunner.calibration.fit import FitOptions, fit_campaign
    from labrunner.calibration.fit_rows import CampaignRows
    from labrunner.calibration.report import evaluation_csv
    from labrunner.procedure import triangular_rates

    frame = make_campaign(seed=3, record_s=120.0, rates_dps=triangular_rates(100.0, 50.0), average_s=1.0)
    chunked = CampaignRows(chunks=lambda: (frame.iloc[i:i + 5000] for i in range(0, len(frame), 5000)))
    opt = FitOptions(rbf_variants=("triad",), rbf_export="triad")
    monkeypatch.setenv(ENV, "1")
    want = evaluation_csv(fit_campaign(chunked, opt))

    gather = fit_module.gather_figure_rows

    def slow_gather(*args, **kwargs):  # type: ignore[no-untyped-def]
        time.sleep(8.0)  # past the planning and the models' pass: the scoring pass meets a busy worker
        return gather(*args, **kwargs)

    monkeypatch.setattr(fit_module, "gather_figure_rows", slow_gather)
    monkeypatch.setenv(ENV, "2")
    t0 = time.perf_counter()
    got = evaluation_csv(fit_campaign(chunked, opt))
    assert got == want
    assert time.perf_counter() - t0 < 200
