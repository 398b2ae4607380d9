"""`labrunner sim serve` in its own process, driven by a plain pymodbus client and by the project's drivers."""

import subprocess
import sys
import time

import pytest
import yaml
from pymodbus.client import ModbusTcpClient

from tests.served_lab import run_answering, serve, stop


@pytest.fixture
def served(tmp_path):
    lab_yaml = tmp_path / "lab.yaml"
    proc, info = serve(lab_yaml, "--speed", "600")
    yield info, lab_yaml
    stop(proc)


def test_independent_client_watches_the_chamber_cool(served):
    info, _ = served
    host, port = info["chamber"].split("//")[1].split(":")
    client = ModbusTcpClient(host, port=int(port), timeout=2)
    assert client.connect()
    try:
        assert not client.write_register(300, (-250) & 0xFFFF, device_id=1).isError()  # -25.0 C
        samples = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < 3.0:
            raw = client.read_holding_registers(100, count=1, device_id=1).registers[0]
            samples.append((time.monotonic() - t0, (raw - 0x10000 if raw & 0x8000 else raw) / 10.0))
            time.sleep(0.25)
    finally:
        client.close()
    (t_a, pv_a), (t_b, pv_b) = samples[0], samples[-1]
    assert pv_b < pv_a - 5.0  # moving toward -25 C
    rate_c_per_min = (pv_a - pv_b) / ((t_b - t_a) * 600.0 / 60.0)
    assert 0.5 < rate_c_per_min < 6.0  # a physically plausible chamber, a few degrees per simulated minute


def test_written_lab_configuration_reaches_all_three_sims(served):
    from labrunner.lab import lab_config_from_dict, real_lab

    info, lab_yaml = served
    config = lab_config_from_dict(yaml.safe_load(lab_yaml.read_text()))
    lab = real_lab(config, max_rate_dps=200.0)
    try:
        assert lab.clock.now() > 0 and config.clock.speed == 600.0
        lab.chamber.connect()
        assert lab.chamber.identity().model == "F4"
        lab.table.connect()
        lab.table.jog(20.0)
        lab.imu.connect()
        start = lab.imu.begin_record()
        lab.clock.sleep(30.0)  # 50 ms of wall time at 600x
        rec = lab.imu.end_record(start, 1000, timeout_s=2.0)
        assert len(rec) == 1000 and rec.dropped == 0
        assert lab.table.velocity() == pytest.approx(20.0, rel=1e-3)
    finally:
        lab.close()


# --- a lab of other controllers: a Watlow F4 in deg F and an Ideal Aerosmith table, served --------------

SIM_F_IDEAL = """\
seed: 5
chamber: {controller_units: F, controller_decimals: 1}
table: {language: ideal_aerosmith}
"""


def _serve(tmp_path, *extra):
    lab_yaml = tmp_path / "lab.yaml"
    proc, info = serve(lab_yaml, *extra)
    return proc, info, lab_yaml


@pytest.fixture
def served_f_ideal(tmp_path):
    sim = tmp_path / "sim.yaml"
    sim.write_text(SIM_F_IDEAL)
    proc, info, lab_yaml = _serve(tmp_path, "--speed", "600", "--config", sim)
    yield info, lab_yaml
    proc.terminate()
    proc.wait(10)


def _quick_z_up(tmp_path):
    """The shipped quick procedure with the served IMU's one orientation (a served lab's operator cannot
    turn the simulated IMU, and the mount is checked against gravity) and two of its temperatures."""
    from importlib.resources import files

    text = files("labrunner.procedures").joinpath("quick.yaml").read_text()
    text = text.replace("orientations: [x_up, x_down, y_up, y_down, z_up, z_down]", "orientations: [z_up]")
    text = text.replace("list_c: [-10, 10, 30, 50]", "list_c: [10, 30]")
    assert "orientations: [z_up]" in text and "list_c: [10, 30]" in text
    path = tmp_path / "quick_z_up.yaml"
    path.write_text(text)
    return path


def test_quick_run_against_a_served_f4_in_fahrenheit_and_an_ideal_aerosmith_table(tmp_path, served_f_ideal):
    _, lab_yaml = served_f_ideal
    lab = yaml.safe_load(lab_yaml.read_text())
    assert lab["chamber"]["driver"] == "watlow_f4" and lab["table"]["driver"] == "ideal_aerosmith"
    checked = subprocess.run([sys.executable, "-m", "labrunner.cli", "check", "--lab", str(lab_yaml)],
                             capture_output=True, text=True, timeout=60)
    assert checked.returncode == 0, checked.stderr
    assert "chamber  driver watlow_f4 (labrunner)" in checked.stdout
    assert "table    driver ideal_aerosmith (labrunner)" in checked.stdout
    assert "installed drivers:" in checked.stdout and "serial_table (table:" in checked.stdout

    db = tmp_path / "served.db"
    code, err = run_answering("run", _quick_z_up(tmp_path), "--lab", lab_yaml, "--db", db, "--quiet", timeout=240)
    assert code == 0, err[-3000:]
    from labrunner.store import Store

    with Store.open_existing(db) as store:
        cid = store.resolve(None)
        steps = store.steps_frame(cid)
        events = store.events_frame(cid)
        blocks = store.campaign(cid)
    assert len(steps) == 16 and (steps.status == "done").all() and (steps.n_samples == 500).all()
    assert not events.kind.isin(["fault"]).any(), events[events.kind == "fault"].message.tolist()
    import labrunner

    with labrunner.open(db) as opened:
        samples = opened.campaign().samples()
    # The chamber read in deg F and converted: the records at 30 C hold the chamber near 30 C, not 86.
    at_30 = samples[samples.setpoint_c == 30.0]
    assert at_30.chamber_c.mean() == pytest.approx(30.0, abs=0.5)
    # The Ideal Aerosmith table held every commanded rate while recording (read back with JOG?).
    held = samples.groupby("step_idx").agg(cmd=("rate_cmd_dps", "first"), rate=("table_rate_dps", "mean"))
    assert ((held.rate - held.cmd).abs() <= 1e-3 * held.cmd.abs() + 0.01).all(), held
    assert blocks.lab_config["table"]["driver"] == "ideal_aerosmith"


