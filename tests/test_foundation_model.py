"""The IMU error model, the recursions under it, and the simulated physics."""

import numpy as np
import pytest

from labrunner.imu.model import (
    ImuInputs,
    ImuModel,
    ModelState,
    baseline_design,
    default_imu_model,
    orientation_index,
    up_vector,
)
from labrunner.imu.recursions import first_order_lag, ltv_first_order, play_state
from labrunner.sims.chamber_plant import ChamberParams, ChamberPlant
from labrunner.sims.table_plant import TablePlant


def _loop(a, b, y0):
    out, y = [], y0
    for ak, bk in zip(a, b, strict=True):
        y = ak * y + bk
        out.append(y)
    return np.array(out)


def test_ltv_recursion_matches_loop_including_resets():
    rng = np.random.default_rng(3)
    a = rng.uniform(0.0, 1.0, 5000)
    a[[10, 400]] = 0.0  # a full reset
    a[1000:3000] = 1.0 - 1e-7  # slow decay over a long stretch
    b = rng.normal(size=5000)
    # Float accumulation over 2000 near-unity steps: agreement to ~1e-8 of values of order 10.
    assert np.allclose(ltv_first_order(a, b, 0.7), _loop(a, b, 0.7), rtol=1e-9, atol=1e-7)


def test_first_order_lag_ramp_and_chunking():
    t = np.arange(0.0, 3000.0, 0.02)
    x = 0.01 * t  # 0.6 C/min
    y = first_order_lag(t, x, 300.0)
    assert x[-1] - y[-1] == pytest.approx(0.01 * 300.0 * (1 - np.exp(-3000 / 300.0)), rel=1e-6)
    k = 77777
    y1 = first_order_lag(t[:k], x[:k], 300.0)
    y2 = first_order_lag(t[k:], x[k:], 300.0, y0=y1[-1], x0=x[k - 1], t0=t[k - 1])
    assert np.allclose(np.concatenate([y1, y2]), y, atol=1e-9)


def test_play_state_keeps_branch_through_a_soak():
    temp = np.concatenate([np.linspace(0, 20, 200), np.full(100, 20.0), np.linspace(20, 10, 100), np.full(50, 10.0)])
    h = play_state(temp, travel=2.0)
    assert h[299] > 0.99  # still on the heating branch after the soak
    assert h[-1] < -0.98


def test_orientation_geometry():
    assert up_vector("x_down").tolist() == [-1.0, 0.0, 0.0]
    assert orientation_index(["z_up", "y_down"]).tolist() == [4, 3]
    with pytest.raises(ValueError, match="sideways"):
        up_vector("sideways")


def test_default_model_magnitudes_like_the_paper():
    m = default_imu_model()
    bz = m.accel.bias_at(np.array([-25.0, 55.0]))[:, 2]
    assert bz[0] == pytest.approx(0.110, abs=1e-6) and bz[1] == pytest.approx(-0.080, abs=1e-6)
    slope = (m.gyro.bias_at(np.array([55.0])) - m.gyro.bias_at(np.array([-25.0]))) / 80.0
    assert np.all(np.abs(slope) < 0.035) and np.all(np.abs(slope) > 0.01)
    sigma = m.noise_sigma(50.0)
    assert sigma[0] == pytest.approx(220e-6 * 5.0) and sigma[3] == pytest.approx(0.03 * 5.0)


def _inputs(n=2000, temp=None, orientation="z_up", rate=50.0):
    t = np.arange(n) * 0.02
    up = up_vector(orientation)
    return ImuInputs(t_s=t, run=np.ones(n, int), t_on_s=t, temp_c=np.full(n, 30.0) if temp is None else temp,
                     force_g=np.tile(up, (n, 1)), rate_dps=np.tile(up * rate, (n, 1)))


def test_baseline_design_reproduces_model_error():
    m = default_imu_model()
    inp = _inputs(temp=np.linspace(-20, 50, 2000))
    for triad, u, sl in ((m.accel, inp.force_g, slice(0, 3)), (m.gyro, inp.rate_dps, slice(3, 6))):
        pred = baseline_design(inp.temp_c, u) @ triad.coefficients().T
        err, _ = m.deterministic_error(inp)
        assert np.allclose(pred, err[:, sl])


