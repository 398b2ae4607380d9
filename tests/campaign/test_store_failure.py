"""A store that stops taking writes mid-run (disk full, read-only file): the lab is brought to its safe
state before the store is touched again, nothing committed is lost, the failure is recorded when the
store can be written again (and said in one line when it cannot), and a resume finishes the campaign
with every step once. In-process on the fakes, and through the command line on the simulated lab."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from sqlalchemy import event

from labrunner.clock import VirtualClock
from labrunner.errors import UserError
from labrunner.runner.journal import Journal
from labrunner.store import Store, StoreError

from .conftest import cli
from .fakes import FakeLab
from .test_runner_inprocess import FRAMES, N_STEPS, PROC, at_step, transitions
from .test_runner_inprocess import Campaign as InprocCampaign

NO_LIMIT = 1073741823  # SQLite's default max_page_count


class StoreLimit:
    """Makes the store's own SQLite refuse writes, on every connection it checks out from now on.

    "full": `PRAGMA max_page_count` at the current page count — SQLite then answers SQLITE_FULL,
    "database or disk is full", exactly as on a full disk (writes that fit in free space inside
    the file still succeed, as they would there). "readonly": `PRAGMA query_only` — every write is
    refused ("attempt to write a readonly database"). None lifts the limit. It also counts the
    statements the store runs, to show when it is left alone."""

    def __init__(self, engine) -> None:
        self.mode: str | None = None
        self.statements = 0
        event.listen(engine, "checkout", self._on_checkout)
        event.listen(engine, "before_cursor_execute", self._count)

    def set(self, mode: str | None) -> None:
        self.mode = mode

    def _count(self, *_args) -> None:
        self.statements += 1

    def _on_checkout(self, dbapi_conn, _record, _proxy) -> None:
        cur = dbapi_conn.cursor()
        limit = cur.execute("PRAGMA page_count").fetchone()[0] if self.mode == "full" else NO_LIMIT
        cur.execute(f"PRAGMA max_page_count = {limit}")
        cur.execute(f"PRAGMA query_only = {1 if self.mode == 'readonly' else 0}")
        cur.close()


def full_disk_cli(after_records: int, state: Path, *args, timeout: float = 300) -> subprocess.CompletedProcess:
    """`labrunner ARGS` in a subprocess whose database disk fills after `after_records` record steps."""
    return subprocess.run([sys.executable, str(Path(__file__).with_name("full_disk_cli.py")), str(after_records),
                           str(state), *map(str, args)], capture_output=True, text=True, timeout=timeout)


def _resume_to_done(c: InprocCampaign, lab: FakeLab) -> None:
    lab2 = FakeLab(VirtualClock(start=lab.clock.now() + 600.0))
    assert c.runner(lab2).run() == "done"
    assert c.store.campaign(c.cid).status == "done"
    assert c.record_blocks_per_step() == {k: 1 for k in range(N_STEPS)}
    recorded = [int(m.split()[1]) for m in c.messages() if " recorded: " in m]
    assert recorded == list(range(N_STEPS))  # every step once, none skipped
    assert len(c.store.samples_frame(c.cid)) == N_STEPS * FRAMES


def test_a_full_disk_while_recording_stops_the_table_then_records_the_failure(tmp_path):
    c = InprocCampaign(tmp_path, PROC)
    limit = StoreLimit(c.store.engine)
    lab = FakeLab()
    seen: dict[str, int] = {}

    def progress(runner) -> None:
        if runner.done_steps() == 3 and "armed" not in seen:
            seen["armed"] = 1
            limit.set("full")  # the disk fills while step 3 (x_up, 35 C, +50 deg/s) is recorded
        if runner.state == "safe_stop" and "safe_stop" not in seen:
            seen["safe_stop"] = limit.statements
        if runner.state == "failed" and "failed" not in seen:
            seen["failed"] = limit.statements
            limit.set(None)  # space freed while the lab was being made safe

    runner = c.runner(lab, progress=progress)
    assert runner.run() == "failed"  # no exception
    path = str(c.store.path)
    assert runner.last_error == f"cannot write the database {path}: database or disk is full"
    # The store was not touched from the abort until the lab was safe.
    assert seen["failed"] == seen["safe_stop"]
    # The table was jogging at the step's rate when the record could not be stored; then it was stopped
    # and the chamber parked at the remount temperature.
    ev = c.events()
    fault = ev[ev.message.str.startswith("store failed in ")]
    assert len(fault) == 1
    assert re.fullmatch(rf"store failed in recording: cannot write the database {re.escape(path)}: database or "
                        r"disk is full", fault.message.iloc[0])
    t_fail = float(fault.t_s.iloc[0])
    assert lab.table.called("jog")[-1][1] == (50.0,) and lab.table.called("jog")[-1][0] < t_fail
    assert lab.table.called("stop")[-1][0] >= t_fail and lab.table.rate == 0.0
    assert lab.chamber.called("set_setpoint")[-1][1] == (23.0,) and lab.chamber.setpoint == 23.0
    # Recorded once the store could be written: the events held during the safe stop, in order, and the status.
    assert transitions(c)[-2:] == ["recording -> safe_stop", "safe_stop -> failed"]
    msgs = c.messages()
    assert msgs.index(fault.message.iloc[0]) < msgs.index("lab in safe state: table stopped, chamber to 23.0 C")
    assert c.store.campaign(c.cid).status == "failed"
    assert ev.t_s.is_monotonic_increasing
    # Nothing committed was lost; the step being recorded was not stored (its transaction rolled back).
    steps = c.steps()
    assert list(steps.status) == ["done"] * 3 + ["planned"] * (N_STEPS - 3)
    assert c.record_blocks_per_step() == {0: 1, 1: 1, 2: 1}
    _resume_to_done(c, lab)
    c.store.close()


def test_a_store_that_cannot_be_written_again_is_reported_in_one_line(tmp_path):
    c = InprocCampaign(tmp_path, PROC)
    limit = StoreLimit(c.store.engine)
    lab = FakeLab()
    progress = at_step([], 2, lambda _r: limit.set("readonly"))  # a read-only file from step 2 on, for good
    runner = c.runner(lab, progress=progress)
    assert runner.run() == "failed"
    t_fail = progress.fired[0]
    assert lab.table.called("stop")[-1][0] >= t_fail and lab.table.rate == 0.0
    assert lab.chamber.setpoint == 23.0
    err = runner.last_error
    assert "\n" not in err
    assert err.startswith(f"cannot write the database {c.store.path}: attempt to write a readonly database; "
                          "the lab is in its safe state; the campaign's end (failed) could not be recorded")
    assert runner.journal.pending > 0  # what could not be written is still in memory, not dropped silently
    limit.set(None)
    # The campaign still reads "running" (the status could not be written): a resume takes it on.
    assert c.store.campaign(c.cid).status == "running"
    assert list(c.steps().status[:2]) == ["done", "done"] and c.record_blocks_per_step() == {0: 1, 1: 1}
    _resume_to_done(c, lab)
    c.store.close()


def test_an_unexpected_error_leaves_the_lab_safe_before_the_store_is_touched(tmp_path):
    c = InprocCampaign(tmp_path, PROC)
    limit = StoreLimit(c.store.engine)
    lab = FakeLab()
    counts: dict[str, int] = {}

    def broken_velocity() -> float:
        raise ZeroDivisionError("a bug")

    def progress(runner) -> None:
        if runner.done_steps() == 1 and not counts:
            counts["armed"] = 1
            lab.table.velocity = broken_velocity  # read when the next record starts
        if runner.state in ("safe_stop", "aborted") and runner.state not in counts:
            counts[runner.state] = limit.statements

    runner = c.runner(lab, progress=progress)
    assert runner.run() == "aborted"
    assert counts["aborted"] == counts["safe_stop"]  # the store was left alone until the lab was safe
    assert runner.last_error == "ZeroDivisionError: a bug"
    assert lab.table.rate == 0.0 and lab.chamber.setpoint == 23.0
    assert c.messages()[-4:] == ["unexpected error in recording: ZeroDivisionError: a bug", "recording -> safe_stop",
                                 "lab in safe state: table stopped, chamber to 23.0 C", "safe_stop -> aborted"]
    assert c.store.campaign(c.cid).status == "aborted"
    c.store.close()


def test_run_on_a_full_disk_exits_failed_without_a_traceback_and_resumes(tmp_path, tiny):
    db = tmp_path / "full.db"
    state = tmp_path / "sim_state.json"
    # The disk fills after the 5th step is stored (full_disk_cli.py sets max_page_count on every connection).
    proc = full_disk_cli(5, state, "run", tiny, "--sim", "--db", db, "--quiet")
    err = proc.stderr
    assert proc.returncode == 1, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    lines = [ln for ln in err.splitlines() if "database or disk is full" in ln]
    assert len(lines) == 1, err
    assert f"cannot write the database {db}: database or disk is full" in lines[0]
    # The simulated lab when it was closed: table commanded to rest, chamber parked at the remount temperature.
    sim = json.loads(state.read_text())
    assert sim["table_commands"][-2][1] != 0.0, "the table was expected to be jogging when the disk filled"
    assert sim["table_commands"][-1][1] == 0.0 and sim["table_commanded_dps"] == 0.0
    assert sim["chamber_setpoint_c"] == 23.0
    # The limit is lifted (another process, the disk freed): what is stored is intact, the status reads
    # failed (recorded after the safe stop) or, if even that could not be written, running with its
    # process gone, which status and resume take as interrupted.
    st = cli("status", db, check=0).stdout
    assert re.search(r"status\s+(failed|running \(process gone: resume it\))", st), st
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        done_before = int((store.steps_frame(cid).status == "done").sum())
    assert done_before >= 5
    res = cli("resume", db, "--quiet")
    assert res.returncode == 0, res.stderr[-3000:]
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        steps = store.steps_frame(cid)
        assert (steps.status == "done").all() and store.campaign(cid).status == "done"
        ev = store.events_frame(cid)
        recorded = sorted(int(m.split()[1]) for m in ev.message if re.match(r"step \d+ recorded: ", m))
        assert recorded == list(range(len(steps)))  # every step exactly once
        assert len(store.samples_frame(cid)) == int(steps.n_samples.sum())


def test_a_store_failure_met_by_another_thread_is_raised_at_the_sequencers_next_safe_point(tmp_path):
    c = InprocCampaign(tmp_path, PROC)
    limit = StoreLimit(c.store.engine)
    journal = Journal(c.store, c.cid)
    limit.set("readonly")
    journal.write(1.0, "fault", "imu link lost", state="soaking", step_idx=0, detail=None, raise_failure=False)
    assert journal.pending == 1 and journal.failure is not None  # the reader thread goes on
    with pytest.raises(StoreError, match="attempt to write a readonly database"):
        journal.raise_failure()
    # Held for the safe stop: kept in order, nothing raised, nothing written.
    journal.hold()
    before = limit.statements
    journal.write(2.0, "transition", "soaking -> safe_stop", state="safe_stop", step_idx=0, detail=None)
    journal.raise_failure()
    assert limit.statements == before and journal.pending == 2
    assert isinstance(journal.flush(), StoreError) and journal.pending == 2
    limit.set(None)
    assert journal.flush() is None and journal.pending == 0 and not journal.held
    ev = c.events()
    assert list(ev.message) == ["imu link lost", "soaking -> safe_stop"] and list(ev.t_s) == [1.0, 2.0]
    c.store.close()


def test_a_store_that_cannot_be_opened_is_named_not_mistaken_for_a_foreign_file(tmp_path):
    c = InprocCampaign(tmp_path, PROC)
    path = c.store.path.file
    assert path is not None
    c.store.close()
    with path.open("r+b") as fh:  # a damaged header page
        fh.seek(100)
        fh.write(b"\xff" * 3000)
    with pytest.raises(StoreError, match=f"cannot open the database {re.escape(str(path))}: "):
        Store.open_existing(path)
    foreign = tmp_path / "notes.db"
    foreign.write_text("not a database at all, just some notes " * 40)
    with pytest.raises(UserError, match="not a labrunner database"):
        Store.open_existing(foreign)
