"""The Python API (labrunner.api, docs/api.md): its examples run, and what it returns matches the store."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import labrunner
from labrunner.campaign_csv import COLUMNS
from labrunner.store import STEP_COLUMNS, Store

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "api.md"

TINY = """\
name: tiny
temperatures: {list_c: [15, 35], order: serpentine}
soak: {tolerance_c: 0.5, stable_window_s: 120, max_wait_s: 7200, on_timeout: continue, sensor: imu, poll_s: 30}
orientations: [x_up, x_down, y_up, y_down, z_up, z_down]
remount_c: 23
remount_s: 60
rates: {list_dps: [-50, 0, 50]}
settle_s: 1
record_s: 6
record_poll_s: 3
fit: {run: false}
"""
N_STEPS, FRAMES = 36, 300  # 6 orientations x 2 temperatures x 3 rates; 6 s at 50 Hz (a fit needs 5 s)


def doc_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)


def test_docs_examples_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    blocks = doc_blocks()
    assert len(blocks) >= 5, "docs/api.md lost its examples"
    monkeypatch.chdir(tmp_path)
    ns: dict[str, object] = {}
    for i, block in enumerate(blocks):
        exec(compile(block, f"{DOC}:block{i + 1}", "exec"), ns)
    out = capsys.readouterr().out
    # What the examples claim in their comments is what happened.
    result = ns["result"]
    assert result.state == "done" and result.exit_code == 0 and result.steps_done == result.steps_total == 192
    assert result.fit_out == Path("quick_fit") / "campaign-1"  # each campaign's end-of-run fit in its own directory
    assert (tmp_path / "quick_fit" / "campaign-1" / "polynomial.json").exists()
    assert (tmp_path / "fit" / "rbf.json").exists()
    assert sorted(ns["fit"].model_dicts()) == ["polynomial", "rbf"]
    assert ns["rows"] == 192 * 500 and (tmp_path / "quick.csv").exists()
    assert "1 done 192/192 sim" in out  # the store's summary
    assert "--csv quick.db is the store quick.db; refusing" in out and "quick.csv exists; use --force" in out
    paused, finished = ns["paused"], ns["finished"]
    assert (paused.state, paused.exit_code, paused.steps_done) == ("paused", 3, 5)
    assert (finished.state, finished.steps_recorded) == ("done", N_STEPS - 5)
    assert "paused 3 5" in out and "2 fits stored" in out and "already" in out
    assert len(ns["procedure"].steps()) == N_STEPS and "True True" in out  # the served sims' ports


@pytest.fixture(scope="module")
def tiny_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("api")
    proc = d / "tiny.yaml"
    proc.write_text(TINY)
    seen: list[labrunner.Progress] = []
    result = labrunner.run(proc, db=d / "tiny.db", seed=3, progress=seen.append)
    assert result.state == "done" and result.exit_code == 0 and result.ok and not result.resumable
    assert (result.steps_done, result.steps_total, result.steps_recorded) == (N_STEPS, N_STEPS, N_STEPS)
    assert result.samples == N_STEPS * FRAMES and result.faults == 0 and result.reason is None
    assert result.fit_summary is None and result.fit_out is None  # fit: {run: false}
    # progress: every transition and record, steps_done never going back, ending complete
    assert len(seen) > N_STEPS and seen[-1].steps_done == N_STEPS and seen[-1].state == "done"
    assert all(a.steps_done <= b.steps_done for a, b in zip(seen, seen[1:]))
    return d / "tiny.db"


def test_samples_match_the_store_with_steps_alongside(tiny_db: Path) -> None:
    with labrunner.open(tiny_db) as db:
        (campaign,) = db.campaigns()
        assert campaign.id == db.campaign().id == 1 and campaign.status == "done" and campaign.name == "tiny"
        samples = campaign.samples()
        steps = campaign.steps().set_index("idx")
    with Store.open_existing(tiny_db) as store:
        raw = store.samples_frame(1)
    assert list(samples.columns) == [*COLUMNS, *STEP_COLUMNS]
    assert len(samples) == len(raw) == int(steps.n_samples.sum()) == N_STEPS * FRAMES
    pd.testing.assert_frame_equal(samples[list(COLUMNS)], raw)
    assert set(samples.kind) == {"record"} and set(samples.state) == {"recording"}
    assert samples.step_idx.dtype == "Int64" and not samples.step_idx.isna().any()
    per_step = samples.groupby("step_idx").size()
    assert per_step.index.tolist() == list(range(N_STEPS)) and (per_step == FRAMES).all()
    plan = steps.loc[samples.step_idx.to_numpy(dtype=int)]
    np.testing.assert_array_equal(samples.setpoint_c.to_numpy(), plan.temperature_c.to_numpy())
    np.testing.assert_array_equal(samples.rate_cmd_dps.to_numpy(), plan.rate_dps.to_numpy())
    assert (samples.orientation.to_numpy() == plan.orientation.to_numpy()).all()
    # what the sequencer commanded is what the instruments did (table within 0.1 %, chamber soaked)
    assert np.allclose(samples.table_rate_dps, samples.rate_cmd_dps, rtol=1e-3, atol=0.05)
    assert (samples.chamber_c - samples.setpoint_c).abs().max() < 1.0


def test_monitor_rows_carry_the_state_and_setpoint_of_their_time(tiny_db: Path) -> None:
    with labrunner.open(tiny_db) as db:
        everything = db.campaign().samples(include_monitor=True)
    with Store.open_existing(tiny_db) as store:
        n_monitor = sum(len(b) for b in store.blocks(1, ("monitor",)))
    monitor = everything[everything.kind == "monitor"]
    assert n_monitor > 0 and len(monitor) == n_monitor and len(everything) == n_monitor + N_STEPS * FRAMES
    assert everything.t_s.is_monotonic_increasing
    assert set(monitor.state) == {"mounting", "ramping", "soaking"}
    assert (monitor.rate_cmd_dps == 0).all() and not monitor.step_idx.isna().any()
    assert (monitor[monitor.state == "mounting"].setpoint_c == 23.0).all()  # remount_c
    moving = monitor[monitor.state != "mounting"]
    assert set(moving.setpoint_c) == {15.0, 35.0}
    # a soaked chamber sits at the setpoint the row names
    soaking = moving[moving.state == "soaking"]
    assert (soaking.chamber_c - soaking.setpoint_c).abs().max() < 1.0


def test_events_include_every_transition(tiny_db: Path) -> None:
    with labrunner.open(tiny_db) as db:
        events = db.campaign().events()
    assert {"id", "t_s", "kind", "state", "step_idx", "message", "detail"} <= set(events.columns)
    trans = events[events.kind == "transition"]
    assert trans.message.iloc[0] == "idle -> preflight" and trans.state.iloc[-1] == "done"
    assert (trans.message == "rate_settling -> recording").sum() == N_STEPS
    assert (events.kind == "record").sum() == N_STEPS
    records = events[events.kind == "record"]
    assert all(isinstance(d, dict) and d["dropped"] == 0 for d in records.detail)  # JSON decoded
    assert events.t_s.is_monotonic_increasing


def test_fit_returns_models_and_stores_them(tiny_db: Path, tmp_path: Path) -> None:
    with labrunner.open(tiny_db) as db:
        campaign = db.campaign()
        assert campaign.fits().empty
        fit = campaign.fit(poly_order=1, rbf_variants=(), rbf_export="", evaluate=False, out=tmp_path / "fit")
        assert len(campaign.fits()) == 1
        again = campaign.fit(poly_order=1, rbf_variants=(), rbf_export="", evaluate=False, save=False)
        assert len(campaign.fits()) == 1
    assert sorted(fit.model_dicts()) == ["polynomial"] and fit.rbf is None
    assert set(fit.polynomial.triads()) == {"accel", "gyro"}
    assert fit.provenance["campaign_id"] == 1 and fit.provenance["rows"] == N_STEPS * FRAMES
    assert (tmp_path / "fit" / "polynomial.json").exists() and (tmp_path / "fit" / "imu_calibration.h").exists()
    assert again.to_dict()["models"] == fit.to_dict()["models"]  # the same data give the same models


def test_fit_of_a_csv_equals_the_fit_of_the_store(tiny_db: Path, tmp_path: Path) -> None:
    csv = tmp_path / "tiny.csv"
    with labrunner.open(tiny_db) as db:
        assert db.campaign().export_csv(csv) == N_STEPS * FRAMES
    options = dict(poly_order=1, rbf_variants=(), rbf_export="", evaluate=False)
    from_csv = labrunner.fit(csv, **options)
    from_store = labrunner.fit(tiny_db, save=False, **options)
    for triad in ("accel", "gyro"):
        a, b = from_csv.polynomial.triads()[triad], from_store.polynomial.triads()[triad]
        np.testing.assert_allclose(a.bias, b.bias, rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(a.scale, b.scale, rtol=1e-4, atol=1e-6)
    assert from_csv.provenance["kind"] == "csv" and from_store.provenance["kind"] == "store"


def test_status_of_a_finished_campaign(tiny_db: Path) -> None:
    s = labrunner.status(tiny_db, events=3)
    assert (s.status, s.state, s.mode) == ("done", "done", "sim")
    assert (s.steps_done, s.steps_total, s.samples) == (N_STEPS, N_STEPS, N_STEPS * FRAMES)
    assert s.next_step is None and s.eta_s is None and s.fraction_done == 1.0 and s.faults == 0
    assert [e.message for e in s.recent_events][-1] == "fitting -> done" and len(s.recent_events) == 3


def test_abort_with_no_process_then_resume(tmp_path: Path) -> None:
    proc = tmp_path / "tiny.yaml"
    proc.write_text(TINY)
    db = tmp_path / "t.db"
    with labrunner.start_run(proc, db=db) as session:
        session.request_pause("test")  # before the first step: pauses at the first safe point
        paused = session.execute()
    assert paused.state == "paused" and paused.exit_code == 3 and paused.resumable
    aborted = labrunner.abort(db)
    assert (aborted.outcome, aborted.status_before, aborted.status, aborted.ok) == ("direct", "paused", "aborted", True)
    assert labrunner.abort(db).outcome == "already"
    done = labrunner.resume(db)
    assert done.state == "done" and done.steps_done == N_STEPS and done.steps_recorded == N_STEPS - paused.steps_done
    again = labrunner.resume(db)
    assert again.already_done and again.state == "done" and again.steps_recorded == 0
    with labrunner.open(db) as database:
        ops = database.campaign().events().query("kind == 'operator'").message.tolist()
    assert "test" in ops and "aborted by labrunner abort (no process running)" in ops


def test_ctrl_c_pauses_a_run_with_handle_signals_and_handlers_are_restored(tmp_path: Path) -> None:
    proc = tmp_path / "tiny.yaml"
    proc.write_text(TINY)
    before = signal.getsignal(signal.SIGINT)

    def ctrl_c_after_three(p: labrunner.Progress) -> None:
        if p.steps_done == 3 and p.state == "rate_settling":
            os.kill(os.getpid(), signal.SIGINT)

    result = labrunner.run(proc, db=tmp_path / "t.db", progress=ctrl_c_after_three, handle_signals=True)
    assert (result.state, result.exit_code) == ("paused", 3) and 3 <= result.steps_done < N_STEPS
    assert signal.getsignal(signal.SIGINT) is before
    with labrunner.open(tmp_path / "t.db") as db:
        assert "Ctrl-C: pause" in db.campaign().events().message.tolist()


def test_user_errors_name_what_is_wrong(tmp_path: Path) -> None:
    with pytest.raises(labrunner.UserError, match="database not found"):
        labrunner.open(tmp_path / "missing.db")
    bad = tmp_path / "bad.yaml"
    bad.write_text(TINY.replace("tolerance_c: 0.5", "tolerance_c: -1"))
    with pytest.raises(labrunner.UserError, match=r"bad.yaml:3: soak.tolerance_c"):
        labrunner.run(bad, db=tmp_path / "x.db")
    assert not (tmp_path / "x.db").exists()
    proc = tmp_path / "tiny.yaml"
    proc.write_text(TINY)
    with pytest.raises(labrunner.UserError, match="simulated lab"):
        labrunner.run(proc, db=tmp_path / "x.db", lab=tmp_path / "lab.yaml", faults=3)


def test_unknown_campaign_and_options(tiny_db: Path) -> None:
    with labrunner.open(tiny_db) as db:
        with pytest.raises(labrunner.UserError, match=r"no campaign 7 \(campaigns: 1\)"):
            db.campaign(7)
        with pytest.raises(labrunner.UserError, match="fit options"):
            db.campaign().fit(polynomial_degree=2)
        with pytest.raises(labrunner.UserError, match="diagnose options"):
            db.campaign().diagnose(evidence=3)


def test_import_is_cheap_and_the_api_is_reexported() -> None:
    code = ("import sys, labrunner; heavy = [m for m in ('pandas', 'numpy', 'sqlalchemy', 'labrunner.sims') "
            "if m in sys.modules]; assert not heavy, heavy; "
            "assert labrunner.open is labrunner.api.open and 'run' in dir(labrunner); print('ok')")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr
    with pytest.raises(AttributeError):
        labrunner.no_such_thing  # noqa: B018
