"""The live view (issue 14, item 3): measured temperatures and soak progress in the progress values
and in `labrunner status`, an ETA from the measured pace that converges, the bar's position on
resume, and `status --watch` ending with the campaign."""

from __future__ import annotations

import io
import math
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import pytest

import labrunner
from labrunner.procedure import parse_procedure
from labrunner.runner.pace import PaceEstimator, Schedule
from labrunner.runner.soak import SoakWindow
from labrunner.store import Store

TINY = """\
name: tiny
temperatures: {list_c: [15, 35], order: serpentine}
soak: {tolerance_c: 0.5, stable_window_s: 120, max_wait_s: 7200, on_timeout: continue, sensor: imu, poll_s: 30}
orientations: [x_up, x_down, y_up, y_down, z_up, z_down]
remount_s: 60
rates: {list_dps: [-50, 0, 50]}
settle_s: 1
record_s: 4
record_poll_s: 2
fit: {run: false}
"""


def _cli(*args: object, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrunner.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


# --- the ETA estimator on a synthetic pace -----------------------------------------------------------


def _synthetic_campaign(seed: int) -> tuple[list[float], list[tuple[float, float, int | None, float]]]:
    """A quick-like plan (24 soaks of ~1 h, 8 short records after each) and a run of it: soaks end
    15 % sooner than planned, give or take 10 %; a soak passes lab time 5x faster per wall second
    than a record (as measured in the quick dry run: its monitor polls against decoded frames). Returns the plan's step
    ends and the run's moments (wall, lab, step, lab in step), soak polls every 30 s of lab time."""
    rng = random.Random(seed)
    ends, t = [], 0.0
    costs = []
    for _ in range(24):
        for rate in range(8):
            cost = (3000.0 if rate == 0 else 0.0) + 12.5
            costs.append(cost)
            t += cost
            ends.append(t)
    moments: list[tuple[float, float, int | None, float]] = []
    wall = lab = 0.0
    for k, cost in enumerate(costs):
        in_step = 0.0
        if cost > 100:
            soak = (cost - 12.5) * 0.85 * rng.uniform(0.9, 1.1)
            while in_step < soak:  # polls: 30 s of lab time in 2.5 ms of wall time
                d = min(30.0, soak - in_step)
                in_step += d
                lab += d
                wall += d / 12000.0
                moments.append((wall, lab, k, in_step))
        lab += 12.5
        in_step += 12.5
        wall += 12.5 / 2500.0  # a record: 12.5 s of lab time in 5 ms
        moments.append((wall, lab, k, in_step))
    moments.append((wall, lab, None, 0.0))
    return ends, moments


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_eta_converges_on_a_synthetic_pace(seed: int) -> None:
    ends, moments = _synthetic_campaign(seed)
    schedule = Schedule.of(ends)
    pace = PaceEstimator(schedule.total_s)
    end_wall = moments[-1][0]
    errors: list[tuple[float, float]] = []  # (fraction of the wall time, relative error of the ETA)
    for wall, lab, k, in_step in moments[:-1]:
        eta = pace.update(wall, lab, schedule.done_s(k, in_step))
        fraction, left = wall / end_wall, end_wall - wall
        if left <= 0:  # the last record: done
            assert eta.wall_left_s == 0.0
            continue
        said = f"{eta.wall_left_s} s for {left:.3f} s at {fraction:.0%}"
        if fraction >= 0.10:
            assert eta.wall_left_s is not None, f"no ETA at {fraction:.0%}"
        # The last 5 % are the last records alone, slower per lab second than the mean pace: there the
        # ETA is off by a fraction of very little (a share of the whole run, checked below).
        if 0.10 <= fraction < 0.95:
            assert 0.5 <= eta.wall_left_s / left <= 2.0, said  # type: ignore[operator]
        if 0.5 <= fraction < 0.95:
            assert abs(eta.wall_left_s / left - 1.0) <= 0.2, said  # type: ignore[operator]
        if fraction >= 0.5:
            assert abs(eta.wall_left_s - left) <= 0.05 * end_wall, said  # type: ignore[operator]
        if eta.wall_left_s is not None:
            errors.append((fraction, abs(eta.wall_left_s - left)))
    # It converges: the ETA's error in seconds shrinks as the run goes on.
    early = max(e for f, e in errors if 0.1 <= f < 0.3)
    late = max(e for f, e in errors if f >= 0.7)
    assert late < early / 2
    # tqdm's ETA (steps left / steps per second) is what the issue saw swing: much worse here.
    steps_eta = [(wall, (192 - k) * wall / k) for wall, _, k, _ in moments[:-1] if k and wall / end_wall >= 0.10]
    worst_steps = max(abs(eta / (end_wall - wall) - 1) for wall, eta in steps_eta if end_wall > wall)
    assert worst_steps > 0.5


def test_on_a_clock_with_a_known_rate_the_eta_is_the_lab_time_left() -> None:
    ends, moments = _synthetic_campaign(4)
    schedule = Schedule.of(ends)
    for speed in (1.0, 60.0):  # a real lab; a rehearsal against `sim serve --speed 60`
        pace = PaceEstimator(schedule.total_s, lab_per_wall=speed)
        first = pace.update(0.0, 0.0, 0.0)
        assert first.wall_left_s == pytest.approx(schedule.total_s / speed)  # the plan, at once
        true_lab = moments[-1][1]
        for wall, lab, k, in_step in moments[:-1]:
            eta = pace.update(wall, lab, schedule.done_s(k, in_step))
            assert eta.wall_left_s == pytest.approx(eta.lab_left_s / speed)
            if lab >= 0.5 * true_lab:  # the plan's 15 % error is measured out of the lab time left
                assert abs(eta.lab_left_s - (true_lab - lab)) <= 0.1 * (true_lab - lab) + 300


def test_planned_progress_counts_a_steps_share_and_no_more() -> None:
    schedule = Schedule.of([100.0, 110.0, 400.0])
    assert schedule.done_s(0, 0.0) == 0.0 and schedule.done_s(0, 50.0) == 50.0
    assert schedule.done_s(0, 5000.0) == 100.0  # a soak past its plan holds progress, the ETA grows
    assert schedule.done_s(2, 10.0) == 120.0 and schedule.done_s(None, 0.0) == 400.0


def test_the_step_schedule_is_the_procedures_estimate_step_by_step() -> None:
    procedure = labrunner.load_procedure("quick")
    ends = procedure.estimated_step_ends_s()
    assert len(ends) == len(procedure.steps()) and all(b > a for a, b in zip(ends, ends[1:]))
    m = procedure.model
    last = procedure.steps()[-1]
    # The whole estimate but the last way back to the remount temperature (nothing waits for it).
    assert ends[-1] == pytest.approx(procedure.estimated_duration_s() - abs(last.temperature_c - m.remount_c) / 2 * 60)
    # A temperature's first step carries its soak: far more lab time than the records after it.
    assert ends[0] > 20 * (ends[1] - ends[0])


# --- soak progress ------------------------------------------------------------------------------------


def test_soak_progress_says_stable_exactly_when_the_soak_window_does() -> None:
    procedure = parse_procedure(TINY, "tiny.yaml")
    soak = procedure.model.soak
    rng = random.Random(5)
    for trial in range(200):
        window = SoakWindow(soak, 15.0)
        imu = 15.0 + rng.uniform(-3, 3)
        for i in range(rng.randint(1, 15)):
            imu += rng.uniform(-0.4, 0.4) if trial % 3 else 0.05
            chamber = 15.0 + (rng.uniform(-0.7, 0.7) if trial % 4 == 0 else 0.1)
            window.add(30.0 * i, chamber, imu if trial % 7 else math.nan)
            p = window.progress()
            assert p is not None and p.stable == window.stable(), (trial, i, p)
            assert 0.0 <= p.stable_s <= soak.stable_window_s and p.soaked_s == 30.0 * i
            assert p.chamber_offset_c == pytest.approx(max(0.0, p.chamber_offset_c))
    assert SoakWindow(soak, 15.0).progress() is None


# --- in-process: the progress values of a run and of a resume -------------------------------------------


def test_progress_while_soaking_carries_temperatures_and_the_soaks_spread(tmp_path: Path) -> None:
    seen: list[labrunner.Progress] = []
    result = labrunner.run(parse_procedure(TINY, "tiny.yaml"), db=tmp_path / "t.db", seed=3, progress=seen.append)
    assert result.state == "done"
    soaking = [p for p in seen if p.state == "soaking" and p.soak is not None]
    assert len(soaking) >= 12 * 4  # 12 soaks, polled every 30 s for a 120 s window at least
    for p in soaking:
        s = p.soak
        assert s is not None and p.chamber_c is not None and p.imu_temp_c is not None
        assert all(math.isfinite(v) for v in (p.chamber_c, p.imu_temp_c, s.imu_spread_c, s.chamber_offset_c,
                                              s.stable_s, s.soaked_s))
        assert s.setpoint_c == p.setpoint_c == p.step.temperature_c  # type: ignore[union-attr]
        assert s.tolerance_c == 0.5 and s.window_s == 120.0 and s.imu_c == p.imu_temp_c
    # Each soak ends stable (the sequencer's own judgement), having started far from it.
    last_of_each = [a for a, b in zip(soaking, soaking[1:] + [None]) if b is None or b.step != a.step]
    assert len(last_of_each) == 12 and all(p.soak.stable for p in last_of_each)  # type: ignore[union-attr]
    assert any(p.soak.imu_spread_c > 0.5 for p in soaking)  # type: ignore[union-attr]
    # The first entry into a soak shows no progress of the previous one.
    entries = [p for a, p in zip(seen, seen[1:]) if p.state == "soaking" and a.state != "soaking"]
    assert entries and all(p.soak is None for p in entries)
    # Readings while ramping too; the ETA comes once the pace is measured, and ends near zero.
    assert any(p.state == "ramping" and p.chamber_c is not None for p in seen)
    etas = [p.eta_s for p in seen if p.eta_s is not None]
    assert etas and all(e >= 0 for e in etas) and seen[-1].lab_left_s == 0.0
    assert [p.steps_done for p in seen] == sorted(p.steps_done for p in seen)


def test_a_resumed_run_reports_the_recorded_steps_from_its_first_progress(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    db = tmp_path / "t.db"
    with labrunner.start_run(parse_procedure(TINY, "tiny.yaml"), db=db, seed=3) as session:
        def pause_after_five(progress: labrunner.Progress) -> None:
            if progress.steps_done == 5:
                session.request_pause("test: pause after five steps")

        assert session.execute(pause_after_five).state == "paused"
    seen: list[labrunner.Progress] = []
    with labrunner.start_resume(db) as session:
        assert session.steps_done == 5  # where a bar starts
        assert session.execute(seen.append).state == "done"
    assert seen[0].steps_done == 5 and seen[-1].steps_done == 36

    # The bar starts there, not at 0 (it used to draw 0/36, then jump, throwing its rate off).
    from labrunner.commands.progress import ProgressBar

    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    bar = ProgressBar(36, quiet=False, initial=5)
    assert bar.bar.n == 5 and "5/36 steps" in stream.getvalue() and "0/36" not in stream.getvalue()
    bar(seen[1])
    bar.close()


def test_the_bar_shows_readings_soak_and_eta_and_fits_the_terminal() -> None:
    from labrunner.commands.progress import fit_parts, postfix_parts
    from labrunner.runner.soak import SoakProgress

    procedure = parse_procedure(TINY, "tiny.yaml")
    soak = SoakProgress(setpoint_c=35.0, tolerance_c=0.5, window_s=120.0, sensor="imu", chamber_c=35.1, imu_c=33.2,
                        chamber_offset_c=0.1, imu_spread_c=1.25, stable_s=60.0, soaked_s=600.0)
    p = labrunner.Progress(steps_done=3, steps_total=36, state="soaking", step=procedure.steps()[3],
                           lab_time_s=7200.0, chamber_c=35.1, imu_temp_c=33.2, setpoint_c=35.0, soak=soak,
                           lab_left_s=20000.0, eta_s=3725.0)
    parts = postfix_parts(p)
    assert parts[0] == "soaking x_up +35C -50dps" and "ETA 1:02:05" in parts
    assert "chamber 35.10C IMU 33.20C" in parts and "soak IMU spread 1.25/0.5C stable 60/120s" in parts
    assert parts[-1] == "lab 2.00 h"
    assert fit_parts(parts, 40) == "soaking x_up +35C -50dps | ETA 1:02:05"  # a narrow terminal drops the tail


# --- status and status --watch --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("live") / "done.db"
    assert labrunner.run(parse_procedure(TINY, "tiny.yaml"), db=db, seed=3).state == "done"
    return db


def test_status_lab_time_is_the_latest_of_heartbeat_events_and_samples(finished: Path, tmp_path: Path) -> None:
    db = tmp_path / "copy.db"
    db.write_bytes(finished.read_bytes())
    with labrunner.open(db) as d:
        last_event = float(d.campaign().events().t_s.max())
        assert labrunner.status(db).lab_time_s == pytest.approx(last_event)
    with Store.open_existing(db) as store:
        info = store.campaign(1)
        store.heartbeat(1, info.clock_t0 + 10.0)  # a heartbeat trailing the events (as a virtual clock's does)
    assert labrunner.status(db).lab_time_s == pytest.approx(last_event)
    with Store.open_existing(db) as store:
        store.heartbeat(1, info.clock_t0 + last_event + 500.0)  # one ahead of them (a real lab's, mid-soak)
    assert labrunner.status(db).lab_time_s == pytest.approx(last_event + 500.0)


def test_status_shows_the_stored_temperatures_and_a_soaks_spread(finished: Path) -> None:
    from labrunner.database import _stored_soak

    s = labrunner.status(finished)
    assert s.chamber_c is not None and abs(s.chamber_c - 15.0) < 1.0  # the last steps are at 15 C
    with labrunner.open(finished) as d:
        last = d.campaign().samples().iloc[-1]  # the latest sample stored: the last record's last frame
    assert s.imu_temp_c == pytest.approx(float(last.imu_temp_c), abs=0.01)
    assert s.soak is None and s.eta_wall_s is None and s.over  # done: no soak, no ETA
    with labrunner.open(finished) as d:
        events = d.campaign().events()
        procedure = d.campaign().procedure()
        store = d.store
        soaks = events[(events.kind == "transition") & (events.state == "soaking")]
        soaked = events[events.message.str.startswith("soaked at")]
        start, end = float(soaks.t_s.iloc[-1]), float(soaked.t_s.iloc[-1])
        # The last soak, as `status` saw it when it ended: stable over its window, from the 1 s means.
        p = _stored_soak(store, 1, procedure, start, 15.0, end)
        assert p is not None and p.stable_s > 0 and p.soaked_s == pytest.approx(end - start, abs=31)
        assert p.imu_spread_c <= 2 * p.tolerance_c and p.chamber_offset_c <= p.tolerance_c


def test_status_watch_on_a_finished_campaign_returns_at_once_with_its_state(finished: Path) -> None:
    started = time.monotonic()
    proc = _cli("status", finished, "--watch", "0.2", timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert time.monotonic() - started < 20
    assert "status      done" in proc.stdout and proc.stdout.rstrip().endswith("campaign 1 ended: done")


def test_status_watch_follows_a_running_campaign_and_exits_when_it_ends(tmp_path: Path) -> None:
    # The quick procedure without its fit: ~5 s of wall time, long enough to be watched.
    text = labrunner.load_procedure("quick").text.replace("fit:\n  run: true", "fit:\n  run: false")
    assert "run: false" in text
    (tmp_path / "q.yaml").write_text(text)
    db = tmp_path / "q.db"
    run = subprocess.Popen([sys.executable, "-m", "labrunner.cli", "run", str(tmp_path / "q.yaml"), "--sim", "--db",
                            str(db), "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # until the campaign's row is there
            if db.exists() and os.path.getsize(db) > 0:
                try:
                    if labrunner.status(db).status == "running":
                        break
                except labrunner.UserError:
                    pass
            time.sleep(0.05)
        watch = _cli("status", db, "--watch", "0.2", timeout=120)
        assert watch.returncode == 0, watch.stderr
        assert "status      running" in watch.stdout  # it watched it run ...
        assert watch.stdout.rstrip().endswith("campaign 1 ended: done")  # ... and left when it ended
        assert "ETA" in watch.stdout and "measured    chamber" in watch.stdout
        assert run.wait(timeout=60) == 0
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
