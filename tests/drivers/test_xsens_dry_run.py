"""A lab whose IMU is an Xsens MTi: `driver: xsens_mti` found through the `labrunner.drivers` entry point, and
the quick procedure run end to end against a simulated MTi speaking Xbus (sim configuration
`imu_format: xsens_mti`, which makes the dry run's lab configuration select the driver)."""

import json
import sqlite3
import subprocess
import sys

import numpy as np

from labrunner.domain import up_vector
from labrunner.drivers.registry import installed, lookup
from labrunner.drivers.xsens_mti import XsensMtiImu
from labrunner.lab import lab_config_from_dict
from labrunner.store import Store


def test_the_driver_is_installed_and_built_from_a_lab_configuration():
    assert installed()["xsens_mti"].source == "labrunner.drivers.xsens_mti:XSENS_MTI"
    assert lookup("xsens_mti", "imu").driver.kind == "imu"
    config = lab_config_from_dict({
        "chamber": {"host": "127.0.0.1", "port": 1502},
        "table": {"port": "socket://127.0.0.1:1"},
        "imu": {"driver": "xsens_mti", "port": "/dev/ttyUSB0", "rate_hz": 100},
    })
    assert config.driver_name("imu") == "xsens_mti"
    section = config.section("imu")
    assert (section.port, section.rate_hz, section.baudrate) == ("/dev/ttyUSB0", 100, 115200)  # the MTi's default


def test_quick_procedure_end_to_end_on_a_simulated_mti(tmp_path):
    sim = tmp_path / "mti.yaml"
    sim.write_text("imu_format: xsens_mti\nseed: 4\n")
    db = tmp_path / "mti.db"
    run = subprocess.run([sys.executable, "-m", "labrunner", "run", "quick", "--sim", "--sim-config", str(sim),
                          "--db", str(db), "--quiet"], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    with sqlite3.connect(db) as con:
        lab = json.loads(con.execute("SELECT lab_config FROM campaigns").fetchone()[0])
        encodings = {e for (e,) in con.execute("SELECT DISTINCT encoding FROM sample_blocks")}
    assert lab["imu"]["driver"] == "xsens_mti"
    assert encodings == {"f32"}  # float32 on the wire, stored as floats (not whole counts)
    with Store.open_existing(db) as store:
        steps = store.steps_frame(1)
        samples = store.samples_frame(1)
        events = store.events_frame(1)
    assert (steps.status == "done").all() and len(steps) == 192 and len(samples) == 192 * 500
    assert not (events.kind == "fault").any()
    # In g and deg/s like the project's frame: +1 g along each orientation's up axis.
    for orientation, rows in samples.groupby("orientation"):
        mean = rows[["ax_g", "ay_g", "az_g"]].mean().to_numpy()
        assert np.allclose(mean, up_vector(orientation), atol=0.1), (orientation, mean)
    assert "fit stored" in "\n".join(events.message)
    assert XsensMtiImu.__mro__[1].__name__ == "SerialImu"  # one reader for both wire formats
