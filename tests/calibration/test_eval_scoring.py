"""The evaluation's scoring in chunks and the networks' evaluation once per distinct input: both give
what scoring every row at once gives."""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.calibration import rbf_model
from labrunner.calibration.evaluation import SplitResult, score
from labrunner.calibration.rbf import train_rbf
from labrunner.calibration.rbf_model import RbfModel, network_inputs
from labrunner.calibration.records import reference_values


def _arrays(n: int, seed: int = 0) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Quantised outputs (as int16 counts give) about their reference, in 40 records of 6 orientations."""
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(40), n // 40)
    orientation = (labels % 6).astype(np.int8)
    rate = np.where(labels % 4 == 0, 30.0 * (1 + labels % 3), 0.0)
    temp = np.round(rng.uniform(-20, 60, 40)[labels] + rng.normal(0, 0.05, labels.size), 2)
    ref = reference_values(orientation, rate)
    y = np.round((ref + 0.01 * rng.normal(size=ref.shape) + 1e-4 * temp[:, None]) * 4096) / 4096
    a = {"y": y, "temp": temp, "orientation": orientation, "rate": rate, "run": labels // 20,
         "t": np.arange(labels.size) * 0.01}
    return a, labels


def test_chunked_scores_equal_the_statistics_of_the_whole_error_array():
    a, labels = _arrays(4000)
    rows = np.arange(0, labels.size, 3)
    whole = SplitResult("x", "x")
    score({}, a, rows, labels, whole, chunk=10 ** 9)
    parts = SplitResult("x", "x")
    score({}, a, rows, labels, parts, chunk=97)
    err = a["y"][rows] - reference_values(a["orientation"][rows], a["rate"][rows])
    for got in (whole.samples["raw"], parts.samples["raw"]):
        np.testing.assert_allclose(got.mean, err.mean(axis=0), rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(got.std, err.std(axis=0), rtol=1e-9)
        np.testing.assert_allclose(got.rms, np.sqrt(np.mean(err ** 2, axis=0)), rtol=1e-9)
        assert got.n == rows.size
    lab = labels[rows]
    rec = np.array([err[lab == r].mean(axis=0) for r in np.unique(lab)])
    np.testing.assert_allclose(parts.records["raw"].rms, np.sqrt(np.mean(rec ** 2, axis=0)), rtol=1e-9)
    static = np.abs(a["rate"][rows]) < 0.05
    v = a["y"][rows][static]
    norm = np.linalg.norm(v[:, :3], axis=1) - 1.0
    check = parts.static["raw"]
    assert check.n == int(static.sum())
    assert check.accel_norm_err_mean == pytest.approx(norm.mean(), rel=1e-9)
    assert check.accel_norm_err_std == pytest.approx(norm.std(), rel=1e-9)
    assert check.gyro_norm_mean == pytest.approx(np.linalg.norm(v[:, 3:], axis=1).mean(), rel=1e-9)


def test_time_block_offsets_in_chunks_equal_the_offsets_removed_from_the_whole_array():
    a, labels = _arrays(4000, seed=3)
    a["y"] = a["y"] + np.where(a["run"] == 1, 0.02, -0.01)[:, None]  # a turn-on bias per run
    test, train = np.arange(1, labels.size, 2), np.arange(0, labels.size, 2)
    res = SplitResult("x", "x")
    score({}, a, test, labels, res, offset_rows=train, chunk=101)
    err = a["y"] - reference_values(a["orientation"], a["rate"])
    for r in (0, 1):
        sel = a["run"][test] == r
        off = err[train][a["run"][train] == r].mean(axis=0)
        err[test[sel]] -= off
    np.testing.assert_allclose(res.samples["raw"].mean, err[test].mean(axis=0), rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(res.samples["raw"].rms, np.sqrt(np.mean(err[test] ** 2, axis=0)), rtol=1e-9)


@pytest.mark.parametrize("variant", ["paper", "triad", "hybrid"])
def test_networks_once_per_distinct_input_give_every_row_its_own_evaluation(variant, monkeypatch):
    a, labels = _arrays(24000, seed=1)
    y, temp = a["y"], a["temp"]
    target = 0.001 * np.sin(temp / 15.0)[:, None] + 0.002 * np.cos(3 * y)
    networks = []
    for k in range(6):
        x = network_inputs(variant, y[:3000], temp[:3000], k)
        networks.append(train_rbf(x, target[:3000, k], max_centres=12, max_candidates=60))
    assert all(net.n_centres > 0 for net in networks)
    model = RbfModel(variant=variant, networks=networks, t_min_c=-10.0, t_max_c=50.0)
    fast = model.compensate(y, temp)
    monkeypatch.setattr(rbf_model, "DISTINCT_MIN_ROWS", 10 ** 12)  # every row evaluated
    direct = model.compensate(y, temp)
    # float32 kernels: the same to their rounding (a few 1e-7 of the correction)
    np.testing.assert_allclose(fast.values, direct.values, rtol=0, atol=1e-6 * np.abs(direct.values - y).max())
    np.testing.assert_array_equal(fast.extrapolated, direct.extrapolated)
    assert 0 < fast.extrapolated.mean() < 1  # inputs on both sides of the range


def test_distinct_inputs_found_and_too_many_left_alone():
    rng = np.random.default_rng(2)
    n = 20000
    cols = {0: rng.integers(0, 50, n) * 0.5, 1: rng.normal(size=n), -1: rng.integers(0, 30, n) * 0.1}
    found = rbf_model._Distinct(cols).rows((0, -1))
    assert found is not None
    first, inverse = found
    assert first.size <= 50 * 30
    np.testing.assert_array_equal(cols[0][first][inverse], cols[0])
    np.testing.assert_array_equal(cols[-1][first][inverse], cols[-1])
    assert rbf_model._Distinct(cols).rows((1, -1)) is None  # every row distinct: no gain
    with_nan = dict(cols)
    with_nan[0] = np.where(np.arange(n) == 5, np.nan, cols[0])
    assert rbf_model._Distinct(with_nan).rows((0, -1)) is None  # NaN inputs take the direct path
