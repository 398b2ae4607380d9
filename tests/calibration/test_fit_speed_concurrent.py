"""The fit's concurrency changes no number (issue 15): the networks trained on several threads equal those
trained one at a time, the final fit run alongside the evaluation equals the fit run before it, and a
final fit that fails still fails the fit as before."""

from __future__ import annotations

import json

import pandas as pd
import pytest

from labrunner.calibration import fit as fit_module
from labrunner.calibration import rbf_model
from labrunner.calibration.fit import FitOptions, fit_campaign, fit_models, json_clean
from labrunner.calibration.records import Records, segment_records
from labrunner.errors import UserError

OPTIONS = FitOptions(eval_max_rows=4000, splits=("random", "between_temperatures"))


def _models_json(models: fit_module.Models) -> str:
    return json.dumps(json_clean({k: m.to_dict() for k, m in models.compensators().items()}), sort_keys=True)


def test_networks_trained_on_threads_equal_those_trained_one_at_a_time(
        cubic_campaign: pd.DataFrame, monkeypatch: pytest.MonkeyPatch) -> None:
    records = segment_records(cubic_campaign, OPTIONS.records)
    monkeypatch.setattr(rbf_model, "TRAIN_WORKERS", 1)
    alone = _models_json(fit_models(records, OPTIONS))
    monkeypatch.setattr(rbf_model, "TRAIN_WORKERS", 3)
    assert _models_json(fit_models(records, OPTIONS)) == alone
    one = rbf_model.train_rbf_model(records, "triad")
    assert json.dumps(json_clean(one.to_dict())) == json.dumps(json_clean(
        rbf_model.train_rbf_models(records, ("paper", "triad"))["triad"].to_dict()))


def test_the_final_fit_alongside_the_evaluation_is_the_fit_before_it(cubic_campaign: pd.DataFrame) -> None:
    result = fit_campaign(cubic_campaign, OPTIONS)
    assert [r.skipped for r in result.evaluation] == [None, None]
    records = segment_records(cubic_campaign, OPTIONS.records)
    assert _models_json(result.models) == _models_json(fit_models(records, OPTIONS))
    assert result.records.step.tolist() == records.step.tolist()
    assert {"fit", "evaluation"} <= set(result.timings_s)


def test_a_final_fit_that_fails_fails_the_fit(cubic_campaign: pd.DataFrame, monkeypatch: pytest.MonkeyPatch) -> None:
    n_all = len(segment_records(cubic_campaign, OPTIONS.records))
    plain = fit_module.fit_models

    def failing(records: Records, options: FitOptions, progress: object = None) -> fit_module.Models:
        if len(records) == n_all:
            raise ValueError("not with every record")
        return plain(records, options)

    monkeypatch.setattr(fit_module, "fit_models", failing)
    with pytest.raises(UserError, match="cannot fit: not with every record"):
        fit_campaign(cubic_campaign, OPTIONS)


@pytest.mark.parametrize("n", [1, 2, 3, 7, 8, 9, 17, 1000, 262_144])
def test_moments_sum_the_rows_as_the_reduction_does(n: int) -> None:
    import numpy as np

    from labrunner.calibration.evaluation import _Moments

    rng = np.random.default_rng(n)
    for x in (rng.normal(size=(n, 6)) * rng.uniform(1e-4, 1e3, 6), np.asfortranarray(rng.normal(size=(n, 6)))):
        m = _Moments(6)
        m.add(x)
        m.add(x[::-1] * 0.5)
        want = (x - x.mean(axis=0)).sum(axis=0) + (x[::-1] * 0.5 - x.mean(axis=0)).sum(axis=0)
        np.testing.assert_array_equal(m.s1, want)
