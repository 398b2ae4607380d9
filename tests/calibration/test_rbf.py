"""RBF network training: forward selection with OLS, GCV, ridge; record means vs raw samples."""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.calibration.rbf import farthest_points, forward_select, gaussian_design, ridge_gcv, train_rbf
from labrunner.calibration.rbf_model import RbfOptions, network_inputs, train_rbf_model
from labrunner.calibration.records import frame_arrays, reference_values, segment_records
from labrunner.imu.model import default_imu_model

from calib_campaigns import make_campaign


def _smooth(x: np.ndarray) -> np.ndarray:
    return np.sin(2.5 * x[:, 0]) * np.exp(-x[:, 1] ** 2) + 0.3 * x[:, 1]


def test_network_learns_a_smooth_function_and_gcv_stops_early():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (600, 2))
    y = _smooth(x) + rng.normal(0, 0.05, 600)
    net = train_rbf(x, y, max_centres=100, max_candidates=200)
    xt = rng.uniform(-0.9, 0.9, (2000, 2))
    err = net.predict(xt, precise=True) - _smooth(xt)
    assert np.sqrt(np.mean(err ** 2)) < 0.03  # well below the 0.05 noise: it generalises
    assert 3 <= net.n_centres < 60  # GCV stopped long before the 100 allowed
    assert net.n_candidates == 200
    # Single precision (the fast path, and a microcontroller's float) stays within its stated bound
    assert np.abs(net.predict(xt) - net.predict(xt, precise=True)).max() <= net.float32_error_bound
    assert net.float32_error_bound < 1e-3 * np.abs(y).max()


def test_pure_noise_selects_nothing_useful():
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (400, 2))
    net = train_rbf(x, rng.normal(0, 1.0, 400), max_centres=50)
    assert net.n_centres <= 5
    assert np.abs(net.predict(x)).std() < 0.3


def test_forward_selection_matches_explicit_least_squares():
    """The incremental OLS bookkeeping equals a direct least-squares fit on the chosen centres."""
    rng = np.random.default_rng(2)
    x = rng.uniform(-1, 1, (300, 2))
    y = _smooth(x)
    cand = x[farthest_points(x, 60)]
    phi = gaussian_design(x, cand, 0.3)
    sel, gcv = forward_select(phi, y, np.ones(300), max_centres=15, patience=100)
    assert len(sel) == 15
    h = phi[:, sel]
    rss = np.sum((y - h @ np.linalg.lstsq(h, y, rcond=None)[0]) ** 2)
    assert gcv <= 300 * rss / (300 - 15) ** 2 * (1 + 1e-6)  # regularised GCV is never worse than lambda = 0
    w, lam, g2 = ridge_gcv(h, y, np.ones(300))
    assert np.sqrt(np.mean((h @ w - y) ** 2)) <= np.sqrt(rss / 300) * 1.05  # ridge costs little fit


def test_candidate_set_does_not_grow_with_samples():
    rng = np.random.default_rng(3)
    for n in (1000, 20000):
        x = rng.uniform(-1, 1, (n, 2))
        net = train_rbf(x, _smooth(x), max_centres=10, max_candidates=150, widths=(0.3,))
        assert net.n_candidates == 150


@pytest.fixture(scope="module")
def raw_campaign():
    # Raw 50 Hz samples: 3 temperatures x 6 orientations x 8 rates x 6 s = 43k rows.
    return make_campaign(default_imu_model(), seed=21, temperatures_c=(-25.0, 15.0, 55.0), record_s=6.0)


