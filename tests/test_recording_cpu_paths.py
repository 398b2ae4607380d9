"""The recording's CPU shortcuts (issue 15, target 1) give the bits of what they replace: the model's outputs
added column by column, the baseline's broadcast reference multiplied as a scalar, the monitor's full bins
summed in one reduction, the temperature history's horizons looked up run by run, the table's rate times the
up vector column by column."""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.imu.baseline import thermal_powers
from labrunner.imu.inputs import ImuInputs
from labrunner.imu.model import ModelState, default_imu_model
from labrunner.runner.monitor import _bin_means, _full_bin_means, average_block
from labrunner.sims.world import SimLabConfig, SimWorld


def _simulate_before(model, inputs, rate_hz, rng, state):  # type: ignore[no-untyped-def]
    """`ImuModel.simulate` as it was: truth + err into a new array by halves, then the noise."""
    err, new = model.deterministic_error(inputs, state, rng)
    n = err.shape[0]
    out = np.empty((n, 6))
    np.add(np.asarray(inputs.force_g, float).reshape(n, 3), err[:, :3], out=out[:, :3])
    np.add(np.asarray(inputs.rate_dps, float).reshape(n, 3), err[:, 3:], out=out[:, 3:])
    if rng is not None:
        noise = rng.standard_normal(out.shape)
        noise *= model.noise_sigma(rate_hz)[None, :]
        out += noise
    return out, new


def _inputs(n: int, rng: np.random.Generator, broadcast: bool) -> ImuInputs:
    t = 100.0 + np.arange(n) / 50.0
    up = np.array([0.0, -1.0, 0.0])
    force = np.broadcast_to(up, (n, 3)) if broadcast else rng.normal(0, 1, (n, 3))
    rate = rng.normal(0, 80, n)
    rate[::7] = -0.0
    return ImuInputs(t_s=t, run=np.ones(n, dtype=np.int64), t_on_s=t - 90.0, temp_c=rng.uniform(-30, 60, n),
                     force_g=force, rate_dps=rate[:, None] * up[None, :] if broadcast else rng.normal(0, 50, (n, 3)))


@pytest.mark.parametrize("broadcast", [True, False])
@pytest.mark.parametrize("noise", [True, False])
def test_simulate_equals_the_sum_by_halves(broadcast: bool, noise: bool) -> None:
    model = default_imu_model(seed=4)
    for n in (0, 1, 2, 1500):
        inputs = _inputs(n, np.random.default_rng(n), broadcast)
        rng_a, rng_b = (np.random.default_rng(9), np.random.default_rng(9)) if noise else (None, None)
        got, _ = model.simulate(inputs, 50.0, rng_a, ModelState())
        want, _ = _simulate_before(model, inputs, 50.0, rng_b, ModelState())
        assert got.shape == want.shape and got.tobytes() == want.tobytes()


def test_baseline_of_a_broadcast_reference_equals_the_column_product() -> None:
    model = default_imu_model()
    rng = np.random.default_rng(3)
    powers = thermal_powers(rng.uniform(-30, 60, 900))
    for up in ([0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.3, -0.0, 0.7], [np.nan, 0.0, 0.0]):
        ref = np.broadcast_to(np.array(up), (900, 3))
        full = np.array(ref)  # the same reference as an (n, 3) array: the column product
        for triad in (model.accel, model.gyro):
            assert triad.error_at_powers(powers, ref).tobytes() == triad.error_at_powers(powers, full).tobytes()


