"""`labrunner list DB` and `Database.summaries()/summary()` (issue 12, item 3): what a store holds."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

import labrunner
from labrunner.cli import main
from labrunner.commands.listing import age_text
from labrunner.store import Store

from .test_api import FRAMES, N_STEPS, TINY


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def two_campaigns(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path | str:
    """A store with campaign 1 done and campaign 2 paused after five steps: a SQLite file, or a
    PostgreSQL database (its URL)."""
    d = tmp_path_factory.mktemp("list")
    proc = d / "tiny.yaml"
    proc.write_text(TINY)
    db: Path | str = d / "two.db"
    if request.param == "postgresql":
        cluster = request.getfixturevalue("pg_cluster")
        db = cluster.url(cluster.new_database())
    assert labrunner.run(proc, db=db, seed=1).state == "done"
    with labrunner.start_run(proc, db=db, seed=2) as session:
        def pause_after_five(p: labrunner.Progress) -> None:
            if p.steps_done == 5:
                session.request_pause("test: pause after five steps")

        assert session.execute(pause_after_five).state == "paused"
    return db


def test_summaries_give_every_field(two_campaigns: Path | str) -> None:
    with labrunner.open(two_campaigns) as db:
        done, paused = db.summaries()
    assert (done.campaign_id, done.name, done.status, done.mode) == (1, "tiny", "done", "sim")
    assert (done.steps_done, done.steps_total, done.samples) == (N_STEPS, N_STEPS, N_STEPS * FRAMES)
    assert (paused.campaign_id, paused.status, paused.steps_done, paused.steps_total) == (2, "paused", 5, N_STEPS)
    assert paused.samples == 5 * FRAMES
    for s in (done, paused):  # not running: no holder, and the heartbeat is the last status change
        assert s.pid is None and s.holder is None and s.process_alive is None
        assert 0 <= s.heartbeat_age_s < 600 and s.heartbeat_wall > 0
    assert paused.heartbeat_wall >= done.heartbeat_wall
    again = labrunner.list_campaigns(two_campaigns)  # the API function reads the same (ages aside)
    assert [(s.campaign_id, s.status, s.steps_done, s.heartbeat_wall) for s in again] == [
        (1, "done", N_STEPS, done.heartbeat_wall), (2, "paused", 5, paused.heartbeat_wall)]


def test_summary_frame_matches_the_status_of_each_campaign(two_campaigns: Path | str) -> None:
    with labrunner.open(two_campaigns) as db:
        frame = db.summary()
    assert list(frame.campaign_id) == [1, 2] and list(frame.status) == ["done", "paused"]
    assert {"name", "mode", "steps_done", "steps_total", "samples", "pid", "host", "process_alive",
            "heartbeat_wall", "heartbeat_age_s", "holder"} <= set(frame.columns)
    assert str(frame.pid.dtype) == "Int64" and frame.pid.isna().all()
    for row in frame.itertuples():
        status = labrunner.status(two_campaigns, campaign=int(row.campaign_id))
        assert (row.steps_done, row.steps_total, row.samples, row.mode) == (
            status.steps_done, status.steps_total, status.samples, status.mode)


def test_list_prints_one_line_per_campaign(two_campaigns: Path | str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["list", str(two_campaigns)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"{two_campaigns}: 2 campaigns"
    assert lines[1].split() == ["id", "name", "status", "steps", "samples", "mode", "process", "last", "heartbeat"]
    all_samples = f"{N_STEPS * FRAMES:,}"
    assert re.fullmatch(rf"\s*1\s+tiny\s+done\s+{N_STEPS}/{N_STEPS}\s+{all_samples}\s+sim\s+-\s+\d+ s ago", lines[2])
    assert re.fullmatch(rf"\s*2\s+tiny\s+paused\s+5/{N_STEPS}\s+{5 * FRAMES:,}\s+sim\s+-\s+\d+ s ago", lines[3])
    assert len(lines) == 4


def test_a_running_campaign_shows_its_process_and_heartbeat(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    proc = tmp_path / "tiny.yaml"
    proc.write_text(TINY)
    db = tmp_path / "run.db"
    seen: list[labrunner.CampaignSummary] = []
    printed: list[str] = []

    def look(p: labrunner.Progress) -> None:
        if p.steps_done == 3 and not seen:  # from the running campaign's own progress callback
            seen.extend(labrunner.list_campaigns(db))
            assert main(["list", str(db)]) == 0
            printed.append(capsys.readouterr().out)

    assert labrunner.run(proc, db=db, progress=look).state == "done"
    (running,) = seen
    assert running.status == "running" and running.steps_done == 3
    assert running.pid == os.getpid() and running.host == os.uname().nodename and running.process_alive is True
    assert running.holder == f"pid {os.getpid()} on {os.uname().nodename}" and running.heartbeat_age_s < 60
    row = printed[0].splitlines()[2]
    assert row.split()[:4] == ["1", "tiny", "running", f"3/{N_STEPS}"]
    assert f"pid {os.getpid()} on {os.uname().nodename}" in row and "gone" not in row
    (after,) = labrunner.list_campaigns(db)
    assert after.status == "done" and after.holder is None


def test_a_dead_process_is_named_gone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    proc = tmp_path / "tiny.yaml"
    proc.write_text(TINY)
    db = tmp_path / "dead.db"
    with labrunner.start_run(proc, db=db) as session:
        session.request_pause("test")
        session.execute()
    # As a kill -9 leaves it: status running, the pid of a process that no longer exists.
    with Store.open_existing(db) as store:
        store.set_status(1, "running", pid=2**22 + 12345)
    (s,) = labrunner.list_campaigns(db)
    assert s.status == "running" and s.process_alive is False
    assert main(["list", str(db)]) == 0
    assert f"pid {2**22 + 12345} on {os.uname().nodename} (gone: resume it)" in capsys.readouterr().out


def test_an_empty_store_and_files_that_are_not_stores(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    Store.create(tmp_path / "empty.db").close()
    assert main(["list", str(tmp_path / "empty.db")]) == 0
    assert capsys.readouterr().out.strip() == f"{tmp_path / 'empty.db'}: a labrunner store with no campaigns yet"
    with labrunner.open(tmp_path / "empty.db") as db:
        assert db.summaries() == [] and db.summary().empty

    text = tmp_path / "notes.db"
    text.write_text("not a database\n")
    zero = tmp_path / "zero.db"
    zero.write_bytes(b"")
    for path, message in ((text, "not a labrunner database"), (zero, "not a labrunner database (an empty file)"),
                          (tmp_path / "missing.db", "database not found"), (tmp_path, "not a labrunner database")):
        assert main(["list", str(path)]) == 2
        err = capsys.readouterr().err
        assert err.strip() == f"labrunner list: error: {path}: {message}", err
    assert text.read_text() == "not a database\n" and zero.read_bytes() == b""  # looked at, not written
    assert not list(tmp_path.glob("*-wal")) and not list(tmp_path.glob("*-shm"))


@pytest.mark.parametrize(("seconds", "text"), [(0, "0 s ago"), (119, "119 s ago"), (600, "10 min ago"),
                                               (3 * 3600, "3.0 h ago"), (5 * 86400, "5.0 d ago")])
def test_heartbeat_ages_read_as_a_person_would(seconds: float, text: str) -> None:
    assert age_text(seconds) == text
