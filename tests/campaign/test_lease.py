"""The campaign lease (runner/lease.py, Store.take_lease): one writer per campaign.

The race: two `resume`s of one campaign let go at the same instant, 20 times; exactly one records,
the other is refused naming the winner, and the store holds no step or monitor stretch twice. On SQLite
and on PostgreSQL (`store_db`, tests/conftest.py): BEGIN IMMEDIATE there, SELECT ... FOR UPDATE here."""

from __future__ import annotations

import os
import re
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

import labrunner
from labrunner.runner.lease import STALE_AFTER_S
from labrunner.store import SCHEMA_VERSION, LeaseLost, Store
from tests.campaign.conftest import cli
from tests.store_sql import store_rows

RACER = Path(__file__).with_name("lease_race_cli.py")
HOST = os.uname().nodename


def _paused(db: str | Path, tiny: Path) -> str | Path:
    with labrunner.start_run(tiny, db=db) as session:
        session.request_pause("test: paused before the first step")
        assert session.execute().state == "paused"
    return db


def _racer(tmp_path: Path, trial: int, me: str, other: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, str(RACER), str(tmp_path / f"go-{trial}"),
                             str(tmp_path / f"{me}-{trial}"), str(tmp_path / f"{other}-{trial}"), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(*paths: Path, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not all(p.exists() for p in paths):
        assert time.monotonic() < deadline, f"timed out waiting for {paths}"
        time.sleep(0.01)


@pytest.mark.timeout(900)  # 40 CLI processes: on a loaded 2-core machine more than the default 300 s
def test_two_resumes_at_the_same_instant_never_both_record(tmp_path, tiny, store_db):
    db = _paused(store_db, tiny)
    trials = 20
    for trial in range(trials):
        racers = {name: _racer(tmp_path, trial, name, other, "resume", str(db), "--quiet")
                  for name, other in (("a", "b"), ("b", "a"))}
        _wait_for(*(tmp_path / f"{n}-{trial}.ready" for n in racers))
        (tmp_path / f"go-{trial}").touch()  # both are polling for it: let go together
        out = {name: p.communicate(timeout=60) for name, p in racers.items()}
        results = {name: (tmp_path / f"{name}-{trial}").read_text() for name in racers}
        winners = [n for n, r in results.items() if r == "recorded"]
        assert len(winners) == 1, (trial, results, out)
        winner = winners[0]
        loser = "b" if winner == "a" else "a"
        assert results[loser] == "exit 2", (trial, results, out[loser][1])
        refusal = out[loser][1]
        assert f"held by pid {racers[winner].pid} on {HOST}" in refusal, refusal
        assert "last heartbeat" in refusal and "Traceback" not in refusal
        if trial:  # the previous winner died holding the lease: stale at once on this host, and said so
            assert "is gone from this host" in out[winner][1], out[winner][1]
        # The store: one more recorded step per trial, each step once, no monitor stretch twice.
        assert store_rows(db, "SELECT count(*) FROM sample_blocks WHERE kind = 'record'") == [(trial + 1,)]
        assert store_rows(db, "SELECT count(*) FROM steps WHERE status = 'done'") == [(trial + 1,)]
        assert store_rows(db, "SELECT step_idx FROM sample_blocks WHERE kind = 'record' GROUP BY step_idx "
                         "HAVING count(*) > 1") == []
        assert store_rows(db, "SELECT t0_s FROM sample_blocks WHERE kind = 'monitor' GROUP BY t0_s "
                         "HAVING count(*) > 1") == []
        assert store_rows(db, "SELECT pid FROM campaigns") == [(racers[winner].pid,)]
    sessions = store_rows(db, "SELECT count(*) FROM events WHERE message LIKE 'campaign % at step %'")
    assert sessions == [(trials + 1,)]  # the run, then each winner; the losers wrote nothing, not even a start


def _hold(db: str | Path, *, host: str, pid: int, age_s: float) -> None:
    """Make the campaign look held by another process (as that process's heartbeat would leave it)."""
    store_rows(db, "UPDATE campaigns SET status = 'running', lease_token = 'elsewhere', pid = :pid, host = :host, "
              "lease_wall = :wall", pid=pid, host=host, wall=time.time() - age_s)


def test_live_lease_of_another_host_is_refused_even_with_take_over(tmp_path, tiny):
    # The refusal is the lease rules' (backend-independent); the take-over below runs on both backends.
    db = _paused(tmp_path / "race.db", tiny)
    _hold(db, host="lab-pc-2", pid=4242, age_s=5.0)
    for extra in ((), ("--take-over",)):
        r = cli("resume", db, "--quiet", *extra, timeout=60)
        assert r.returncode == 2, r.stderr
        line = r.stderr.strip()
        age = re.search(r"last heartbeat ([0-9]+) s ago", line)
        assert "pid 4242 on lab-pc-2" in line and age and 5 <= int(age.group(1)) < STALE_AFTER_S, line
        assert len(line.splitlines()) == 1 and "Traceback" not in line
    assert store_rows(db, "SELECT lease_token, host FROM campaigns") == [("elsewhere", "lab-pc-2")]
    assert store_rows(db, "SELECT count(*) FROM events WHERE message LIKE 'campaign % at step %'") == [(1,)]
    # status and list believe a fresh heartbeat of another host (its pid cannot be looked at here)
    assert "process gone" not in cli("status", db, check=0).stdout
    assert "pid 4242 on lab-pc-2" in cli("list", db, check=0).stdout


def test_stale_lease_is_taken_only_with_take_over(tmp_path, tiny, store_db):
    db = _paused(store_db, tiny)
    _hold(db, host="lab-pc-2", pid=4242, age_s=STALE_AFTER_S + 30)
    store_rows(db, "UPDATE campaigns SET updated_wall = lease_wall")  # the holder's last heartbeat, as it left it
    assert "pid 4242 on lab-pc-2 (stale: resume --take-over" in cli("list", db, check=0).stdout
    r = cli("resume", db, "--quiet", timeout=60)
    assert r.returncode == 2, r.stderr
    assert "pid 4242 on lab-pc-2" in r.stderr and "stale" in r.stderr and "--take-over" in r.stderr, r.stderr
    assert store_rows(db, "SELECT lease_token FROM campaigns") == [("elsewhere",)]

    (tmp_path / "other-0").touch()  # no other racer: the taker records one step and dies
    taker = _racer(tmp_path, 0, "me", "other", "resume", str(db), "--quiet", "--take-over")
    _wait_for(tmp_path / "me-0.ready")
    (tmp_path / "go-0").touch()
    _out, err = taker.communicate(timeout=60)
    assert (tmp_path / "me-0").read_text() == "recorded", err
    assert "taken over from pid 4242 on lab-pc-2" in err, err
    token, pid, host = store_rows(db, "SELECT lease_token, pid, host FROM campaigns")[0]
    assert token != "elsewhere" and (pid, host) == (taker.pid, HOST)
    assert store_rows(db, "SELECT count(*) FROM sample_blocks WHERE kind = 'record'") == [(1,)]


def test_a_lease_taken_over_stops_the_old_holder_writing(tiny, store_db):
    db = _paused(store_db, tiny)
    store = Store.open_existing(db)
    try:
        from labrunner.runner.lease import acquire

        assert acquire(store, 1).reason == "free"
        store.heartbeat(1, 10.0)  # renews while it holds the lease
        _hold(db, host="lab-pc-2", pid=4242, age_s=0.0)  # another process took it over
        with pytest.raises(LeaseLost, match="taken over"):
            store.heartbeat(1, 11.0)
        with pytest.raises(LeaseLost):
            store.event(1, 11.0, "info", "must not be written")
        store.release_lease(1)  # not ours any more: left as the taker's
    finally:
        store.close()
    assert store_rows(db, "SELECT lease_token, clock_last FROM campaigns")[0][0] == "elsewhere"
    assert store_rows(db, "SELECT count(*) FROM events WHERE message = 'must not be written'") == [(0,)]


def test_a_run_holds_its_campaign_and_releases_it_at_the_end(tiny, store_db):
    db = _paused(store_db, tiny)
    assert store_rows(db, "SELECT lease_token, lease_wall FROM campaigns") == [(None, None)]  # released


def test_a_schema_1_store_is_migrated_when_opened(tmp_path, tiny):  # SQLite's: no schema-1 store on PostgreSQL
    db = _paused(tmp_path / "old.db", tiny)
    with sqlite3.connect(db) as conn:  # what labrunner wrote before the lease
        conn.execute("ALTER TABLE campaigns DROP COLUMN lease_token")
        conn.execute("ALTER TABLE campaigns DROP COLUMN lease_wall")
        conn.execute("UPDATE labrunner_meta SET value = '1' WHERE key = 'schema_version'")
    assert "paused" in cli("list", db, check=0).stdout
    assert store_rows(db, "SELECT value FROM labrunner_meta WHERE key = 'schema_version'") == [(str(SCHEMA_VERSION),)]
    columns = [r[1] for r in store_rows(db, "PRAGMA table_info(campaigns)")]
    assert "lease_token" in columns and "lease_wall" in columns
