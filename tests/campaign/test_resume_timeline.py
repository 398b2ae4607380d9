"""A resumed campaign keeps one clean timeline: a resumed dry run continues after everything already
stored (monitor stretches included), the end-of-run fit is stored once, and a fault plan's faults fire
once per campaign, not once per session. Each is killed at a chosen point (crashing_cli.py) and resumed."""

from __future__ import annotations

import json
import signal

import numpy as np
import yaml
from sqlalchemy import text

from labrunner.store import Store

from .conftest import cli, crashing_cli


def _ids(db):
    """The largest block and event ids stored so far: what a later session writes has larger ones."""
    with Store.open_existing(db) as store, store.engine.connect() as conn:
        blocks = conn.execute(text("SELECT COALESCE(MAX(id), 0) FROM sample_blocks")).scalar()
        events = conn.execute(text("SELECT COALESCE(MAX(id), 0) FROM events")).scalar()
    return int(blocks), int(events)


def _block_times(db, lo, hi):
    """Campaign times of every sample and reading of blocks with lo < id <= hi (records and monitor rows)."""
    out = []
    with Store.open_existing(db) as store, store.engine.connect() as conn:
        rows = conn.execute(text("SELECT t0_s, rate_hz, counter, chamber, \"table\" FROM sample_blocks "
                                 "WHERE id > :lo AND id <= :hi ORDER BY id"), {"lo": lo, "hi": hi}).fetchall()
    for t0, rate, counter, chamber, table in rows:
        out.append(t0 + np.frombuffer(counter, dtype="<i4") / rate)
        for readings in (chamber, table):
            out.append(np.frombuffer(readings, dtype="<f8").reshape(-1, 2)[:, 0])
    return np.concatenate(out) if out else np.zeros(0)


def test_a_resumed_dry_run_continues_after_the_monitor_data_already_stored(tmp_path, tiny):
    db = tmp_path / "t.db"
    # Killed while soaking, as the 40th monitor stretch is about to be stored: the stretches before it
    # lie after the last event, and the heartbeat's clock is older still.
    proc = crashing_cli("monitor:40", "run", tiny, "--sim", "--db", db, "--quiet")
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    blocks_1, events_1 = _ids(db)
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        info = store.campaign(cid)
        ev1 = store.events_frame(cid)
    t1 = _block_times(db, 0, blocks_1)
    last_1 = max(float(t1.max()), float(ev1.t_s.max()))
    # What resume used to start from lies before the stored monitor data: the case this test is about.
    assert max(info.clock_last - info.clock_t0, float(ev1.t_s.max())) + 60.0 < float(t1.max())

    cli("resume", db, "--quiet", check=0)
    blocks_2, events_2 = _ids(db)
    t2 = _block_times(db, blocks_1, blocks_2)
    with Store.open_existing(db) as store:
        ev = store.events_frame(cid)
        frame = store.samples_frame(cid, include_monitor=True)
    ev2 = ev[ev.id > events_1]
    assert len(t2) and len(ev2)
    # The second session starts after everything the first one stored, events and samples alike.
    first_2 = min(float(t2.min()), float(ev2.t_s.min()))
    assert first_2 > last_1
    assert ev2.message.iloc[0] == f"campaign resumed at step {int(ev2.step_idx.iloc[0])}"
    # Events in the order they were written have non-decreasing campaign times across the boundary.
    assert ev.sort_values("id").t_s.is_monotonic_increasing
    # The exported rows (monitor included) of the two sessions do not share a campaign time.
    assert not frame.t_s.duplicated().any()


def test_a_kill_between_storing_the_fit_and_done_leaves_one_fit(tmp_path, tiny):
    # Six orientations and records longer than the fit's 5 s stable stretches: the end-of-run fit can run.
    tiny.write_text(tiny.read_text().replace("fit: {run: false}", "fit: {run: true, rbf: false, polynomial_order: 1}")
                    .replace("record_s: 4", "record_s: 6"))
    db = tmp_path / "f.db"
    proc = crashing_cli("fit:1", "run", tiny, "--sim", "--db", db, "--quiet")
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        assert len(store.fits_frame(cid)) == 1 and store.campaign(cid).status == "running"
    res = cli("resume", db, "--quiet", check=0)
    assert "calibration" in res.stdout.lower() or res.stdout.strip(), res.stderr[-2000:]  # the summary again
    with Store.open_existing(db) as store:
        fits = store.fits_frame(cid)
        assert store.campaign(cid).status == "done"
        ev = store.events_frame(cid)
    assert len(fits) == 1
    assert (ev.message == "fit stored").sum() == 1  # the killed session died before it could say so
    # A fit of other data (a later `labrunner fit`) is stored as its own row: only the same data is skipped.
    assert cli("fit", db, "--json", tmp_path / "fit.json").returncode == 0
    with Store.open_existing(db) as store:
        assert len(store.fits_frame(cid)) == 2


def test_a_scheduled_fault_fires_once_per_campaign_across_a_kill(tmp_path, tiny):
    schedule = [{"at_step": 2, "after_s": 0.0, "kind": "modbus_busy", "count": 1},
                {"at_step": 9, "after_s": 1.0, "kind": "modbus_busy", "count": 1},
                {"at_s": 3000.0, "kind": "modbus_timeout", "duration_s": 5.0}]
    sim = tmp_path / "sim.yaml"
    sim.write_text(yaml.safe_dump({"faults": {"schedule": schedule}}))
    db = tmp_path / "x.db"
    # Killed as step 2 is about to be stored: the fault anchored to step 2 has fired, the step is not stored.
    proc = crashing_cli("record:3", "run", tiny, "--sim", "--sim-config", sim, "--db", db, "--quiet")
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]

    def injected():
        with Store.open_existing(db) as store:
            cid = store.resolve(None)
            ev = store.events_frame(cid)
            nxt = store.next_step(cid)
        return [json.loads(d) for d in ev[ev.kind == "injected"].detail], nxt

    fired, nxt = injected()
    assert nxt == 2 and [f["at_step"] for f in fired] == [2]
    # Resumed at step 2 (the step the first fault is anchored to), then killed again as step 9 (the
    # second fault's) is about to be stored, and resumed at step 9.
    proc = crashing_cli("record:8", "resume", db, "--quiet")
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    fired, nxt = injected()
    assert nxt == 9 and [f["at_step"] for f in fired if f["at_step"] is not None] == [2, 9]
    cli("resume", db, "--quiet", check=0)
    fired, nxt = injected()
    assert nxt is None
    keys = sorted((f["kind"], f["at_step"], f["at_s"]) for f in fired)
    assert keys == sorted((f["kind"], f.get("at_step"), f.get("at_s")) for f in schedule)  # each once
