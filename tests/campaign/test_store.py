"""The store, on SQLite and PostgreSQL: a record step is all or nothing, never twice, and reads back exactly."""

import numpy as np
import pytest
from sqlalchemy import event
from sqlalchemy.exc import IntegrityError

from labrunner.procedure import parse_procedure
from labrunner.store import SampleBlock, Store

from .conftest import TINY


class Crash(Exception):
    pass


def _block(step, n=200, lsb=(0.001, 0.00875, 0.01)):
    rng = np.random.default_rng(step)
    counts = rng.integers(-2000, 2000, size=(n, 7))
    return SampleBlock(kind="record", step_idx=step, run=1, orientation="x_up", t0_s=100.0 * step, rate_hz=50.0,
                       counter=np.arange(n) + 10 * step, accel_g=counts[:, :3] * lsb[0],
                       gyro_dps=counts[:, 3:6] * lsb[1],
                       temp_c=counts[:, 6] * lsb[2], chamber=np.array([[100.0 * step, 15.0], [100.0 * step + 4, 15.2]]),
                       table=np.array([[100.0 * step, -50.0]]), lsb=lsb)


@pytest.fixture
def store(store_db):  # on SQLite and on PostgreSQL (tests/conftest.py)
    p = parse_procedure(TINY, "tiny.yaml")
    s = Store.create(store_db)
    cid = s.new_campaign(name=p.name, procedure_text=p.text, procedure_path=None, procedure_sha256=p.sha256,
                         lab_config={}, mode="sim", sim_config={}, clock_t0=0.0, plan=p.steps())
    yield s, cid
    s.close()


def test_a_step_is_all_or_nothing(store):
    s, cid = store

    def die(_conn):
        raise Crash  # as a kill inside the transaction: rows written, commit never reached

    event.listen(s.engine, "commit", die)
    try:
        with pytest.raises(Crash):
            s.commit_record(cid, _block(0), dropped=0, corrupt=0, t_end=4.0, event_message="x")
    finally:
        event.remove(s.engine, "commit", die)
    assert s.next_step(cid) == 0
    assert s.samples_frame(cid).empty
    assert s.events_frame(cid).empty
    s.commit_record(cid, _block(0), dropped=0, corrupt=0, t_end=4.0, event_message="step 0")
    assert s.next_step(cid) == 1
    assert len(s.samples_frame(cid)) == 200


def test_a_step_cannot_be_stored_twice(store):
    s, cid = store
    s.commit_record(cid, _block(0), dropped=0, corrupt=0, t_end=4.0, event_message="step 0")
    with pytest.raises(IntegrityError):
        s.commit_record(cid, _block(0), dropped=0, corrupt=0, t_end=4.0, event_message="again")
    assert len(s.samples_frame(cid)) == 200 and s.next_step(cid) == 1


def test_only_record_blocks_are_one_per_step(store):
    # The unique index is partial on both backends: monitor stretches logged around a step are many.
    s, cid = store
    s.commit_record(cid, _block(2), dropped=0, corrupt=0, t_end=204.0, event_message="step 2")
    for k in range(3):
        monitor = _block(2, n=10)
        monitor.kind, monitor.lsb, monitor.t0_s = "monitor", None, 300.0 + 20 * k
        s.save_monitor(cid, monitor)
    assert len(s.samples_frame(cid, include_monitor=True)) == 200 + 30
    with pytest.raises(IntegrityError):
        s.commit_record(cid, _block(2), dropped=0, corrupt=0, t_end=204.0, event_message="again")


def test_counts_read_back_exactly_with_interpolated_readings(store):
    s, cid = store
    b = _block(3)
    s.commit_record(cid, b, dropped=0, corrupt=0, t_end=304.0, event_message="step 3")
    f = s.samples_frame(cid)
    assert np.array_equal(f[["ax_g", "ay_g", "az_g"]].to_numpy(), b.accel_g)
    assert np.array_equal(f["gz_dps"].to_numpy(), b.gyro_dps[:, 2])
    assert f.t_s.iloc[1] - f.t_s.iloc[0] == pytest.approx(0.02)
    assert f.chamber_c.iloc[0] == 15.0 and f.chamber_c.iloc[-1] == pytest.approx(15.0 + 0.2 * (199 * 0.02) / 4)
    assert (f.table_rate_dps == -50.0).all()
    steps = s.steps_frame(cid).set_index("idx")
    assert steps.loc[3, "status"] == "done" and steps.loc[3, "n_samples"] == 200


def test_opening_something_else_is_a_clear_error(tmp_path):
    from labrunner.errors import UserError

    junk = tmp_path / "junk.db"
    junk.write_bytes(b"not a database at all" * 10)
    with pytest.raises(UserError, match="not a labrunner database"):
        Store.open_existing(junk)
    with pytest.raises(UserError, match="database not found"):
        Store.open_existing(tmp_path / "missing.db")
