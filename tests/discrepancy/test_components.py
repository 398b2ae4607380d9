"""The pieces the diagnosis rests on, each against an independent computation."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from labrunner.discrepancy.blocks import Blocks
from labrunner.discrepancy.crossval import cross_validate
from labrunner.discrepancy.drift import FoldFilters, riccati
from labrunner.discrepancy.measurements import Measurements
from labrunner.discrepancy.temperature import ROOM_C, branch_state, dequantize
from labrunner.imu.effects.turn_on_bias import offsets_roughness, turn_on_sigma
from labrunner.imu.model import ImuInputs, ImuModel, default_imu_model
from labrunner.imu.recursions import play_state


def _blocks(t: np.ndarray, count: np.ndarray, run: np.ndarray) -> Blocks:
    start = np.r_[0, np.cumsum(count)[:-1]]
    new_run = np.r_[True, run[1:] != run[:-1]]
    return Blocks(start=start, count=count, weight=count.astype(float), t_s=t, run=run, new_run=new_run, block_s=10.0)


def _kalman_innovations(y, dt, r, rho, observed, diffuse=1e20):
    """Textbook scalar local-level filter: scaled innovations of the observed blocks."""
    level, p, out = 0.0, diffuse, []
    for k in range(y.size):
        pp = p + rho * dt[k]
        if not observed[k]:
            p = pp
            continue
        f = pp + r[k]
        out.append((y[k] - level) / np.sqrt(f))
        gain = pp / f
        level += gain * (y[k] - level)
        p = pp * r[k] / f  # (not pp * (1 - gain): with a diffuse pp, 1 - gain rounds to 0)
    out[0] = 0.0  # against a diffuse level the first innovation says nothing
    return np.array(out)


def test_fold_filters_whiten_exactly_like_a_kalman_filter_that_skips_the_held_out_blocks():
    rng = np.random.default_rng(1)
    m = 300
    t = np.cumsum(rng.uniform(5, 40, m))
    count = rng.integers(1, 30, m)
    folds = (np.arange(m) // 17) % 5
    y = np.cumsum(rng.normal(0, 0.05, m)) + rng.normal(0, 1, m) / np.sqrt(count)
    ff = FoldFilters(_blocks(t, count, np.ones(m, int)), 3e-3, folds, 5)
    w = ff.whiten(np.column_stack([y, 2 * y]))
    dt = np.r_[0.0, np.diff(t)]
    expected = _kalman_innovations(y, dt, 1.0 / count, 3e-3, np.ones(m, bool))
    assert np.allclose(w.full[:, 0], expected, atol=1e-9)
    assert np.allclose(w.full[:, 1], 2 * expected, atol=1e-9)
    for f in range(5):
        expected = _kalman_innovations(y, dt, 1.0 / count, 3e-3, folds != f)
        assert np.allclose(w.folds[f][:, 0], expected, atol=1e-9)


def test_held_out_score_is_the_conditional_gaussian_likelihood_of_the_held_out_blocks():
    rng = np.random.default_rng(2)
    m, rho = 60, 0.02
    t = np.cumsum(rng.uniform(5, 20, m))
    count = rng.integers(2, 10, m)
    folds = (np.arange(m) // 6) % 3
    y = np.cumsum(rng.normal(0, 0.3, m)) + rng.normal(0, 1, m) / np.sqrt(count)
    ff = FoldFilters(_blocks(t, count, np.ones(m, int)), rho, folds, 3)
    w = ff.whiten(y[:, None])
    # Brute force: level = a + random walk from the first block, a diffuse (large prior).
    prior = 1e4  # effectively diffuse at this data scale, and still well conditioned
    walk = rho * np.minimum.outer(t - t[0], t - t[0])
    cov = prior + walk + np.diag(1.0 / count)
    for f in range(3):
        h, tr = folds == f, folds != f
        k = cov[np.ix_(h, tr)] @ np.linalg.inv(cov[np.ix_(tr, tr)])
        resid = y[h] - k @ y[tr]
        s = cov[np.ix_(h, h)] - k @ cov[np.ix_(tr, h)]
        brute = resid @ np.linalg.solve(s, resid)
        score = np.sum(w.full ** 2) - np.sum(w.folds[f] ** 2)
        assert score == pytest.approx(brute, rel=1e-5)


def test_cross_validation_from_grams_equals_refitting_without_each_fold():
    rng = np.random.default_rng(3)
    m, p = 400, 5
    x = rng.normal(size=(m, p))
    y = x @ rng.normal(size=p) + rng.normal(size=m)
    folds = (np.arange(m) // 20) % 4
    a = np.column_stack([x, y])
    full = a.T @ a
    train = np.stack([a[folds != f].T @ a[folds != f] for f in range(4)])
    cv = cross_validate(full, train, m)
    sse = 0.0
    for f in range(4):
        b = np.linalg.lstsq(x[folds != f], y[folds != f], rcond=None)[0]
        sse += np.sum((y[folds == f] - x[folds == f] @ b) ** 2)
        assert np.allclose(cv.betas[f], b)
    assert cv.sse == pytest.approx(sse, rel=1e-9)
    assert cv.n_params == p


def test_riccati_restarts_the_level_at_power_ons():
    gain, _ = riccati(np.full(6, 10.0), np.full(6, 0.5), np.array([0.0]), reset=np.array([1, 0, 0, 1, 0, 0], bool))
    assert gain[0, 0] == pytest.approx(1.0) and gain[3, 0] == pytest.approx(1.0)  # diffuse: take the sample
    assert gain[1, 0] == pytest.approx(0.5) and gain[4, 0] == pytest.approx(0.5)  # then average


def test_dequantize_recovers_a_ramp_and_does_not_favour_the_approach_direction():
    t = np.arange(0.0, 4000.0)
    true = np.where(t < 1000, 10 + 0.01 * t, 20.0) + 0.003 * np.sin(t / 40)  # ramp then soak
    true = np.concatenate([true, true[::-1]])  # and back down: cooling into the same soak
    t = np.arange(true.size, dtype=float)
    q = 0.25
    logged = np.round(true / q) * q
    est = dequantize(t, logged, np.ones(t.size, int), q, settle_s=q / 0.01)
    ramp = np.abs(np.gradient(true)) > 0.005
    assert np.sqrt(np.mean((est - true)[ramp] ** 2)) < 0.2 * np.sqrt(np.mean((logged - true)[ramp] ** 2))
    soak = ~ramp
    heating, cooling = soak & (t < 4000), soak & (t >= 4000)
    assert abs(np.mean(est[heating] - true[heating]) - np.mean(est[cooling] - true[cooling])) < 0.25 * q


def test_branch_state_goes_through_room_temperature_at_a_remount():
    temp = np.array([-20.0, -20.0, -5.0, -5.0, 50.0, 50.0])
    h = branch_state(temp, 2.0, remounts=np.array([4]))
    # The log starts in a soak at -20: reached from room temperature, i.e. by cooling.
    assert h[0] == pytest.approx(-1.0, abs=1e-6)
    assert h[2] > 0.99
    # Without the remount the 50 degC soak would look like a plain continuation of heating;
    # with it the path is -5 -> 23 -> 50: still heating, and the same as play_state says.
    assert h[4] == pytest.approx(play_state(np.array([ROOM_C, -20, -20, -5, -5, ROOM_C, 50]), 2.0)[-1])


def test_turn_on_sigma_sees_only_the_offsets_the_rest_of_the_model_cannot_explain():
    rng = np.random.default_rng(4)
    runs, sigma = 40, 0.05
    # Runs 0..39 at 4 temperatures; the rest of the model explains a constant per temperature.
    temperature = np.arange(runs) % 4
    d = np.eye(runs)[:, 1:]  # per-run columns, run 0 the reference
    other = np.eye(4)[temperature]
    estimates = []
    for _ in range(200):
        offsets = rng.normal(0, sigma, runs)
        x = np.column_stack([other, d])
        beta = np.linalg.lstsq(x, offsets, rcond=None)[0]
        g = x.T @ x
        schur = g[4:, 4:] - g[4:, :4] @ np.linalg.solve(g[:4, :4], g[:4, 4:])
        estimates.append(turn_on_sigma(beta[4:], schur, np.zeros((runs - 1, runs - 1))))
    assert np.mean(estimates) == pytest.approx(sigma, rel=0.05)


def test_offsets_roughness_tells_independent_offsets_from_a_drift():
    rng = np.random.default_rng(5)
    schur = np.eye(35)
    iid = [offsets_roughness(rng.normal(size=35), schur) for _ in range(50)]
    walk = [offsets_roughness(np.cumsum(rng.normal(size=35)), schur) for _ in range(50)]
    assert 1.7 < np.mean(iid) < 2.3 and min(iid) > 1.0
    assert max(walk) < 1.0


def test_measurements_keep_runs_in_order_when_the_clock_restarts_per_run():
    rows = []
    for run, orient in ((1, "z_up"), (2, "z_down")):
        for k in range(5):
            rows.append({"t_s": float(k), "run": run, "orientation": orient, "chamber_c": 20.0, "imu_temp_c": 25.0,
                         "table_rate_dps": 0.0, "ax_g": 0.0, "ay_g": 0.0, "az_g": 1.0 if run == 1 else -1.0,
                         "gx_dps": 0.0, "gy_dps": 0.0, "gz_dps": 0.0})
    meas = Measurements.from_frame(pd.DataFrame(rows))
    assert list(meas.run) == [1] * 5 + [2] * 5
    assert np.allclose(meas.t_on_s, list(range(5)) * 2)
    assert np.allclose(meas.error, 0.0)


# --- the sims additions ------------------------------------------------------------------


def _inputs(n, rate_dps, up=(0, 0, 1.0), run=1):
    up = np.asarray(up)
    return ImuInputs(t_s=np.arange(n, dtype=float), run=np.full(n, run), t_on_s=np.arange(n, dtype=float),
                     temp_c=np.full(n, 25.0), force_g=np.tile(up, (n, 1)), rate_dps=np.outer(np.full(n, rate_dps), up))


def test_lever_arm_adds_the_centripetal_acceleration_on_the_horizontal_axes():
    base = default_imu_model()
    model = base.with_effects(lever_arm={"r_m": [0.05, -0.02, 0.03]})
    inp = _inputs(3, 100.0)
    extra = model.deterministic_error(inp)[0] - base.deterministic_error(inp)[0]
    w2 = np.deg2rad(100.0) ** 2
    assert np.allclose(extra[:, 0], -w2 * 0.05 / 9.80665)
    assert np.allclose(extra[:, 1], w2 * 0.02 / 9.80665)
    assert np.allclose(extra[:, 2:], 0.0)  # along the rotation axis, and the gyros: nothing
    back = ImuModel.from_dict(model.to_dict())
    assert back.effects["lever_arm"].r_m == [0.05, -0.02, 0.03]
    with pytest.raises(ValueError, match="r_m must be 3 numbers"):
        base.with_effects(lever_arm={"r_m": [1.0, 2.0]})


def test_turn_on_offsets_can_be_pinned_per_run_and_survive_json():
    model = default_imu_model(seed=3).with_effects(
        turn_on_bias={"sigma": {"gyro_x": 0.1}, "offsets": {"2": {"gyro_x": 0.25, "accel_z": -0.002}}})
    back = ImuModel.from_dict(model.to_dict())
    offsets = back.run_offsets(np.array([1, 2, 2, 3]))
    assert offsets[1, 3] == 0.25 and offsets[2, 5 - 3] == -0.002
    assert offsets[0, 3] != 0.0 and offsets[0, 3] != offsets[3, 3]  # other runs still drawn from sigma
    unpinned = default_imu_model(seed=3).with_effects(turn_on_bias={"sigma": {"gyro_x": 0.1}})
    assert np.allclose(unpinned.run_offsets(np.array([1, 3])), back.run_offsets(np.array([1, 3])))
    with pytest.raises(ValueError, match="unknown channel"):
        default_imu_model().with_effects(turn_on_bias={"offsets": {"1": {"gyro_q": 1.0}}})