def test_training_on_record_means_equals_training_on_raw_samples(raw_campaign):
    """The scalable path (record means weighted by duration) gives the network raw samples give."""
    widths = (0.15, 0.3, 0.6)
    rec = segment_records(raw_campaign)
    model = train_rbf_model(rec, "paper", options=RbfOptions(widths=widths))
    a = frame_arrays(raw_campaign)
    rows = rec.row_record >= 0
    y, temp = a["y"][rows], a["temp"][rows]
    truth = reference_values(a["orientation"][rows], a["rate"][rows])
    lab = rec.row_record[rows]
    for k, net in enumerate(model.networks):
        x_rec = network_inputs("paper", rec.mean, rec.temp_c, k)
        x_raw = network_inputs("paper", y, temp, k)
        # Exact: samples at their record's input give the very same network (least squares and GCV).
        same = train_rbf(x_rec[lab], truth[:, k] - y[:, k], widths=widths, candidates=x_rec,
                         in_offset=net.in_offset, in_scale=net.in_scale)
        assert same.n_centres == net.n_centres and same.width.tolist() == net.width.tolist()
        p_same, p_net = same.predict(x_rec, precise=True), net.predict(x_rec, precise=True)
        # Identical up to the GCV optimiser's convergence (its ridge factor agrees to ~1e-6): 1 ppm of the correction.
        assert np.max(np.abs(p_same - p_net)) < 1e-6 * np.max(np.abs(p_net)), k
        # Raw inputs (each sample's own noisy reading and temperature):
        raw_net = train_rbf(x_raw, truth[:, k] - y[:, k], widths=widths, candidates=x_rec,
                            in_offset=net.in_offset, in_scale=net.in_scale)
        # Same model choices ...
        assert raw_net.width.tolist() == net.width.tolist()
        assert abs(raw_net.n_centres - net.n_centres) <= max(2, 0.2 * net.n_centres)
        # ... and the same function where the data are: the networks differ by far less than
        # the correction they make, and compensate the raw samples equally well.
        p_rec, p_raw = net.predict(x_raw, precise=True), raw_net.predict(x_raw, precise=True)
        target = truth[:, k] - y[:, k]
        scale = np.sqrt(np.mean(target ** 2))
        assert np.sqrt(np.mean((p_rec - p_raw) ** 2)) < 0.02 * scale, k
        e_rec = np.sqrt(np.mean((target - p_rec) ** 2))
        e_raw = np.sqrt(np.mean((target - p_raw) ** 2))
        assert e_rec == pytest.approx(e_raw, rel=0.05), (k, e_rec, e_raw)


def _greedy_maximin(z: np.ndarray, k: int, start: int) -> list[int]:
    """Farthest-point sampling written plainly: squared distances as the row-wise einsum."""
    chosen = [start]
    d = np.einsum("ij,ij->i", z - z[start], z - z[start])
    while len(chosen) < k:
        j = int(np.argmax(d))
        if d[j] <= 0:
            break
        chosen.append(j)
        d = np.minimum(d, np.einsum("ij,ij->i", z - z[j], z - z[j]))
    return chosen


@pytest.mark.parametrize("dim", [1, 2, 3, 4])
def test_farthest_points_are_the_plain_greedy_maximin_choice(dim):
    rng = np.random.default_rng(dim)
    z = np.round(rng.uniform(-1, 1, (3000, dim)), 3)  # quantised, as record means of int16 outputs are
    w = rng.uniform(1, 50, 3000)
    got = farthest_points(z, 200, w)
    assert got.tolist() == _greedy_maximin(z, 200, int(np.argmax(w)))  # the same points in the same order
    few = np.repeat(z[:5], 40, axis=0)
    assert sorted(farthest_points(few, 50).tolist()) == sorted(_greedy_maximin(few, 50, 0))  # stops at 5


@pytest.mark.parametrize("dim", [1, 2, 4])
def test_outside_flags_rows_with_any_input_beyond_the_range_and_margin(dim):
    rng = np.random.default_rng(10 + dim)
    x = rng.uniform(-1.2, 1.2, (5000, dim))
    x[::97, -1] = np.nan  # NaN is never outside (as before: comparisons with NaN are false)
    net = train_rbf(rng.uniform(-1, 1, (400, dim)), rng.normal(size=400), widths=(0.3,), max_centres=5)
    lo, hi = net.input_min, net.input_max
    for margin in (0.0, 0.05):
        span = (hi - lo) * margin
        want = np.any((x < lo - span) | (x > hi + span), axis=1)
        np.testing.assert_array_equal(net.outside(x, margin), want)
    assert net.outside(x, 0.0).any() and not net.outside(x, 0.0).all()


def test_distinct_inputs_past_the_dense_code_space_are_found_in_first_appearance_order():
    from labrunner.calibration import rbf_model

    rng = np.random.default_rng(4)
    n = 20_000
    k = rng.integers(0, 3000, n)
    a = k * 0.01  # 3000 values x 16 overflows 2 n: the codes are refactored on the way
    b = (k % 8 + 8 * rng.integers(0, 2, n)) * 0.5  # 16 values, two per value of a
    t = (k % 2) * 10.0
    found = rbf_model._Distinct({0: a, 1: b, -1: t}).rows((0, 1, -1))
    assert found is not None
    first, inverse = found
    x = np.column_stack([a, b, t])
    np.testing.assert_array_equal(x[first][inverse], x)  # every row is its distinct input
    _, at = np.unique(x, axis=0, return_index=True)
    assert first.size == at.size
    np.testing.assert_array_equal(inverse[np.sort(at)], np.arange(at.size))  # numbered by first appearance
