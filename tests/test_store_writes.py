"""The store's hot writes, built once and executed with parameters (issue 15, target 1): they write what
they say, `next_step` stays right whoever records and in whatever order, and the lease still stops a
writer whose lease was taken over."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labrunner.procedure import parse_procedure
from labrunner.store import LeaseLost, SampleBlock, Store
from tests.campaign.conftest import TINY


def _record(step: int, n: int = 20) -> SampleBlock:
    return SampleBlock(kind="record", step_idx=step, run=1, orientation="x_up", t0_s=10.0 * step, rate_hz=10.0,
                       counter=np.arange(n), accel_g=np.zeros((n, 3)), gyro_dps=np.ones((n, 3)),
                       temp_c=np.full(n, 25.0), chamber=np.array([[10.0 * step, 15.0]]), table=np.zeros((1, 2)))


@pytest.fixture
def campaign(tmp_path: Path) -> tuple[Store, int]:
    p = parse_procedure(TINY, "tiny.yaml")
    s = Store.create(tmp_path / "w.db")
    cid = s.new_campaign(name=p.name, procedure_text=p.text, procedure_path=None, procedure_sha256=p.sha256,
                         lab_config={}, mode="sim", sim_config={}, clock_t0=0.0, plan=p.steps(), lease_token="mine")
    yield s, cid
    s.close()


def _commit(s: Store, cid: int, step: int) -> None:
    s.commit_record(cid, _record(step), dropped=1, corrupt=2, t_end=10.0 * step + 2, event_message=f"step {step}")


def test_next_step_follows_the_records_in_any_order_and_from_any_writer(campaign):
    s, cid = campaign
    assert s.next_step(cid) == 0
    _commit(s, cid, 0)
    _commit(s, cid, 1)
    assert s.next_step(cid) == 2
    _commit(s, cid, 5)  # out of order: 2 is still the first not done
    assert s.next_step(cid) == 2
    with Store.open_existing(s.path) as other:  # another writer (a resumed process) records 2..4
        other.leases[cid] = "mine"
        for k in (2, 3, 4):
            _commit(other, cid, k)
    assert s.next_step(cid) == 6
    n = len(s.steps_frame(cid))
    for k in range(6, n):
        _commit(s, cid, k)
    assert s.next_step(cid) is None


def test_the_writes_store_what_they_are_given(campaign):
    s, cid = campaign
    s.note_attempt(cid, 3)
    s.note_attempt(cid, 3)
    _commit(s, cid, 3)
    step = s.steps_frame(cid).set_index("idx").loc[3]
    assert (step.status, step.attempts, step.run, step.n_samples) == ("done", 2, 1, 20)
    assert (step.dropped, step.corrupt) == (1, 2)
    assert (step.t_start, step.t_end, step.imu_temp_c, step.chamber_c) == (30.0, 32.0, 25.0, 15.0)
    s.event(cid, 7.5, "info", "hello", state="soaking", step_idx=4, detail={"a": 1}, wall=123.0)
    ev = s.events_frame(cid)
    last = ev.iloc[-1]
    assert (last.t_s, last.kind, last.message, last.state, last.step_idx, last.detail, last.wall) == (
        7.5, "info", "hello", "soaking", 4, '{"a": 1}', 123.0)
    assert ev.message.tolist()[-2] == "step 3"
    s.request(cid, "pause")
    assert s.pending_request(cid) == "pause"
    s.set_status(cid, "paused", clock_last=99.0)
    info = s.campaign(cid)
    assert (info.status, info.clock_last) == ("paused", 99.0)
    s.heartbeat(cid, 123.5)
    info = s.campaign(cid)
    assert info.clock_last == 123.5 and info.lease_token == "mine" and info.lease_wall == info.updated_wall


def test_a_writer_whose_lease_was_taken_stops(campaign):
    s, cid = campaign
    with Store.open_existing(s.path) as other:
        other.take_lease(cid, "theirs", lambda holder: None)
    with pytest.raises(LeaseLost):
        s.heartbeat(cid, 1.0)
    with pytest.raises(LeaseLost):
        _commit(s, cid, 0)
    assert s.next_step(cid) == 0  # nothing was written
    info = s.campaign(cid)
    assert info.lease_token == "theirs" and info.clock_last != 1.0


def test_a_heartbeat_without_a_lease_still_stamps_the_campaign(campaign):
    s, cid = campaign
    s.leases.clear()  # labrunner abort, tests driving a runner: no lease held
    s.heartbeat(cid, 42.0)
    assert s.campaign(cid).clock_last == 42.0
