"""Campaigns end to end against the simulated lab, through the drivers."""

import signal
import time

import numpy as np
import pytest

from labrunner.campaign_csv import read_campaign
from labrunner.store import Store

from .conftest import ROOT, cli, popen


def test_quick_procedure_end_to_end_and_export(tmp_path):
    db = tmp_path / "quick.db"
    proc = cli("run", ROOT / "procedures" / "quick.yaml", "--sim", "--db", db, "--quiet", check=0)
    assert "done. 192/192 steps recorded" in proc.stderr
    # The end-of-run fit leaves the paper's figures next to the models, and its summary starts with the headline.
    fit_dir = next((tmp_path / "quick_fit").glob("**/imu_calibration.h")).parent
    figures = {p.name for p in fit_dir.glob("*.png") if p.read_bytes()[:4] == b"\x89PNG"}
    assert {"thermal_accel_bias.png", "thermal_gyro_scale.png", "heldout_error_accel.png", "static_norm_gyro.png",
            "allan_deviation.png"} <= figures
    assert "**Exported** to the C header" in proc.stdout and "`static_norm_accel.png`" in proc.stdout
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        steps = store.steps_frame(cid)
        ev = store.events_frame(cid)
    assert (steps.status == "done").all() and (steps.n_samples == 500).all()
    # Every state was entered through a logged transition, in order.
    trans = ev[ev.kind == "transition"].message.tolist()
    assert trans[:5] == ["idle -> preflight", "preflight -> mounting", "mounting -> ramping", "ramping -> soaking",
                         "soaking -> rate_settling"]
    assert trans[-1] == "fitting -> done"
    assert (ev[ev.kind == "transition"].t_s.diff().dropna() >= 0).all()
    csv = tmp_path / "quick.csv"
    cli("export", db, "--csv", csv, check=0)
    frame = read_campaign(csv)  # valid campaign CSV
    assert len(frame) == 192 * 500
    assert set(frame.orientation.unique()) == {"x_up", "x_down", "y_up", "y_down", "z_up", "z_down"}
    assert frame.run.nunique() == 6
    z_up = frame[frame.orientation == "z_up"]
    assert z_up.az_g.mean() == pytest.approx(1.0, abs=0.1)
    spin = frame[(frame.orientation == "z_up") & (frame.table_rate_dps > 99)]
    assert spin.gz_dps.mean() == pytest.approx(100.0, rel=0.03)
    assert np.isfinite(frame.chamber_c).all()
    status = cli("status", db, check=0).stdout
    assert "192/192 steps" in status and "done" in status


def test_chamber_that_never_stabilises_triggers_the_timeout_policy(tmp_path, tiny):
    sim = tmp_path / "sim.yaml"
    sim.write_text("faults:\n  chamber: {compressor_failed: true}\n")  # it can heat but never cool
    text = (tiny.read_text().replace("list_c: [15, 35]", "list_c: [5, 35]")
            .replace("max_wait_s: 7200", "max_wait_s: 1800"))
    for policy, code, status in (("abort", 4, "aborted"), ("pause", 3, "paused")):
        proc_file = tmp_path / f"{policy}.yaml"
        proc_file.write_text(text.replace("on_timeout: continue", f"on_timeout: {policy}"))
        db = tmp_path / f"{policy}.db"
        proc = cli("run", proc_file, "--sim", "--sim-config", sim, "--db", db, "--quiet")
        assert proc.returncode == code, proc.stderr
        assert "did not stabilise within soak.max_wait_s" in proc.stderr
        with Store.open_existing(db) as store:
            cid = store.resolve(None)
            assert store.campaign(cid).status == status
            ev = store.events_frame(cid)
        assert ev[ev.kind == "fault"].message.str.contains("on_timeout").any()
        if policy == "abort":
            assert ev.message.str.contains("lab in safe state").any()
    # "continue" records anyway, with a warning.
    proc_file = tmp_path / "continue.yaml"
    proc_file.write_text(text)
    db = tmp_path / "continue.db"
    cli("run", proc_file, "--sim", "--sim-config", sim, "--db", db, "--quiet", check=0)
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        ev = store.events_frame(cid)
        assert store.next_step(cid) is None
    assert ev[ev.kind == "warning"].message.str.contains("did not stabilise").any()


def _wait_for_steps(db, n, timeout=60):
    deadline = time.time() + timeout
    while time.time() < deadline:
        time.sleep(0.2)
        if not db.exists():
            continue
        try:
            with Store.open_existing(db) as store:
                cid = store.resolve(None)
                if (store.steps_frame(cid).status == "done").sum() >= n:
                    return
        except Exception:
            continue
    raise AssertionError(f"fewer than {n} steps recorded within {timeout} s")


def test_ctrl_c_pauses_then_resume_finishes(tmp_path):
    db = tmp_path / "q.db"
    p = popen("run", ROOT / "procedures" / "quick.yaml", "--sim", "--db", db, "--quiet")
    _wait_for_steps(db, 3)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 3, err
    assert "pausing at the next safe point" in err and "labrunner resume" in err
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        info = store.campaign(cid)
        done = int((store.steps_frame(cid).status == "done").sum())
        ev = store.events_frame(cid)
    assert info.status == "paused" and 0 < done < 192
    assert ev.message.str.contains("-> paused").any()
    proc = cli("resume", db, "--quiet", check=0)
    assert "done. 192/192" in proc.stderr


def test_labrunner_abort_from_another_terminal_brings_the_lab_to_safe_state(tmp_path):
    for how in ("abort",):
        db = tmp_path / f"{how}.db"
        p = popen("run", ROOT / "procedures" / "quick.yaml", "--sim", "--db", db, "--quiet")
        _wait_for_steps(db, 2)
        r = cli("abort", db)
        assert r.returncode == 0, r.stderr
        out, err = p.communicate(timeout=60)
        assert p.returncode == 4, err
        with Store.open_existing(db) as store:
            cid = store.resolve(None)
            assert store.campaign(cid).status == "aborted"
            ev = store.events_frame(cid)
        assert ev.message.str.contains("-> safe_stop").any()
        assert ev.message.str.contains("lab in safe state: table stopped").any()
        # An aborted campaign stays resumable.
        assert "resume" in err


def test_status_from_another_process_while_running(tmp_path):
    db = tmp_path / "q.db"
    p = popen("run", ROOT / "procedures" / "quick.yaml", "--sim", "--db", db, "--quiet")
    try:
        _wait_for_steps(db, 2)
        out = cli("status", db, check=0).stdout
        assert "status      running" in out and "steps (" in out and "next step" in out
    finally:
        p.send_signal(signal.SIGINT)
        p.communicate(timeout=60)


def test_fits_are_stored_with_provenance(tmp_path, tiny):
    import json

    db = tmp_path / "t.db"
    tiny.write_text(tiny.read_text().replace("fit: {run: false}", "fit: {run: true, rbf: false}")
                    .replace("record_s: 4", "record_s: 6"))
    cli("run", tiny, "--sim", "--db", db, "--quiet", check=0)
    cli("fit", db, "--rbf", "", "--no-eval", "--quiet", check=0)  # a second fit, from the command line
    with Store.open_existing(db) as store:
        fits = store.fits_frame(1)
    assert len(fits) == 2  # the campaign's own fit at its end, and the one from `labrunner fit`
    for prov in fits.provenance.map(json.loads):
        assert prov["campaign_id"] == 1 and prov["kind"] == "store"
        assert len(prov["t_range_s"]) == 2 and prov["rows"] == 36 * 300
        assert prov["software"]["version"]
