"""Rehearsal against `labrunner sim serve` in another process, through a lab configuration, in real time
(sped up): the operator answers at the terminal, and a second Ctrl-C during a record aborts to a safe state."""

import signal
import subprocess
import sys
import threading
import time

import pytest

from labrunner.store import Store
from tests.served_lab import serve, stop

from .conftest import popen

PROC = """\
name: rehearsal
temperatures: {list_c: [23]}
soak: {tolerance_c: 1.0, stable_window_s: 60, max_wait_s: 3600, sensor: chamber, poll_s: 10}
orientations: [{name: z_up, prompt: "Mount the IMU z up"}]
rates: {list_dps: [0, 20, -20, 40]}
settle_s: 2
record_s: 30
record_poll_s: 10
fit: {run: false}
"""


@pytest.fixture
def served_lab(tmp_path):
    lab_yaml = tmp_path / "lab.yaml"
    proc, _ = serve(lab_yaml, "--speed", "50")
    yield lab_yaml
    stop(proc)


class _OperatorAtTerminal:
    """`labrunner run` on the served lab, with an operator who types one Enter ahead at the start (which
    must confirm nothing: it is discarded before the prompt) and answers each prompt once it is shown."""

    def __init__(self, proc_file, lab_yaml, db) -> None:
        self.p = subprocess.Popen([sys.executable, "-m", "labrunner.cli", "run", str(proc_file), "--lab",
                                   str(lab_yaml), "--db", str(db), "--quiet"], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self._answer()  # typed ahead
        self.err: list[str] = []
        self.out: list[str] = []
        self._readers = [threading.Thread(target=self._read_err, daemon=True),
                         threading.Thread(target=lambda: self.out.extend(self.p.stdout), daemon=True)]
        for t in self._readers:
            t.start()

    def _answer(self) -> None:
        try:
            self.p.stdin.write("\n")
            self.p.stdin.flush()
        except (BrokenPipeError, ValueError):  # the run ended meanwhile
            pass

    def _read_err(self) -> None:
        for line in self.p.stderr:
            self.err.append(line)
            if line.startswith(">>> Press Enter"):
                self._answer()

    def send_signal(self, sig) -> None:
        self.p.send_signal(sig)

    def kill(self) -> None:
        self.p.kill()

    @property
    def returncode(self):
        return self.p.returncode

    def communicate(self, timeout):
        self.p.wait(timeout)
        for t in self._readers:
            t.join(10)
        return "".join(self.out), "".join(self.err)


def _run_on_lab(proc_file, lab_yaml, db):
    return _OperatorAtTerminal(proc_file, lab_yaml, db)


def _wait_steps(db, n, timeout):
    deadline = time.time() + timeout
    while _steps_done(db) < n and time.time() < deadline:
        time.sleep(0.1)


def _steps_done(db):
    try:
        with Store.open_existing(db) as store:
            return int((store.steps_frame(store.resolve(None)).status == "done").sum())
    except Exception:
        return 0


def test_rehearsal_runs_to_the_end(tmp_path, served_lab):
    (tmp_path / "p.yaml").write_text(PROC)
    db = tmp_path / "r.db"
    p = popen("run", tmp_path / "p.yaml", "--lab", served_lab, "--db", db, "--quiet")
    p.stdin = None
    out, err = p.communicate(timeout=120)
    # No terminal to acknowledge the mounting prompt: a clear message, the lab left safe, resumable.
    assert p.returncode == 4, err
    assert "no terminal to acknowledge" in err or "stdin" in err

    db2 = tmp_path / "r2.db"
    p = _run_on_lab(tmp_path / "p.yaml", served_lab, db2)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    assert "OPERATOR: Mount the IMU z up" in err
    with Store.open_existing(db2) as store:
        steps = store.steps_frame(store.resolve(None))
    assert (steps.status == "done").all() and (steps.n_samples == 1500).all()


def test_second_ctrl_c_during_a_record_aborts_to_safe_state(tmp_path, served_lab):
    (tmp_path / "p.yaml").write_text(PROC)
    db = tmp_path / "r.db"
    p = _run_on_lab(tmp_path / "p.yaml", served_lab, db)
    _wait_steps(db, 1, 60)
    time.sleep(0.2)  # into the next record (0.6 s of wall time at 50x)
    p.send_signal(signal.SIGINT)
    time.sleep(0.15)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 4, err
    assert "pausing at the next safe point" in err and "aborting" in err
    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        ev = store.events_frame(cid)
        assert store.campaign(cid).status == "aborted"
    assert ev.message.str.contains("lab in safe state: table stopped").any()


def test_abort_with_no_process_running_makes_the_lab_safe_itself(tmp_path, served_lab):
    """A lab campaign whose process died (kill -9) while the table spins: `labrunner abort` connects to
    the stored lab configuration, stops the table and sends the chamber to the remount temperature."""
    import yaml

    from labrunner.drivers.rate_table import SerialRateTable
    from labrunner.lab import lab_config_from_dict, real_lab

    (tmp_path / "p.yaml").write_text(PROC.replace("list_c: [23]", "list_c: [30]").replace(
        "tolerance_c: 1.0", "tolerance_c: 1.5"))
    db = tmp_path / "r.db"
    p = _run_on_lab(tmp_path / "p.yaml", served_lab, db)
    _wait_steps(db, 2, 90)
    p.kill()
    p.communicate(timeout=30)
    cfg = lab_config_from_dict(yaml.safe_load(served_lab.read_text()))
    table = SerialRateTable(cfg.section("table").port, max_rate_dps=200)
    try:
        table.jog(40.0)  # make sure it spins, whatever step the kill interrupted
        time.sleep(0.2)
        assert abs(table.velocity()) > 10
    finally:
        table.close()
    proc = subprocess.run([sys.executable, "-m", "labrunner.cli", "abort", str(db)], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "aborted" in proc.stdout
    lab = real_lab(cfg, max_rate_dps=200)
    try:
        time.sleep(0.2)  # the table decelerates (100 deg/s^2, 50x sped up)
        assert lab.table.velocity() == 0.0
        lab.chamber.connect()
        assert lab.chamber.read_setpoint() == 23.0
    finally:
        lab.close()
    with Store.open_existing(db) as store:
        assert store.campaign(1).status == "aborted"


def test_an_enter_typed_ahead_on_the_terminal_does_not_confirm_the_remount(tmp_path, served_lab):
    """`labrunner run` with a pseudo-terminal as stdin: an Enter typed before the prompt appears is
    discarded (the campaign waits at the prompt, nothing is mounted or recorded); the Enter typed after
    it confirms the mount, and the run goes to the end."""
    import os
    import pty

    (tmp_path / "p.yaml").write_text(PROC)
    db = tmp_path / "r.db"
    master, slave = pty.openpty()
    p = subprocess.Popen([sys.executable, "-m", "labrunner.cli", "run", str(tmp_path / "p.yaml"), "--lab",
                          str(served_lab), "--db", str(db), "--quiet"], stdin=slave, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    os.close(slave)
    err: list[str] = []
    prompted = threading.Event()

    def read_err() -> None:
        for line in p.stderr:
            err.append(line)
            if line.startswith(">>> Press Enter"):
                prompted.set()

    reader = threading.Thread(target=read_err, daemon=True)
    reader.start()
    try:
        os.write(master, b"\n")  # typed ahead, while the run starts
        assert prompted.wait(60), "".join(err)
        time.sleep(1.5)  # 75 s of lab time at 50x: a confirmed mount would have recorded by now
        assert p.poll() is None
        with Store.open_existing(db) as store:
            ev = store.events_frame(store.resolve(None))
        assert ev.message.str.startswith("remount: Mount the IMU z up").sum() == 1
        assert not ev.message.str.startswith("IMU mounted").any() and _steps_done(db) == 0
        os.write(master, b"\n")  # the operator's answer
        p.wait(120)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)
        os.close(master)
    reader.join(10)
    assert p.returncode == 0, "".join(err)
    with Store.open_existing(db) as store:
        ev = store.events_frame(store.resolve(None))
    assert ev.message.str.startswith("IMU mounted z_up, powered on (run 1); gravity: z axis up").sum() == 1
    assert _steps_done(db) == 4
