"""The run summary and `labrunner status` count re-recorded steps the same way, in the same words."""

import re

import pytest
import yaml

from labrunner.store import Store

from ..faults.test_fault_kinds import PROC
from .conftest import cli


# imu_stall re-records one step twice: the summary once counted the re-records (2), status the steps (1).
@pytest.mark.parametrize("kind", ["imu_corrupt", "imu_stall"])
def test_run_summary_counts_rerecorded_steps_as_status_does(tmp_path, kind):
    (tmp_path / "p.yaml").write_text(PROC)
    cli("run", tmp_path / "p.yaml", "--sim", "--db", tmp_path / "ref.db", "--quiet", check=0)
    with Store.open_existing(tmp_path / "ref.db") as store:
        t_start = float(store.steps_frame(1).set_index("idx").loc[2, "t_start"])
    # An IMU fault mid-record of step 2: frames are lost, the step is recorded again.
    (tmp_path / "sim.yaml").write_text(yaml.safe_dump(
        {"faults": {"schedule": [{"at_s": t_start + 3.0, "kind": kind, "duration_s": 30.0, "count": 5}]}}))
    db = tmp_path / "f.db"
    run = cli("run", tmp_path / "p.yaml", "--sim", "--sim-config", tmp_path / "sim.yaml", "--db", db, "--quiet",
              check=0)
    with Store.open_existing(db) as store:
        stored = int((store.steps_frame(1).attempts > 1).sum())
    assert stored >= 1
    status = cli("status", db, check=0)
    in_status = re.search(r"re-recorded steps: (\d+)", status.stdout)
    summary = next((line for line in run.stderr.splitlines() if line.startswith("campaign 1 in ")), "")
    in_run = re.search(r"re-recorded steps: (\d+)", summary)
    assert in_status and in_run, (status.stdout, run.stderr)
    assert int(in_run.group(1)) == int(in_status.group(1)) == stored
    assert "recorded again" not in summary
    assert "this session)" not in summary  # one session: nothing to tell apart


def test_rerecorded_text_names_this_session_when_it_differs():
    from labrunner.commands.campaign import rerecorded_text

    assert rerecorded_text(1, 1) == "re-recorded steps: 1"
    assert rerecorded_text(1, 0) == "re-recorded steps: 1 (0 this session)"