def _columns(n: int, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    accel = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-3, 6, (n, 3))
    accel[rng.random((n, 3)) < 0.2] = -0.0
    gyro = np.rint(rng.normal(0, 300, (n, 3))) * 0.00875
    gyro[::11, 1] = np.nan
    temp = rng.normal(25, 0.01, n)
    temp[: max(1, n // 3)] = -0.0  # a bin of negative zeros: bincount's sum from 0.0 is +0.0
    return accel, gyro, temp, 1e5 + np.arange(n) / 50.0


@pytest.mark.parametrize("per_bin", [1, 2, 7, 8, 9, 50, 129])
@pytest.mark.parametrize("n_bins", [2, 3, 8, 30, 101])
def test_full_bins_summed_at_once_equal_the_bincount_means(per_bin: int, n_bins: int) -> None:
    n = per_bin * n_bins
    columns = _columns(n, np.random.default_rng(per_bin * 1000 + n_bins))
    offs = np.arange(n)
    fast = _full_bin_means(offs, per_bin, columns)
    assert fast is not None
    for got, want in zip(fast, _bin_means(offs // per_bin, columns), strict=True):
        assert got.shape == want.shape and got.tobytes() == want.tobytes()


def test_bins_that_are_not_all_full_take_the_bincount_path() -> None:
    offs = np.arange(100)
    columns = _columns(100, np.random.default_rng(1))
    assert _full_bin_means(offs, 100, columns) is None  # one bin: numpy would sum it pairwise
    assert _full_bin_means(offs[:99], 50, tuple(c[:99] for c in columns)) is None  # a partial bin
    assert _full_bin_means(np.delete(np.arange(101), 40), 50, columns) is None  # a frame lost
    assert _full_bin_means(offs + 1, 50, columns) is None  # not from the stretch's first frame


def test_a_monitor_stretch_is_the_bincount_means() -> None:
    from labrunner.drivers.protocols import ImuRecord

    rng = np.random.default_rng(8)
    n = 1500
    accel, gyro, temp, _ = _columns(n, rng)
    rec = ImuRecord(counter=np.arange(401, 401 + n), accel_g=accel, gyro_dps=gyro, temp_c=temp, expected=n,
                    dropped=0, corrupt=0, lsb=None)
    block = average_block(rec, start=400, t0_s=1234.5, rate_hz=50.0, average_s=1.0, run=2, orientation="y_up",
                          chamber=np.zeros((2, 2)))
    assert block is not None
    offs = rec.counter - 401
    t = (1234.5 + (offs + 1) / 50.0).astype(float)
    want = _bin_means(offs // 50, (accel, gyro, temp, t))
    for got, exp in zip((block.accel_g, block.gyro_dps, block.temp_c), want[:3], strict=True):
        assert got.tobytes() == exp.tobytes()
    assert block.t0_s == float(want[3][0])


def _history_per_time(world: SimWorld, times: np.ndarray, column: int, until: np.ndarray) -> np.ndarray:
    """`SimWorld._history` with a horizon looked up for every time (as it was)."""
    ht = world._hist[: world._n, 0]
    out = np.interp(times, ht, world._hist[: world._n, column])
    last = np.searchsorted(ht, until + 1e-9, side="right") - 1
    after = times > ht[last]
    out[after] = world._hist[last[after], column]
    return out


def test_horizons_looked_up_run_by_run_equal_the_lookup_per_time() -> None:
    world = SimWorld(SimLabConfig(seed=2), start_t=0.0)
    world.chamber.set_setpoint(-20.0)
    world.advance(4000.0)
    rng = np.random.default_rng(6)
    for runs in (1, 3, 40, 63, 64, 65, 400):
        times = np.sort(rng.uniform(100.0, 3990.0, 1500))
        edges = np.sort(rng.choice(np.arange(1, 1500), runs - 1, replace=False)) if runs > 1 else np.zeros(0, int)
        bounds = [0, *edges.tolist(), 1500]
        until = np.concatenate([np.full(b - a, times[b - 1] + rng.uniform(-1.5, 0.0)) for a, b in
                                zip(bounds[:-1], bounds[1:])])
        for column in (1, 2):
            got = world._history(times, column, until)
            assert got.tobytes() == _history_per_time(world, times, column, until).tobytes()


def test_the_table_rate_times_the_up_vector_column_by_column() -> None:
    world = SimWorld(SimLabConfig(seed=1, orientation="y_down"), start_t=0.0)
    world.table.command(0.0, -73.0)
    times = np.arange(500) / 50.0
    world.advance(float(times[-1]))
    inputs = world.imu_inputs(times)
    want = world.table.rate_at(times)[:, None] * np.array([0.0, -1.0, 0.0])[None, :]
    assert inputs.rate_dps.tobytes() == want.tobytes()


def test_hot_statements_as_driver_sql_write_and_read_what_execute_does(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Every hot statement through `_hot` (SQLite: compiled once, run as driver SQL) against `execute`: the
    same rows in two stores, the same reads, and the engine's events still see each statement."""
    from sqlalchemy import event

    from labrunner import store as st
    from labrunner.procedure import parse_procedure
    from tests.campaign.conftest import TINY

    p = parse_procedure(TINY, "tiny.yaml")
    seen: list[str] = []
    results = []
    for name, run in (("hot", st._hot), ("execute", lambda conn, stmt, params: conn.execute(stmt, params))):
        s = st.Store.create(tmp_path / f"{name}.db")
        cid = s.new_campaign(name=p.name, procedure_text=p.text, procedure_path=None, procedure_sha256=p.sha256,
                             lab_config={}, mode="sim", sim_config={}, clock_t0=0.0, plan=p.steps(),
                             lease_token="tok")
        event.listen(s.engine, "before_cursor_execute", lambda *a, _n=name: seen.append(_n))
        block = st.SampleBlock(kind="record", step_idx=1, run=2, orientation="x_up", t0_s=5.0, rate_hz=50.0,
                               counter=np.arange(7), accel_g=np.ones((7, 3)), gyro_dps=np.zeros((7, 3)),
                               temp_c=np.full(7, 21.5), chamber=np.array([[5.0, 20.0]]), table=np.zeros((1, 2)),
                               lsb=(0.001, 0.00875, 0.01))
        with s.transaction() as conn:
            kept = run(conn, st._RENEW, {"w_id": cid, "w_token": "tok", "lease_wall": 12.5, "clock_last": 3.0})
            lost = run(conn, st._RENEW, {"w_id": cid, "w_token": "other", "lease_wall": 13.5})
            run(conn, st._INSERT_BLOCK, s._block_row(cid, block))
            run(conn, st._ATTEMPT, {"w_campaign": cid, "w_idx": 1})
            run(conn, st._UPDATE_STEP, {"w_campaign": cid, "w_idx": 1, "status": "done", "n_samples": 7,
                                        "imu_temp_c": None})
            run(conn, st._INSERT_EVENT, {"campaign_id": cid, "t_s": 1.0, "wall": 2.0, "kind": "info", "state": None,
                                         "step_idx": 1, "message": "m", "detail": None})
            nxt = run(conn, st._NEXT_STEP, {"w_campaign": cid, "w_from": 0}).scalar()
            pending = run(conn, st._PENDING, {"w_campaign": cid}).scalar()
        with s.reading() as conn:
            rows = {t: [tuple(r) for r in conn.exec_driver_sql(f"SELECT * FROM {t} ORDER BY 1, 2")]
                    for t in ("steps", "sample_blocks", "events")}
            rows["campaigns"] = [tuple(r) for r in conn.exec_driver_sql(
                "SELECT lease_token, lease_wall, clock_last FROM campaigns")]  # the rest holds the wall time
        results.append((kept.rowcount, lost.rowcount, nxt, pending, rows))
        s.close()
    assert results[0] == results[1]
    assert results[0][:3] == (1, 0, 0)
    assert seen.count("hot") == seen.count("execute") >= 8


def test_syncs_counted_equal_the_positions_found() -> None:
    from labrunner.drivers.imu_frames import SYNC, _count_syncs, _sync_positions

    rng = np.random.default_rng(12)
    for size in (0, 1, 2, 3, 20, 41, 1000, 1001):
        for _ in range(20):
            buf = rng.choice(np.frombuffer(SYNC + b"\x00\xa5", dtype=np.uint8), size).astype(np.uint8)
            assert _count_syncs(buf) == _sync_positions(buf).size


def test_the_chunks_of_a_window_found_from_the_newest_back_are_those_that_hold_it() -> None:
    from labrunner.drivers.imu_serial import _chunks_between

    rng = np.random.default_rng(4)
    chunks, first = [], 0
    for _ in range(40):  # in counter order, apart by gaps of lost frames now and then
        size = int(rng.integers(1, 300))
        chunks.append((np.arange(first, first + size), None, None, None))
        first += size + int(rng.integers(0, 3)) * int(rng.integers(1, 100))
    for start in range(-5, int(chunks[-1][0][-1]) + 5, 37):
        for n in (0, 1, 50, 1500):
            want = [ch for ch in chunks if ch[0][-1] > start and ch[0][0] <= start + n]
            assert _chunks_between(chunks, start, start + n) == want  # type: ignore[arg-type]


def test_chamber_registers_cached_by_value_keep_the_sign_of_zero() -> None:
    from labrunner.clock import VirtualClock
    from labrunner.sims.chamber_server import ChamberServer

    world = SimWorld(SimLabConfig(seed=0), start_t=0.0)
    server = ChamberServer(world, VirtualClock(start=0.0), "watlow_f4t", transport="memory")
    try:
        for value in (0.0, -0.0, 0.0, 12.5, 12.5, -3.25, -0.0):
            for output in (False, True):
                got = server._encoded(601, value, output)
                assert got == server.profile.encode(value, output=output, units=server.units)
    finally:
        server.close()


def _steps_with_builtins(plant, n: int, dt: float) -> list[tuple[float, float]]:  # type: ignore[no-untyped-def]
    """`ChamberPlant.run_steps` as it was, with min() and max() (the reference for the written-out ones)."""
    import math

    from labrunner.sims.chamber_plant import _NORMALS_BLOCK

    p = plant.p
    setpoint, air, integral, fluct, t = plant.setpoint_c, plant.air_c, plant.integral, plant._fluct, plant.t
    kp, ti, ambient, loss_tau = p.kp_pct_per_c, p.ti_s, p.ambient_c, p.loss_tau_s
    heat_cap = plant.heating_capacity()
    stuck = plant.heater_stuck
    cool_rate = 0.0 if plant.compressor_failed else p.cool_rate_c_per_min / 60.0
    lo, span = p.min_reachable_c, p.ambient_c - p.min_reachable_c
    a = math.exp(-dt / p.fluctuation_tau_s)
    kick = p.fluctuation_c * math.sqrt(1 - a * a)
    u = plant.output_pct
    out = []
    normals, k = plant._normals, plant._next_normal
    for _ in range(n):
        err = setpoint - air
        u_unsat = kp * (err + integral / ti)
        u = min(max(u_unsat, -100.0), 100.0)
        if u == u_unsat or (u_unsat > 100.0 and err < 0) or (u_unsat < -100.0 and err > 0):
            integral += err * dt
        heat = (1.0 if stuck else max(u, 0.0) / 100.0) * heat_cap
        cool = max(-u, 0.0) / 100.0 * (cool_rate * min(max((air - lo) / span, 0.0), 1.5))
        loss = (ambient - air) / loss_tau
        base = air - fluct
        base += (heat - cool + loss) * dt
        if k == len(normals):
            normals = plant._normals = plant._rng.standard_normal(_NORMALS_BLOCK).tolist()
            k = 0
        fluct = a * fluct + kick * normals[k]
        k += 1
        air = base + fluct
        t += dt
        out.append((t, air))
    plant._next_normal = k
    plant.air_c, plant.integral, plant._fluct, plant.t, plant.output_pct = air, integral, fluct, t, u
    return out


def test_the_chamber_plant_without_min_max_calls_is_the_same_to_the_bit() -> None:
    from labrunner.sims.chamber_plant import ChamberParams, ChamberPlant

    params = ChamberParams(min_reachable_c=-20.0)
    new, old = ChamberPlant(params, seed=3), ChamberPlant(params, seed=3)
    schedule = [(85.0, 2500), (-60.0, 6000), (-40.0, 900), (23.0, 1500), (23.0, 10), (-10.0, 700)]
    outputs, airs = set(), []
    for k, (setpoint, steps) in enumerate(schedule * 2):
        for plant in (new, old):
            plant.set_setpoint(setpoint)
            plant.heater_failed = k == 3
            plant.compressor_failed = k == 7
            plant.heater_stuck = k == 9
        rows = new.run_steps(steps, 1.0)
        assert rows == _steps_with_builtins(old, steps, 1.0)
        assert (new.t, new.air_c, new.integral, new.output_pct, new._fluct) == (
            old.t, old.air_c, old.integral, old.output_pct, old._fluct)
        outputs.add(new.output_pct if abs(new.output_pct) == 100.0 else 0.0)
        airs += [air for _, air in rows]
    assert outputs == {-100.0, 0.0, 100.0}  # saturated both ways, and in between
    assert min(airs) < -10.0 and max(airs) > -20.0 + 1.5 * (23.0 + 20.0)  # cooling falling off, and clipped at 1.5
