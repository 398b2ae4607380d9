"""The runner's small helpers: store requests and heartbeat, the fault log, the preflight checks."""

import pytest

from labrunner.clock import VirtualClock
from labrunner.drivers.errors import InstrumentTimeout, LimitError
from labrunner.procedure import parse_procedure
from labrunner.runner import control
from labrunner.runner.control import Control, RunStats, StoreRequests
from labrunner.runner.fault_log import FaultLog
from labrunner.runner.preflight import check_chamber, check_table
from labrunner.store import Store

from .conftest import TINY
from .fakes import FakeLab


@pytest.fixture
def store(tmp_path):
    p = parse_procedure(TINY, "tiny.yaml")
    s = Store.create(tmp_path / "c.db")
    cid = s.new_campaign(name=p.name, procedure_text=p.text, procedure_path=None, procedure_sha256=p.sha256,
                         lab_config={}, mode="sim", sim_config={}, clock_t0=0.0, plan=p.steps())
    yield s, cid
    s.close()


def test_store_requests_reach_the_control_and_the_heartbeat_is_written(store, monkeypatch):
    s, cid = store
    now = {"t": 1000.0}
    monkeypatch.setattr(control.time, "monotonic", lambda: now["t"])
    ctl = Control()
    req = StoreRequests(s, cid, VirtualClock(start=5000.0), ctl)
    s.request(cid, "pause")
    req.poll()
    assert ctl.pause and not ctl.abort and ctl.reason == "pause requested by labrunner"
    assert s.campaign(cid).clock_last == 5000.0  # heartbeat
    s.request(cid, "abort")
    now["t"] += 0.2
    req.poll()  # too soon: the store is not read again
    assert not ctl.abort
    now["t"] += 0.4
    req.poll()
    assert ctl.abort and ctl.reason == "abort requested by labrunner abort"


def test_fault_log_counts_retries_and_notes_recoveries_once():
    events = []
    stats = RunStats()
    flog = FaultLog(stats, lambda kind, message, **detail: events.append((kind, message)))

    class Driver:
        on_retry = None

    chamber, table = Driver(), Driver()
    flog.attach(chamber, table, object())
    chamber.on_retry(1, InstrumentTimeout("chamber", "tcp://x:502", "no answer"))
    assert flog.retrying and stats.faults == 1
    flog.note_recoveries()
    flog.note_recoveries()
    assert events == [("fault", "retry 1: chamber at tcp://x:502: no answer"), ("recovery", "chamber answers again")]
    assert stats.recoveries == 1 and not flog.retrying
    flog.on_imu_event("imu_link_lost", "link lost")
    flog.on_imu_event("imu_link_restored", "link restored")
    assert (stats.faults, stats.recoveries) == (2, 2)


def test_preflight_refuses_what_the_instruments_cannot_do():
    lab = FakeLab()
    identity, message = check_chamber(lab.chamber, [-10.0, 50.0])
    assert identity["vendor"] == "Fake" and message == "chamber Fake chamber answers; setpoint range -70.0..180.0 C"
    with pytest.raises(LimitError, match="procedure temperature 200.0 C is outside the controller's setpoint range"):
        check_chamber(lab.chamber, [20.0, 200.0])
    assert check_table(lab.table, [100.0]) is None  # the fake does not report its limits

    lab.table.limits = lambda: (150.0, 100.0)  # type: ignore[attr-defined]
    assert check_table(lab.table, [-150.0])[1] == "rate table Fake table answers; max 150.0 deg/s, 100.0 deg/s^2"
    with pytest.raises(LimitError, match="procedure rate 200.0 deg/s exceeds the table's maximum 150.0"):
        check_table(lab.table, [50.0, -200.0])
