"""Nothing overwritten silently (issue 12, item 4): `check_output` case by case, then the commands
and the API that use it, on a real store whose bytes must not change when a write is refused."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

import labrunner
from labrunner.cli import main
from labrunner.output_paths import OutputPathError, check_output
from labrunner.store import Store

from .test_api import TINY

# The tiny procedure with its end-of-run fit switched on (a small one: order 1, no RBF).
TINY_FIT = TINY.replace("fit: {run: false}", "fit: {run: true, polynomial_order: 1, rbf: false}")
FAST_FIT = ["--order", "1", "--rbf", "", "--no-eval", "--quiet"]


def fingerprint(db: Path) -> dict[str, str]:
    """SHA-256 of a store and of whichever SQLite companion files exist beside it."""
    files = [db, *(Path(f"{db}{s}") for s in ("-wal", "-shm", "-journal"))]
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in files if f.exists()}


def cli(*args: object, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrunner", *map(str, args)], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


# --- check_output, case by case ------------------------------------------------------------------------


def test_a_new_file_in_an_existing_directory_is_allowed(tmp_path: Path) -> None:
    assert check_output(tmp_path / "new.csv", inputs=[tmp_path / "in.db"]) == (tmp_path / "new.csv").resolve()


def test_stdout_is_allowed_only_where_the_caller_says(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert check_output("-", inputs=["x.db"], allow_stdout=True) is None
    Path("-").write_text("a file named '-'")
    with pytest.raises(OutputPathError, match="exists"):
        check_output("-", inputs=["x.db"])  # a command without stdout writes a file called '-'


def test_the_store_itself_is_refused_even_with_force(tmp_path: Path) -> None:
    db = tmp_path / "w.db"
    Store.create(db).close()
    with pytest.raises(OutputPathError, match=r"--csv .*w.db is the store .*w.db; refusing to overwrite it"):
        check_output(db, store=db, force=True, option="--csv")
    with pytest.raises(OutputPathError, match=r"is the store"):  # named as the store when it is an input too
        check_output(db, store=db, inputs=[db], force=True)


def test_a_store_given_by_url_is_protected_by_its_file_or_not_at_all(tmp_path: Path) -> None:
    from labrunner.store_address import store_address

    db = tmp_path / "u.db"
    for store in (f"sqlite:///{db}", store_address(f"sqlite:///{db}")):  # a SQLite URL names its file
        with pytest.raises(OutputPathError, match="is the store"):
            check_output(db, store=store, force=True)
        with pytest.raises(OutputPathError, match="companion file of the store"):
            check_output(f"{db}-wal", store=store, force=True)
    # A server database is no file: an output may be named anything, the password is never in a message.
    server = "postgresql+psycopg://u:s3cret@db.lab/cal"
    assert check_output(tmp_path / "cal", store=server, force=True) == (tmp_path / "cal").resolve()
    (tmp_path / "old.csv").write_text("x")
    with pytest.raises(OutputPathError) as err:
        check_output(tmp_path / "old.csv", store=store_address(server), inputs=[server])
    assert "s3cret" not in str(err.value)


def test_an_input_that_is_not_a_store_is_named_an_input(tmp_path: Path) -> None:
    proc = tmp_path / "quick.yaml"
    proc.write_text(TINY)
    with pytest.raises(OutputPathError, match="is the input"):
        check_output(proc, inputs=[proc], force=True, option="--lab-config")


def test_the_same_file_by_another_name_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    db = tmp_path / "w.db"
    Store.create(db).close()
    (tmp_path / "sub").mkdir()
    monkeypatch.chdir(tmp_path / "sub")
    for alias in ("../w.db", f"{tmp_path}/./sub/../w.db"):
        with pytest.raises(OutputPathError, match="is the store"):
            check_output(alias, store=db, force=True)
    os.symlink(db, tmp_path / "link.db")
    with pytest.raises(OutputPathError, match="is the store"):
        check_output(tmp_path / "link.db", store=db, force=True)
    os.link(db, tmp_path / "hard.db")  # a hard link resolves to itself: only samefile sees it
    with pytest.raises(OutputPathError, match="is the store"):
        check_output(tmp_path / "hard.db", store=db, force=True)
    with pytest.raises(OutputPathError, match="is the input"):  # and the other way round
        check_output(db, inputs=[tmp_path / "hard.db"], force=True)


@pytest.mark.parametrize("suffix", ["-wal", "-shm", "-journal"])
def test_sqlite_companions_are_refused_whether_they_exist_or_not(tmp_path: Path, suffix: str) -> None:
    db = tmp_path / "w.db"
    Store.create(db).close()
    with pytest.raises(OutputPathError, match=f"w.db{suffix} is a companion file of the store"):
        check_output(f"{db}{suffix}", store=db, force=True)
    with pytest.raises(OutputPathError, match=f"w.db{suffix} is a companion file of the input"):
        check_output(f"{db}{suffix}", inputs=[db], force=True)  # fit and diagnose read a store or a CSV


def test_an_existing_file_needs_force(tmp_path: Path) -> None:
    out = tmp_path / "out.csv"
    out.write_text("old")
    with pytest.raises(OutputPathError, match=r"--csv .*out.csv exists; use --force to overwrite it"):
        check_output(out, option="--csv")
    assert check_output(out, force=True) == out.resolve()
    assert out.read_text() == "old"  # the check itself writes nothing


def test_file_outputs_need_an_existing_parent_and_are_not_directories(tmp_path: Path) -> None:
    with pytest.raises(OutputPathError, match="directory .*nowhere does not exist"):
        check_output(tmp_path / "nowhere" / "x.json")
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputPathError, match="is not a directory"):
        check_output(tmp_path / "file" / "x.json", force=True)
    with pytest.raises(OutputPathError, match="is a directory"):
        check_output(tmp_path, force=True)


def test_a_directory_output_new_empty_or_forced(tmp_path: Path) -> None:
    assert check_output(tmp_path / "a" / "b", directory=True) == (tmp_path / "a" / "b").resolve()  # created later
    out = tmp_path / "out"
    out.mkdir()
    assert check_output(out, directory=True) == out.resolve()
    (out / "polynomial.json").write_text("{}")
    with pytest.raises(OutputPathError, match=r"--out .*out is not empty; use --force to write into it"):
        check_output(out, directory=True, option="--out")
    assert check_output(out, directory=True, force=True) == out.resolve()


def test_a_directory_output_that_is_a_file_or_under_one(tmp_path: Path) -> None:
    db = tmp_path / "x.db"
    Store.create(db).close()
    with pytest.raises(OutputPathError, match="is the store"):
        check_output(db, store=db, directory=True, force=True)
    with pytest.raises(OutputPathError, match="is a file, not a directory"):
        check_output(db, directory=True, force=True)
    with pytest.raises(OutputPathError, match="is not a directory"):
        check_output(db / "fit", directory=True, force=True)


def test_a_directory_holding_an_input_is_refused_even_with_force(tmp_path: Path) -> None:
    # The writers put fixed names (evaluation.csv, summary.md, ...) into it: an input there could be hit.
    data = tmp_path / "evaluation.csv"
    data.write_text("t_s\n")
    with pytest.raises(OutputPathError, match="holds the input"):
        check_output(tmp_path, inputs=[data], directory=True, force=True)
    # An input deeper down is out of the writers' reach.
    assert check_output(tmp_path.parent, inputs=[data], directory=True, force=True) == tmp_path.parent.resolve()


def test_the_check_opens_no_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Closing any descriptor of a database drops the SQLite locks this process holds on it (POSIX
    # locks are per process and file): a run checks its fit directory with its store open, and a
    # dropped lock let `labrunner abort`'s process delete the WAL the run was writing.
    db = tmp_path / "w.db"
    Store.create(db).close()
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "x").write_text("")

    def no_open(*args: object, **kwargs: object) -> None:
        raise AssertionError(f"check_output opened {args[0]!r}")

    monkeypatch.setattr("builtins.open", no_open)
    monkeypatch.setattr("os.open", no_open)
    for kwargs in ({"store": db}, {"inputs": [db]}):
        with pytest.raises(OutputPathError, match="is the"):
            check_output(db, force=True, **kwargs)  # type: ignore[arg-type]
        with pytest.raises(OutputPathError, match="holds the"):
            check_output(tmp_path, force=True, directory=True, **kwargs)  # type: ignore[arg-type]
        with pytest.raises(OutputPathError, match="not empty"):
            check_output(tmp_path / "out", directory=True, **kwargs)  # type: ignore[arg-type]


def test_a_running_store_keeps_its_wal_through_refused_writes(tmp_path: Path) -> None:
    # The failure the check once caused: with the run's locks dropped, another process closing the
    # store took itself for the last one and deleted the WAL the run still wrote to.
    db = tmp_path / "w.db"
    proc = tmp_path / "tiny.yaml"
    proc.write_text(TINY)
    with labrunner.start_run(proc, db=db) as session:
        def refuse_and_peek(p: labrunner.Progress) -> None:
            if p.steps_done == 2 and p.state == "rate_settling":
                with labrunner.open(db) as database:  # as a script reading its own running store would
                    with pytest.raises(labrunner.OutputPathError):
                        database.campaign().export_csv(db, force=True)
                code = f"import labrunner; labrunner.list_campaigns({str(db)!r})"
                peek = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
                assert peek.returncode == 0, peek.stderr
                assert Path(f"{db}-wal").exists(), "another process deleted the WAL of the running store"

        result = session.execute(refuse_and_peek)
    assert result.state == "done" and result.steps_done == 36
    assert labrunner.status(db).steps_done == 36


def test_missing_inputs_and_none_are_fine(tmp_path: Path) -> None:
    assert check_output(tmp_path / "o.json", inputs=[None, tmp_path / "absent.csv"]) is not None
    with pytest.raises(OutputPathError):  # an absent input still may not be the output
        check_output(tmp_path / "absent.csv", inputs=[tmp_path / "absent.csv"])


# --- the commands and the API on a real store -------------------------------------------------------------


@pytest.fixture(scope="module")
def store_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("outputs")
    (d / "tiny.yaml").write_text(TINY)
    assert labrunner.run(d / "tiny.yaml", db=d / "w.db", seed=2).state == "done"
    return d


def test_export_to_the_store_is_refused_and_the_store_is_intact(store_dir: Path) -> None:
    before = fingerprint(store_dir / "w.db")
    for target in ("w.db", "w.db-wal", "./w.db"):
        proc = cli("export", "w.db", "--csv", target, "--force", cwd=store_dir)
        assert proc.returncode == 2, proc.stderr
        assert f"labrunner export: error: --csv {Path(target)} is " in proc.stderr and "Traceback" not in proc.stderr
    assert fingerprint(store_dir / "w.db") == before
    assert labrunner.status(store_dir / "w.db").steps_done == 36  # still a readable store


def test_fit_json_to_the_store_is_refused_and_the_store_is_intact(store_dir: Path) -> None:
    before = fingerprint(store_dir / "w.db")
    proc = cli("fit", "w.db", "--json", "w.db", *FAST_FIT, cwd=store_dir)
    assert proc.returncode == 2 and proc.stderr.strip() == (
        "labrunner fit: error: --json w.db is the store w.db; refusing to overwrite it (choose another path)")
    proc = cli("fit", "w.db", "--out", "w.db", "--force", *FAST_FIT, cwd=store_dir)
    assert proc.returncode == 2 and "--out w.db is the store w.db" in proc.stderr
    assert fingerprint(store_dir / "w.db") == before  # refused before the fit was computed or stored
    with labrunner.open(store_dir / "w.db") as db:
        assert db.campaign().fits().empty


def test_diagnose_json_to_the_store_is_refused(store_dir: Path) -> None:
    before = fingerprint(store_dir / "w.db")
    assert main(["diagnose", str(store_dir / "w.db"), "--json", str(store_dir / "w.db"), "--force"]) == 2
    assert main(["diagnose", str(store_dir / "w.db"), "--json", str(store_dir / "d.json"),
                 "--model", str(store_dir / "d.json")]) == 2
    assert fingerprint(store_dir / "w.db") == before
    assert not (store_dir / "d.json").exists()


def test_existing_outputs_need_force_on_the_command_line(store_dir: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    db = str(store_dir / "w.db")
    csv = tmp_path / "w.csv"
    csv.write_text("precious\n")
    assert main(["export", db, "--csv", str(csv)]) == 2
    assert f"--csv {csv} exists; use --force to overwrite it" in capsys.readouterr().err
    assert csv.read_text() == "precious\n"
    assert main(["export", db, "--csv", str(csv), "--force"]) == 0
    assert csv.read_text().startswith("t_s,run,orientation")

    out = tmp_path / "fit"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    fit_json = tmp_path / "fit.json"
    fit_json.write_text("{}")
    assert main(["fit", db, "--json", str(fit_json), "--no-store", *FAST_FIT]) == 2
    assert main(["fit", db, "--out", str(out), "--no-store", *FAST_FIT]) == 2
    assert fit_json.read_text() == "{}" and sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert main(["fit", db, "--json", str(fit_json), "--out", str(out), "--no-store", "--force", *FAST_FIT]) == 0
    assert '"models"' in fit_json.read_text() and (out / "polynomial.json").exists() and (out / "notes.txt").exists()
    assert main(["fit", db, "--json", "-", "--no-store", *FAST_FIT]) == 0  # stdout stays allowed
    assert '"models"' in capsys.readouterr().out


def test_sim_serve_does_not_overwrite_a_procedure(tmp_path: Path) -> None:
    proc = tmp_path / "quick.yaml"
    proc.write_text(TINY)
    args = ["sim", "serve", "--speed", "600", "--lab-config", proc, "--duration", "0"]
    refused = cli(*args, cwd=tmp_path)
    assert refused.returncode == 2 and "quick.yaml exists; use --force" in refused.stderr
    assert proc.read_text() == TINY
    refused = cli(*args, "--config", proc, "--force", cwd=tmp_path)  # the sim configuration read is an input
    assert refused.returncode == 2 and "is the input" in refused.stderr and proc.read_text() == TINY
    served = cli(*args, "--force", cwd=tmp_path)  # asked for: replaced by a lab configuration
    assert served.returncode == 0, served.stderr
    assert "chamber:" in proc.read_text()


def test_the_api_checks_as_the_commands_do(store_dir: Path, tmp_path: Path) -> None:
    db = store_dir / "w.db"
    before = fingerprint(db)
    with labrunner.open(db) as database:
        campaign = database.campaign()
        with pytest.raises(labrunner.OutputPathError, match="is the store"):
            campaign.export_csv(db, force=True)
        with pytest.raises(labrunner.OutputPathError, match="holds the store"):
            campaign.fit(out=store_dir, force=True, poly_order=1, rbf_variants=(), rbf_export="", evaluate=False)
        (tmp_path / "x.csv").write_text("")
        with pytest.raises(labrunner.OutputPathError, match="exists"):
            campaign.export_csv(tmp_path / "x.csv")
    with pytest.raises(labrunner.UserError, match="holds the store"):
        labrunner.fit(db, out=store_dir, save=False, force=True)
    assert fingerprint(db) == before


# --- the end-of-run fit: one directory per campaign --------------------------------------------------------


def test_each_campaign_fits_into_its_own_directory(tmp_path: Path) -> None:
    proc = tmp_path / "tiny.yaml"
    proc.write_text(TINY_FIT)
    db = tmp_path / "x.db"
    first = labrunner.run(proc, db=db)
    second = labrunner.run(proc, db=db)
    assert (first.campaign_id, second.campaign_id) == (1, 2) and first.fit_ok and second.fit_ok
    assert first.fit_out == tmp_path / "x_fit" / "campaign-1" and second.fit_out == tmp_path / "x_fit" / "campaign-2"
    one, two = (first.fit_out / "polynomial.json").read_text(), (second.fit_out / "polynomial.json").read_text()
    assert one != two  # the second campaign did not overwrite the first one's models

    # A store made again under the same name restarts its ids: campaign-1's directory is then refused.
    for f in tmp_path.glob("x.db*"):
        f.unlink()
    with pytest.raises(labrunner.OutputPathError, match=r"the fit directory .*campaign-1 is not empty; use --force"):
        labrunner.run(proc, db=db)
    assert labrunner.list_campaigns(db) == []  # refused before the campaign was created
    assert (first.fit_out / "polynomial.json").read_text() == one
    again = labrunner.run(proc, db=db, force=True)
    assert again.fit_ok and again.fit_out == first.fit_out


def test_explicit_fit_out_is_kept_and_checked(tmp_path: Path) -> None:
    proc = tmp_path / "tiny.yaml"
    proc.write_text(TINY_FIT)
    db = tmp_path / "x.db"
    result = labrunner.run(proc, db=db, fit_out=tmp_path / "models")
    assert result.fit_out == tmp_path / "models" and (tmp_path / "models" / "polynomial.json").exists()
    with pytest.raises(labrunner.OutputPathError, match="models is not empty"):
        labrunner.run(proc, db=db, fit_out=tmp_path / "models")
    with pytest.raises(labrunner.OutputPathError, match="holds the store"):
        labrunner.run(proc, db=db, fit_out=tmp_path, force=True)
    assert [s.campaign_id for s in labrunner.list_campaigns(db)] == [1]  # the refusals added no campaign
    proc_cli = cli("run", proc, "--sim", "--db", db, "--fit-out", tmp_path / "models", "--quiet", cwd=tmp_path)
    assert proc_cli.returncode == 2 and "use --force" in proc_cli.stderr
    resumed = cli("resume", db, "--fit-out", db, cwd=tmp_path)  # a done campaign: nothing to write
    assert resumed.returncode == 0 and "nothing to resume" in resumed.stdout
