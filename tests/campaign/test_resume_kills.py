"""Kill a dry run at many points (kill -9, mid-record, mid-commit) and resume: the data are exactly
those of an uninterrupted run, with no step lost, repeated or duplicated. On SQLite (a dozen kills) and on
PostgreSQL (five: the same kinds of kill point, fewer of them, to keep the suite's time), both compared
with an uninterrupted run stored in SQLite."""

import random
import signal
import time

from labrunner.store import Store

from .conftest import cli, crashing_cli, popen


def _summary(db):
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        steps = store.steps_frame(cid)
        frame = store.samples_frame(cid)
        with store.engine.connect() as conn:
            from sqlalchemy import text
            blocks = conn.execute(text("SELECT step_idx, COUNT(*) FROM sample_blocks WHERE kind='record' "
                                       "GROUP BY step_idx HAVING COUNT(*) > 1")).fetchall()
        status = store.campaign(cid).status
    per_step = steps[["idx", "orientation", "temperature_c", "rate_dps", "status", "n_samples"]]
    return per_step.reset_index(drop=True), len(frame), blocks, status


def test_killed_anywhere_and_resumed_equals_uninterrupted(tmp_path, tiny, store_db):
    # Long enough (120 steps) that a dozen kills land before it can finish.
    rates = "[-100, -75, -50, -25, 0, 10, 25, 50, 75, 100]"
    tiny.write_text(tiny.read_text().replace("list_dps: [-50, 0, 50]", f"list_dps: {rates}"))
    ref = tmp_path / "ref.db"
    cli("run", tiny, "--sim", "--db", ref, "--quiet", check=0)
    ref_steps, ref_rows, _, _ = _summary(ref)

    db = store_db  # a SQLite file's path or a PostgreSQL database's URL
    wanted = 12 if store_db.endswith(".db") else 5
    rng = random.Random(20261122)
    kills = []
    # The first run dies mid-commit of its 3rd step (inside the database transaction).
    proc = crashing_cli("commit:3", "run", tiny, "--sim", "--db", db, "--quiet")
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    kills.append("commit:3")
    # Killed inside the third step's transaction: its rows were written but never committed.
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        assert store.next_step(cid) == 2
        assert not store.events_frame(cid).message.str.startswith("step 2 recorded").any()
    # Then resume, killing again at chosen points (mid-record: samples read, not yet stored;
    # mid-commit) and at random moments (kill -9), until `wanted` kills have landed.
    cycle = ["record:2", "random", "commit:1", "random", "record:3", "random", "commit:2", "random"]
    i = 0
    while len(kills) < wanted:
        what = cycle[i % len(cycle)]
        i += 1
        assert i < 60, "the campaign finished or stalled before a dozen kills"
        if what == "random":
            p = popen("resume", db, "--quiet")
            time.sleep(rng.uniform(0.3, 1.0))
            if p.poll() is None:
                p.send_signal(signal.SIGKILL)
                kills.append("random")
            p.communicate(timeout=60)
            assert p.returncode in (0, -signal.SIGKILL)
            assert p.returncode != 0, "finished before a dozen kills: make the campaign longer"
        else:
            with Store.open_existing(db) as store:
                before = store.next_step(store.resolve(None))
            proc = crashing_cli(what, "resume", db, "--quiet")
            assert proc.returncode == -signal.SIGKILL, "finished early or failed: " + proc.stderr[-2000:]
            kills.append(what)
            # "record:N"/"commit:N" die before the N-th record of the session is stored.
            with Store.open_existing(db) as store:
                assert store.next_step(store.resolve(None)) == before + int(what.split(":")[1]) - 1
    proc = cli("resume", db, "--quiet")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert any(k.startswith("commit") for k in kills) and any(k.startswith("record") for k in kills)

    steps, rows, dup_blocks, status = _summary(db)
    assert status == "done"
    assert dup_blocks == []  # no step stored twice
    assert rows == ref_rows
    assert steps.equals(ref_steps)  # same steps, same order, same sample counts
    with Store.open_existing(db) as store:
        ev = store.events_frame(store.resolve(None))
    # Every resume that got as far as its first step says so (a random kill may land before that).
    assert ev.message.str.contains("campaign resumed at step").sum() >= len([k for k in kills if k != "random"])