def test_effects_switch_on_and_stream_in_chunks():
    base = default_imu_model(seed=4)
    model = base.with_effects(
        thermal_lag={"tau_s": 200.0},
        hysteresis={"width": {"gyro_x": 0.05}},
        warmup={"tau_s": 300.0, "amplitude": {"accel_x": 0.003}},
        turn_on_bias={"sigma": {"gyro_z": 0.02}},
        g_sensitivity={"matrix_dps_per_g": [[0, 0, 0.01], [0, 0, 0], [0, 0, 0]]},
        scale_nonlinearity={"k2_per_dps": {"gyro_z": 1e-5}},
        temperature_nonlinearity={"amplitude": {"accel_y": 0.004}},
    )
    inp = _inputs(n=6000, temp=np.linspace(10, 20, 6000))
    e0, _ = base.deterministic_error(inp)
    e1, _ = model.deterministic_error(inp)
    assert np.all(np.abs(e1 - e0).max(axis=0) > 1e-4)
    # Streaming in two chunks with carried state equals one batch.
    half = 3000
    parts = [ImuInputs(**{k: (v[:half] if k != "x" else v) for k, v in inp.__dict__.items()}),
             ImuInputs(**{k: v[half:] for k, v in inp.__dict__.items()})]
    a, st = model.deterministic_error(parts[0])
    b, _ = model.deterministic_error(parts[1], st)
    assert np.allclose(np.concatenate([a, b]), e1, atol=1e-12)


def test_model_round_trips_through_json(tmp_path):
    model = default_imu_model(seed=9).with_effects(warmup={"tau_s": 400.0, "amplitude": {"gyro_y": 0.1}})
    path = tmp_path / "imu.json"
    model.save(path)
    back = ImuModel.load(path)
    inp = _inputs()
    assert np.allclose(back.deterministic_error(inp)[0], model.deterministic_error(inp)[0])
    with pytest.raises(ValueError, match="unknown effect"):
        ImuModel.from_dict({"effects": {"magic": {}}})
    with pytest.raises(ValueError, match="unknown channel"):
        model.with_effects(warmup={"amplitude": {"gyro_w": 1.0}})


def test_simulation_is_seeded():
    m = default_imu_model()
    inp = _inputs()
    a, _ = m.simulate(inp, 50.0, np.random.default_rng(1), ModelState())
    b, _ = m.simulate(inp, 50.0, np.random.default_rng(1), ModelState())
    assert np.array_equal(a, b)


def test_chamber_ramps_at_a_plausible_rate_with_small_overshoot():
    plant = ChamberPlant(ChamberParams(fluctuation_c=0.0))
    plant.advance_to(60)
    plant.set_setpoint(55.0)
    temps = []
    for k in range(1, 3601):
        plant.advance_to(60 + k)
        temps.append(plant.air_c)
    temps = np.array(temps)
    rate = np.max(np.diff(temps)) * 60.0
    assert 1.0 < rate < 6.0  # a few degrees per minute
    assert 0.0 < temps.max() - 55.0 < 1.0  # a little overshoot
    assert abs(temps[-1] - 55.0) < 0.05


def test_chamber_with_failed_heater_cannot_heat():
    plant = ChamberPlant(ChamberParams(fluctuation_c=0.0))
    plant.heater_failed = True
    plant.set_setpoint(55.0)
    plant.advance_to(3600)
    assert plant.air_c < plant.p.ambient_c + 0.1


def test_table_is_acceleration_limited_and_accurate():
    table = TablePlant()
    table.command(0.0, 100.0)
    r = table.rate_at(np.array([0.5, 2.0, 10.0]))
    assert r[0] == pytest.approx(50.0, rel=0.01)
    assert abs(r[1] / 100.0 - 1) <= 1e-4 and abs(r[2] / 100.0 - 1) <= 1e-4