# --- labrunner check --lab --ping -----------------------------------------------------------------------


def test_ping_reads_every_instrument_and_gravity_without_moving_anything(tmp_path):
    sim = tmp_path / "sim.yaml"
    sim.write_text("seed: 2\norientation: y_down\nchamber: {controller_units: F, controller_decimals: 0}\n"
                   "table: {language: ideal_aerosmith}\n")
    proc, _, lab_yaml = _serve(tmp_path, "--speed", "50", "--config", sim)
    try:
        r = subprocess.run([sys.executable, "-m", "labrunner.cli", "check", "--lab", str(lab_yaml), "--ping"],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stdout + r.stderr
        out = r.stdout
        assert "chamber  ok: driver watlow_f4" in out and "units F" in out and "decimals 0" in out
        assert "air 23" in out or "air 22" in out  # converted from whole degrees F
        assert "table    ok: driver ideal_aerosmith" in out and "limits 360 deg/s" in out
        assert "status STOP settled" in out
        assert "imu      ok: driver labrunner_imu" in out
        assert "gravity  ok: y axis down" in out
        # Nothing moved, nothing written: the served lab still holds its starting setpoint and rest.
        from labrunner.lab import lab_config_from_dict, real_lab

        lab = real_lab(lab_config_from_dict(yaml.safe_load(lab_yaml.read_text())), max_rate_dps=10)
        try:
            assert lab.table.velocity() == 0.0
            assert lab.chamber.read_setpoint() == pytest.approx(23.0, abs=0.3)
        finally:
            lab.close()
    finally:
        proc.terminate()
        proc.wait(10)


def test_ping_of_an_unreachable_lab_is_one_line_per_problem_and_exit_1(tmp_path):
    import socket

    ports = []
    for _ in range(3):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    lab = tmp_path / "lab.yaml"
    lab.write_text(f"name: nobody home\nchamber: {{driver: watlow_f4, port: {ports[0]}, retries: 0}}\n"
                   f"table: {{port: 'socket://127.0.0.1:{ports[1]}', retries: 0}}\n"
                   f"imu: {{port: 'socket://127.0.0.1:{ports[2]}'}}\n")
    r = subprocess.run([sys.executable, "-m", "labrunner.cli", "check", "--lab", str(lab), "--ping"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "Traceback" not in r.stderr
    errors = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(errors) == 1, r.stderr
    assert errors[0].startswith(f"labrunner check: error: {lab}: ping failed: chamber: connect: chamber at "
                                f"modbus-tcp://127.0.0.1:{ports[0]}")
    assert f"table: connect: rate table at socket://127.0.0.1:{ports[1]}: cannot open serial line" in errors[0]
    assert f"imu: connect: imu at socket://127.0.0.1:{ports[2]}" in errors[0]
    assert "chamber  FAILED" in r.stdout and "table    FAILED" in r.stdout


def test_ping_needs_a_lab():
    r = subprocess.run([sys.executable, "-m", "labrunner.cli", "check", "quick", "--ping"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and "--ping talks to the instruments of a lab configuration" in r.stderr


def test_gravity_verdicts():
    import numpy as np

    from labrunner.lab_ping import _gravity

    rng = np.random.default_rng(1)
    noise = rng.normal(0, 0.002, (50, 3))
    v, problem = _gravity(noise + [0.0, 0.0, -1.0], 10.0, 0.1)
    assert problem is None and v.measured == "z_down"
    tilt = np.deg2rad(20.0)
    v, problem = _gravity(noise + [np.sin(tilt), 0.0, np.cos(tilt)], 10.0, 0.1)
    assert "z axis up is 20.0° from vertical, more than 10°" in problem
    v, problem = _gravity(noise + [0.0, 1.5, 0.0], 10.0, 0.1)
    assert "|a| = 1.500 g, not 1 g within 0.1 g" in problem
    v, problem = _gravity(np.empty((0, 3)), 10.0, 0.1)
    assert v is None and "no IMU frames" in problem


def test_serving_units_the_profile_cannot_report_is_refused_in_one_line(tmp_path):
    sim = tmp_path / "sim.yaml"
    sim.write_text("chamber: {controller_units: F}\n")
    r = subprocess.run([sys.executable, "-m", "labrunner.cli", "sim", "serve", "--profile", "watlow_f4t", "--config",
                        str(sim), "--duration", "1"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert ("labrunner sim serve: error: cannot start the simulated lab: chamber sim: profile 'watlow_f4t' has no "
            "units register") in r.stderr
