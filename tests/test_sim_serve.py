"""`labrunner sim serve` in its own process, driven by a plain pymodbus client and by the project's drivers."""

import json
import subprocess
import sys
import time

import pytest
import yaml
from pymodbus.client import ModbusTcpClient


@pytest.fixture
def served(tmp_path):
    lab_yaml = tmp_path / "lab.yaml"
    proc = subprocess.Popen([sys.executable, "-m", "labrunner.cli", "sim", "serve", "--speed", "600",
                             "--lab-config", str(lab_yaml)], stdout=subprocess.PIPE, text=True)
    info = None
    for line in proc.stdout:
        if line.strip().startswith("ready "):
            info = json.loads(line.split("ready ", 1)[1])
            break
    assert info is not None, "sim serve did not report ready"
    yield info, lab_yaml
    proc.terminate()
    proc.wait(10)


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
