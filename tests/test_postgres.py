"""A store in PostgreSQL, by URL (issue 12, item 1): every command on it, passwords never shown, one-line
errors for a server that cannot be used, damage named, and a server lost mid-run handled as a store
failure. The server is a throwaway cluster (tests/pg_server.py, fixture `pg_cluster`)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

import labrunner
from labrunner.errors import UserError
from labrunner.store import Store
from labrunner.store_address import is_store, store_address
from tests import pg_server
from tests.campaign.conftest import TINY, cli
from tests.store_sql import store_rows

FULL_DISK_CLI = Path(__file__).parent / "campaign" / "full_disk_cli.py"
# Four temperatures (the cubic thermal fit needs them), the end-of-run fit on: it writes summary.md.
FITTED = (TINY.replace("list_c: [15, 35]", "list_c: [-10, 10, 30, 50]").replace("record_s: 4", "record_s: 6")
          .replace("fit: {run: false}", "fit: {run: true, polynomial_order: 3, rbf: false}"))


def _main(capsys: pytest.CaptureFixture[str], *args: object) -> subprocess.CompletedProcess[str]:
    """`labrunner ARGS` in this process (the command line's own `main`, errors and exit codes included):
    a subprocess costs seconds of imports, and these tests run many commands."""
    from labrunner.cli import main

    capsys.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as exc:  # argparse's own errors (a DB argument no store can have)
        code = int(exc.code or 0)
    out = capsys.readouterr()
    return subprocess.CompletedProcess([str(a) for a in args], code, out.out, out.err)


def _one_line(r: subprocess.CompletedProcess[str], code: int) -> str:
    assert r.returncode == code, (r.returncode, r.stdout[-1000:], r.stderr[-2000:])
    assert "Traceback" not in r.stderr, r.stderr
    lines = [line for line in r.stderr.splitlines() if "error:" in line]  # fit's progress lines aside
    assert len(lines) == 1, r.stderr
    return lines[0]


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


@pytest.fixture(scope="module")
def done_db(pg_cluster: pg_server.PgServer, tmp_path_factory: pytest.TempPathFactory) -> str:
    """A database holding the tiny procedure run to the end (a template: each test copies it)."""
    folder = tmp_path_factory.mktemp("pg")
    procedure = folder / "tiny.yaml"
    procedure.write_text(TINY)
    name = pg_cluster.new_database("done")
    assert labrunner.run(procedure, db=pg_cluster.url(name)).state == "done"
    return name


def _copy(pg_cluster: pg_server.PgServer, done_db: str) -> str:
    return pg_cluster.url(pg_cluster.new_database(template=done_db))


# --- addresses -------------------------------------------------------------------------------------------------


def test_paths_and_urls_name_stores(tmp_path: Path) -> None:
    assert store_address(tmp_path / "c.db").file == tmp_path / "c.db"
    assert store_address(f"sqlite:///{tmp_path}/c.db").file == tmp_path / "c.db"
    pg = store_address("postgresql://u:secret@db.lab:5433/cal")
    assert pg.is_server and pg.url.drivername == "postgresql+psycopg" and pg.url.password == "secret"
    assert str(pg) == "postgresql+psycopg://u:***@db.lab:5433/cal" and pg.server == "db.lab:5433"
    assert pg.beside("_fit") == Path("cal_fit")
    for bad, says in [("mysql://u:secret@h/db", "labrunner stores are"), ("postgresql://u@h", "names no database"),
                      ("postgresql+psycopg2://u@h/db", "not the one labrunner uses"),
                      ("sqlite://", "must be a file")]:
        with pytest.raises(UserError, match=says) as err:
            store_address(bad)
        assert "secret" not in str(err.value)
    assert is_store("postgresql+psycopg://u@h/db") and not is_store(tmp_path / "missing.csv")


def test_a_url_creates_no_local_file(pg_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "tiny.yaml").write_text(TINY)
    monkeypatch.chdir(tmp_path)
    r = _main(capsys, "run", "tiny.yaml", "--sim", "--db", pg_url, "--quiet")
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.yaml"]  # the data went to the server
    assert store_rows(pg_url, "SELECT count(*) FROM steps WHERE status = 'done'") == [(36,)]


# --- every command, and the password nowhere -------------------------------------------------------------------


def test_a_password_in_the_url_is_never_shown(pg_cluster: pg_server.PgServer, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    name = pg_cluster.new_database(owner=pg_server.PASSWORD_USER)
    url = pg_cluster.url(name, user=pg_server.PASSWORD_USER, password=pg_server.PASSWORD)
    procedure = tmp_path / "fitted.yaml"
    procedure.write_text(FITTED)
    out = tmp_path / "out"
    out.mkdir()
    runs = [cli("-v", "run", procedure, "--sim", "--db", url, "--fit-out", out / "end-fit", check=0),
            _main(capsys, "-v", "fit", url, "--json", out / "fit.json", "--out", out / "fit", "--no-eval"),
            _main(capsys, "list", url), _main(capsys, "status", url), _main(capsys, "check", "--db", url),
            _main(capsys, "export", url, "--csv", out / "data.csv"),
            _main(capsys, "report", url, "--html", out / "r.html")]
    assert [r.returncode for r in runs] == [0] * len(runs), [r.stderr[-1000:] for r in runs]
    assert (out / "end-fit" / "summary.md").is_file() and (out / "fit.json").is_file()
    masked = f"{pg_server.PASSWORD_USER}:***@127.0.0.1:{pg_cluster.port}/{name}"
    assert masked in runs[0].stdout and masked in runs[2].stdout
    for r in runs:
        assert pg_server.PASSWORD not in r.stdout + r.stderr, (r.args, r.stdout[-500:], r.stderr[-500:])
    for path in out.rglob("*"):
        if path.is_file():
            assert pg_server.PASSWORD.encode() not in path.read_bytes(), path
    stored = json.dumps(store_rows(url, "SELECT lab_config, sim_config, procedure_path FROM campaigns")
                        + store_rows(url, "SELECT provenance, result FROM fits")
                        + store_rows(url, "SELECT message, detail FROM events"))
    assert pg_server.PASSWORD not in stored
    assert store_rows(url, "SELECT count(*) FROM fits") == [(2,)]  # the end-of-run fit and `fit`'s, stored back
    assert masked in json.loads(store_rows(url, "SELECT provenance FROM fits ORDER BY id DESC LIMIT 1")[0][0])["source"]


def test_the_password_from_pgpassword_or_pgpass(pg_cluster: pg_server.PgServer, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    name = pg_cluster.new_database(owner=pg_server.PASSWORD_USER)
    url = pg_cluster.url(name, user=pg_server.PASSWORD_USER)  # no password in the URL
    (tmp_path / "tiny.yaml").write_text(TINY.replace("list_dps: [-50, 0, 50]", "list_dps: [0]"))
    monkeypatch.delenv("PGPASSWORD", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.pgpass
    line = _one_line(_main(capsys, "list", url), 1)
    assert "refused the login of lab_pw@127.0.0.1" in line and "PGPASSWORD or ~/.pgpass" in line
    monkeypatch.setenv("PGPASSWORD", pg_server.PASSWORD)
    r = _main(capsys, "run", tmp_path / "tiny.yaml", "--sim", "--db", url, "--quiet")
    assert r.returncode == 0, r.stderr[-2000:]
    home = tmp_path / "home"
    home.mkdir()
    pgpass = home / ".pgpass"
    pgpass.write_text(f"127.0.0.1:{pg_cluster.port}:{name}:{pg_server.PASSWORD_USER}:{pg_server.PASSWORD}\n")
    pgpass.chmod(0o600)
    monkeypatch.delenv("PGPASSWORD")
    monkeypatch.setenv("HOME", str(home))
    r = _main(capsys, "list", url)
    assert "1 campaign" in r.stdout, r.stderr
    assert pg_server.PASSWORD not in r.stdout + r.stderr


def test_resume_abort_status_watch_diagnose_on_a_server(pg_url: str, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    procedure = tmp_path / "tiny.yaml"
    procedure.write_text(TINY.replace("record_s: 4", "record_s: 6"))  # records long enough to fit
    with labrunner.start_run(procedure, db=pg_url) as session:
        session.request_pause("test: paused before the first step")
        assert session.execute().state == "paused"
    r = cli("resume", pg_url, "--quiet")  # a subprocess: resume takes the lease as another process would
    assert r.returncode == 0, r.stderr[-2000:]
    assert "1 campaign" in _main(capsys, "list", pg_url).stdout
    st = _main(capsys, "status", pg_url, "--watch", "1")  # a finished campaign: one view, then it ends
    assert st.returncode == 0 and "done" in st.stdout and "36/36" in st.stdout, st.stdout + st.stderr
    a = _main(capsys, "abort", pg_url)
    assert a.returncode == 0 and "campaign 1 is already done" in a.stdout, a.stdout + a.stderr
    d = _main(capsys, "diagnose", pg_url, "--json", tmp_path / "d.json", "--causes", "thermal_lag")
    assert d.returncode == 0, d.stderr[-2000:]
    assert json.loads((tmp_path / "d.json").read_text())["data"]["kind"] == "store"


def test_a_new_campaign_takes_the_id_it_checked(pg_cluster: pg_server.PgServer, pg_url: str, tmp_path: Path) -> None:
    # A PostgreSQL sequence moves on when an insert rolls back: the largest id + 1 is not the next id.
    procedure = tmp_path / "tiny.yaml"
    procedure.write_text(TINY.replace("fit: {run: false}", "fit: {run: true}"))
    store = Store.create(pg_url)
    try:
        assert store.reserve_campaign_id() == 1  # drawn and dropped, as a refused run would
    finally:
        store.close()
    with labrunner.start_run(procedure, db=pg_url, fit_out=tmp_path / "f") as session:
        assert session.campaign_id == 2
        assert session.runner is not None and session.runner.fit_out_dir == tmp_path / "f"
    assert store_rows(pg_url, "SELECT id FROM campaigns") == [(2,)]


# --- errors -----------------------------------------------------------------------------------------------------


def test_a_server_that_cannot_be_used_gets_one_line(pg_cluster: pg_server.PgServer, pg_url: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    port = pg_cluster.port
    dead = pg_server._free_port()
    cases = [
        (f"postgresql+psycopg://lab@127.0.0.1:{dead}/x", 1, f"cannot reach the PostgreSQL server at 127.0.0.1:{dead}: "
                                                          "connection refused"),
        ("postgresql+psycopg://lab:pw@no-such-host.invalid:5432/x", 1, "unknown host 'no-such-host.invalid'"),
        (pg_cluster.url("postgres", user="lab_pw", password="wrong-Pass1"), 1,
         f"the PostgreSQL server at 127.0.0.1:{port} refused the login of lab_pw@127.0.0.1: password authentication "
         "failed"),
        (pg_cluster.url("no_such_db"), 2, f"the PostgreSQL server at 127.0.0.1:{port} has no database 'no_such_db'"),
        (pg_url, 2, "not a labrunner database (no table labrunner_meta"),  # an empty database: no schema
        ("mysql://u:pw@h/db", 2, "labrunner stores are a SQLite file"),
    ]
    for url, code, says in cases:
        for args in (("list", url), ("status", url), ("fit", url, "--json", "-"), ("export", url, "--csv", "-"),
                     ("check", "--db", url), ("abort", url)):
            line = _one_line(_main(capsys, *args), code)
            assert says in line, (args, line)
            assert "wrong-Pass1" not in line and ":pw@" not in line, line
    a_run = _one_line(cli("resume", f"postgresql+psycopg://lab@127.0.0.1:{dead}/x", timeout=60), 1)
    assert "connection refused" in a_run


def test_a_foreign_database_is_not_taken_over(pg_url: str, tiny: Path, capsys: pytest.CaptureFixture[str]) -> None:
    store_rows(pg_url, "CREATE TABLE campaigns (x int)")
    line = _one_line(_main(capsys, "run", tiny, "--sim", "--db", pg_url), 2)
    assert "not a labrunner database (it holds table campaigns but no labrunner_meta)" in line


# --- damage -----------------------------------------------------------------------------------------------------


def test_check_db_on_a_clean_server_store(pg_cluster: pg_server.PgServer, done_db: str) -> None:
    r = cli("check", "--db", pg_cluster.url(done_db), check=0)
    assert "the store is intact: page-level checks are the PostgreSQL server's job" in r.stdout, r.stdout
    assert "1 campaign(s)" in r.stdout


def test_bad_json_and_a_short_blob_are_named(pg_cluster: pg_server.PgServer, done_db: str, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    url = _copy(pg_cluster, done_db)
    store_rows(url, "UPDATE campaigns SET lab_config = '{not json'")
    block, n = store_rows(url, "SELECT id, n FROM sample_blocks WHERE kind = 'record' AND step_idx = 5")[0]
    store_rows(url, "UPDATE sample_blocks SET accel_g = substring(accel_g from 1 for 100) WHERE id = :id", id=block)
    line = _one_line(cli("status", url), 2)
    assert "campaign 1, table campaigns: column lab_config is not JSON" in line, line
    store_rows(url, "UPDATE campaigns SET lab_config = '{}'")
    where = f"campaign 1, table sample_blocks, step 5 (block {block}): column accel_g holds 100 bytes"
    for args in (("export", url, "--csv", tmp_path / "out.csv"), ("fit", url)):
        line = _one_line(_main(capsys, *args), 2)
        assert where in line and f"{n} samples need" in line, line
    store_rows(url, "UPDATE campaigns SET lab_config = '{x'")
    r = _main(capsys, "check", "--db", url)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "campaign 1, table campaigns, row 1: column lab_config is not JSON" in r.stdout
    assert where in r.stdout
    store_rows(url, "UPDATE labrunner_meta SET value = 'x7' WHERE key = 'schema_version'")
    assert "table labrunner_meta: schema version 'x7'" in _one_line(_main(capsys, "list", url), 2)


# --- output guards ---------------------------------------------------------------------------------------------


def test_output_guards_protect_the_inputs_of_a_server_store(pg_cluster: pg_server.PgServer, done_db: str,
                                                            tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url = pg_cluster.url(done_db)
    existing = tmp_path / "old.csv"
    existing.write_text("keep me")
    assert "exists; use --force" in _one_line(_main(capsys, "export", url, "--csv", existing), 2)
    assert existing.read_text() == "keep me"
    procedure = tmp_path / "fit.yaml"
    procedure.write_text(TINY.replace("fit: {run: false}", "fit: {run: true}"))
    line = _one_line(_main(capsys, "run", procedure, "--sim", "--db", pg_cluster.url(pg_cluster.new_database()),
                           "--fit-out", tmp_path, "--force"), 2)
    assert "holds the input" in line and procedure.read_text().startswith("name: tiny")


# --- the server lost mid-run -----------------------------------------------------------------------------------


def test_a_server_stopped_mid_run_leaves_the_lab_safe_and_resume_finishes(pg_cluster: pg_server.PgServer,
                                                                           pg_url: str, tiny: Path,
                                                                           tmp_path: Path) -> None:
    rates = "[-100, -75, -50, -25, 0, 10, 25, 50, 75, 100]"  # 120 steps: long enough to be caught mid-run
    tiny.write_text(tiny.read_text().replace("list_dps: [-50, 0, 50]", f"list_dps: {rates}"))
    state = tmp_path / "sim_state.json"
    # full_disk_cli.py never fills anything here (after 10**9 records): it records the simulated lab's last state.
    run = subprocess.Popen([sys.executable, str(FULL_DISK_CLI), str(10**9), str(state), "run", str(tiny), "--sim",
                            "--db", pg_url, "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while True:
        try:
            if store_rows(pg_url, "SELECT count(*) FROM steps WHERE status = 'done'")[0][0] >= 5:
                break
        except Exception:  # the schema is not there yet
            pass
        assert run.poll() is None and time.monotonic() < deadline, "the run ended before it was caught"
        time.sleep(0.05)
    pg_cluster.stop("immediate")  # as a crash of the server or its machine: every connection gone at once
    try:
        _out, err = run.communicate(timeout=120)
    finally:
        pg_cluster.start()
    assert run.returncode == 1, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    assert f"cannot write the database {pg_url}" in err or f"cannot read the database {pg_url}" in err, err[-3000:]
    sim = json.loads(state.read_text())
    assert sim["table_commands"][-1][1] == 0.0 and sim["table_commanded_dps"] == 0.0
    assert sim["chamber_setpoint_c"] == 23.0
    st = cli("status", pg_url, check=0).stdout
    assert re.search(r"status\s+(failed|running \(process gone: resume it\))", st), st
    done_before = store_rows(pg_url, "SELECT count(*) FROM steps WHERE status = 'done'")[0][0]
    assert done_before >= 5
    res = cli("resume", pg_url, "--quiet")
    assert res.returncode == 0, res.stderr[-3000:]
    with Store.open_existing(pg_url) as store:
        steps = store.steps_frame(1)
        assert (steps.status == "done").all() and store.campaign(1).status == "done"
        ev = store.events_frame(1)
        recorded = sorted(int(m.split()[1]) for m in ev.message if re.match(r"step \d+ recorded: ", m))
        assert recorded == list(range(len(steps)))  # every step exactly once, the committed ones kept
        assert len(store.samples_frame(1)) == int(steps.n_samples.sum())


def test_a_terminated_connection_is_replaced_not_fatal(pg_cluster: pg_server.PgServer, pg_url: str,
                                                       tiny: Path) -> None:
    # A server that drops the store's connections between writes (pg_terminate_backend, a failover) costs
    # nothing: the pool checks a connection before use.
    with labrunner.start_run(tiny, db=pg_url) as session:
        session.request_pause("test")
        session.execute()
    store = Store.open_existing(pg_url)
    try:
        assert store.campaign_ids() == [1]
        assert pg_cluster.terminate(store_address(pg_url).url.database or "") >= 1
        assert store.campaign(1).status == "paused"
    finally:
        store.close()
