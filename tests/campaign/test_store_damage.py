"""A damaged store is detected and named (issue 12, item 6): a garbled page, bad JSON, a short blob.

Each command gives one line naming the store and where (campaign, table, step), exit 2, never a
traceback and never a silent pass; `labrunner check --db` runs the full integrity check and decodes
every JSON column and blob."""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import pytest

import labrunner
from labrunner.store import Store, StoreDamage
from tests.campaign.conftest import TINY, cli


@pytest.fixture(scope="module")
def clean_db(tmp_path_factory) -> Path:
    """A real store: the tiny procedure run to the end on the simulated lab."""
    folder = tmp_path_factory.mktemp("damage")
    procedure = folder / "tiny.yaml"
    procedure.write_text(TINY)
    db = folder / "clean.db"
    assert labrunner.run(procedure, db=db).state == "done"
    return db


def _copy(clean_db: Path, tmp_path: Path, name: str) -> Path:
    db = tmp_path / name
    shutil.copy(clean_db, db)
    return db


def _garble_events_page(db: Path) -> int:
    """Overwrite 400 bytes in the middle of one of the events table's leaf pages; returns its number."""
    with sqlite3.connect(db) as conn:
        size = conn.execute("PRAGMA page_size").fetchone()[0]
        pages = [r[0] for r in conn.execute("SELECT pageno FROM dbstat WHERE name = 'events' AND pagetype = 'leaf' "
                                            "ORDER BY pageno")]
    assert len(pages) >= 2, "the tiny campaign fills more than one page of events"
    page = pages[len(pages) // 2]
    with db.open("r+b") as f:
        f.seek((page - 1) * size + size // 2 - 200)
        f.write(b"\xa5" * 400)
    return page


def _one_line_error(r, db: Path) -> str:
    assert r.returncode == 2, (r.returncode, r.stdout[-500:], r.stderr[-2000:])
    assert "Traceback" not in r.stderr
    lines = [line for line in r.stderr.splitlines() if "error:" in line]
    assert len(lines) == 1, r.stderr
    assert str(db) in lines[0] or db.name in lines[0]
    return lines[0]


def test_garbled_page_is_named_by_export_fit_status_and_resume(clean_db, tmp_path):
    db = _copy(clean_db, tmp_path, "garbled.db")
    _garble_events_page(db)
    for args in (("status", db), ("export", db, "--csv", tmp_path / "out.csv"), ("fit", db), ("resume", db),
                 ("list", db)):
        line = _one_line_error(cli(*args, timeout=120), db)
        assert "damaged" in line and "table events" in line and "campaign 1" in line, line
        assert "quick_check" in line and f"labrunner check --db {db}" in line, line
    assert not (tmp_path / "out.csv").exists()
    with pytest.raises(StoreDamage, match="table events"):
        Store.open_existing(db)


def test_check_db_on_a_garbled_page(clean_db, tmp_path):
    db = _copy(clean_db, tmp_path, "garbled.db")
    page = _garble_events_page(db)
    r = cli("check", "--db", db, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr
    assert f"{db}: the store is damaged" in r.stdout
    assert f"PRAGMA integrity_check: On tree page {page}" in r.stdout, r.stdout
    assert "damaged pages in table events, after the row of campaign 1 step" in r.stdout, r.stdout


def test_check_db_on_a_clean_store(clean_db):
    r = cli("check", "--db", clean_db, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "the store is intact: integrity check ok, schema version ok, 1 campaign(s)" in r.stdout


def test_bad_json_names_campaign_table_and_column(clean_db, tmp_path):
    db = _copy(clean_db, tmp_path, "json.db")
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE campaigns SET lab_config = '{not json'")
        event_id, step = conn.execute("SELECT id, step_idx FROM events WHERE step_idx IS NOT NULL "
                                      "ORDER BY id LIMIT 1").fetchone()
        conn.execute("UPDATE events SET detail = '[1,' WHERE id = ?", (event_id,))
    line = _one_line_error(cli("status", db, timeout=120), db)
    assert "campaign 1, table campaigns: column lab_config is not JSON" in line, line
    r = cli("check", "--db", db, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "campaign 1, table campaigns, row 1: column lab_config is not JSON" in r.stdout, r.stdout
    assert f"campaign 1, table events, row {event_id}, step {step}: column detail is not JSON" in r.stdout, r.stdout
    with sqlite3.connect(db) as conn:  # the events' JSON alone, as read through the Python API
        conn.execute("UPDATE campaigns SET lab_config = '{}'")
    with labrunner.open(db) as d, pytest.raises(StoreDamage, match=f"campaign 1, table events, step {step}"):
        d.campaign().events()


@pytest.mark.parametrize("column, cut", [("accel_g", 100), ("counter", 7), ("temp_c", 0)])
def test_short_blob_names_campaign_and_step(clean_db, tmp_path, column, cut):
    db = _copy(clean_db, tmp_path, "short.db")
    with sqlite3.connect(db) as conn:
        block, n = conn.execute("SELECT id, n FROM sample_blocks WHERE kind = 'record' AND step_idx = 5").fetchone()
        conn.execute(f"UPDATE sample_blocks SET {column} = substr({column}, 1, ?) WHERE id = ?", (cut, block))
    where = f"campaign 1, table sample_blocks, step 5 (block {block}): column {column} holds {cut} bytes"
    for args in (("export", db, "--csv", tmp_path / "out.csv"), ("fit", db)):
        line = _one_line_error(cli(*args, timeout=120), db)
        assert where in line and f"{n} samples need" in line, line
    r = cli("check", "--db", db, timeout=120)
    assert r.returncode == 2 and where in r.stdout, r.stdout + r.stderr


def test_a_schema_version_that_is_not_a_number_is_named(clean_db, tmp_path):
    db = _copy(clean_db, tmp_path, "meta.db")
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE labrunner_meta SET value = 'x7' WHERE key = 'schema_version'")
    line = _one_line_error(cli("status", db, timeout=120), db)
    assert "table labrunner_meta: schema version 'x7'" in line, line
