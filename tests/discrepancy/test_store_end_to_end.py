"""Diagnosis of this tool's own campaigns, through the whole chain: a dry run (sequencer, drivers,
simulated lab) into the store, raw 50 Hz record steps mixed with 1 s monitor rows of the ramps and soaks,
then `labrunner diagnose` on the database."""

import json

import pytest

from ..campaign.conftest import ROOT, cli


@pytest.mark.parametrize("hidden", [None, {"thermal_lag": {"tau_s": 240.0, "channels": ["accel_z", "gyro_x"]}}])
def test_diagnose_a_dry_run_from_the_store(tmp_path, hidden):
    sim = tmp_path / "sim.yaml"
    sim.write_text(json.dumps({"seed": 5, "imu_model": {"effects": hidden or {}}}))
    db = tmp_path / "c.db"
    cli("run", ROOT / "procedures" / "quick.yaml", "--sim", "--sim-config", sim, "--db", db, "--quiet", check=0)
    out = tmp_path / "d.json"
    cli("diagnose", db, "--json", out, check=0)
    d = json.loads(out.read_text())
    assert d["coverage"]["rows"] > 192 * 500  # the monitor rows are in
    # The Python API reads the store the same bounded way (1 s summaries) and comes to the same answer.
    import labrunner

    via_api = labrunner.open(db).campaign().diagnose()
    assert via_api.verdict == d["verdict"]
    assert via_api.to_json()["coverage"]["rows"] == d["coverage"]["rows"]
    if hidden is None:
        assert d["verdict"] == "none", d["findings"]
        return
    assert d["verdict"] == "thermal_lag"
    lag = next(f for f in d["findings"] if f["cause"] == "thermal_lag")
    assert set(lag["channels"]) == {"accel_z", "gyro_x"}
    assert lag["parameters"]["tau_s"] == pytest.approx(240.0, rel=0.05)
    assert lag["gain"]["improvement_pct"] > 0
