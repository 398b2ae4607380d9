"""Every kind of injected fault: the policy's response shows in the events, the campaign finishes with the
steps and sample counts of a fault-free run, and what was recorded before the fault is untouched."""

import pytest
import yaml

from labrunner.fault_plan import RANDOM_KINDS
from labrunner.store import Store

from ..campaign.conftest import cli

PROC = """\
name: faults
temperatures: {list_c: [15, 35], order: ascending}
soak: {tolerance_c: 0.5, stable_window_s: 120, max_wait_s: 1800, on_timeout: pause, sensor: chamber, poll_s: 30}
orientations: [z_up, x_up]
remount_s: 60
rates: {list_dps: [-50, 0, 50, 100]}
settle_s: 1
record_s: 10
record_poll_s: 5
safety: {chamber_min_c: -40, chamber_max_c: 40, max_rate_dps: 150, imu_max_temp_c: 85}
faults: {policy: pause, max_rerecords: 2}
fit: {run: false}
"""

# What the events must show for each fault kind (the sequencer's answer to it).
EVIDENCE = {
    "modbus_timeout": ["no valid answer", "resuming after a fault pause", "chamber answers again"],
    "modbus_exception": ["Modbus exception 4", "resuming after a fault pause"],
    "modbus_busy": ["Modbus exception 6", "chamber answers again"],
    "modbus_drop": ["retry 1: chamber", "chamber answers again"],
    "modbus_outage": ["cannot connect", "resuming after a fault pause", "chamber answers again"],
    "heater_failure": ["did not stabilise within soak.max_wait_s", "resuming after a fault pause"],
    "compressor_failure": ["did not stabilise within soak.max_wait_s", "resuming after a fault pause"],
    "garbage_pv": ["not a plausible temperature", "resuming after a fault pause"],
    "table_fault": ["table at +0.0000 deg/s while recording", "resuming after a fault pause"],
    "table_silent": ["no reply within", "resuming after a fault pause"],
    "table_garbage": ["garbage reply", "resuming after a fault pause"],
    "imu_stall": ["frames lost", "recording again"],
    "imu_corrupt": ["frames lost", "recording again"],
    "imu_gap": ["frames lost", "recording again"],
    "table_link_drop": ["rate table", "resuming after a fault pause"],
    "imu_link_drop": ["link lost", "link restored", "recording again"],
}
# When each fault strikes: mid-record of step 2, or just before a ramp that needs the failing part.
WHEN = {"heater_failure": ("t_end", 3, 1.0, 3000.0),  # before the ramp 15 -> 35 C
        "compressor_failure": ("t_end", 7, 1.0, 3000.0)}  # before the remount at 23 C from 35 C


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    d = tmp_path_factory.mktemp("ref")
    (d / "p.yaml").write_text(PROC)
    cli("run", d / "p.yaml", "--sim", "--db", d / "ref.db", "--quiet", check=0)
    with Store.open_existing(d / "ref.db") as store:
        steps = store.steps_frame(1)
        samples = store.samples_frame(1)
    return steps, samples


def _run_with(tmp_path, schedule, policy="pause", proc_text=PROC, extra=()):
    (tmp_path / "p.yaml").write_text(proc_text.replace("policy: pause", f"policy: {policy}"))
    (tmp_path / "sim.yaml").write_text(yaml.safe_dump({"faults": {"schedule": schedule}}))
    db = tmp_path / "f.db"
    proc = cli("run", tmp_path / "p.yaml", "--sim", "--sim-config", tmp_path / "sim.yaml", "--db", db, "--quiet",
               *extra)
    return proc, db


def _fault_time(steps, kind):
    col, idx, offset, duration = WHEN.get(kind, ("t_start", 2, 3.0, 30.0))
    return float(steps.set_index("idx").loc[idx, col]) + offset, duration


def _check_same_as_reference(db, reference, t_fault):
    ref_steps, ref_samples = reference
    with Store.open_existing(db) as store:
        steps = store.steps_frame(1)
        samples = store.samples_frame(1)
        ev = store.events_frame(1)
    cols = ["idx", "orientation", "temperature_c", "rate_dps", "status", "n_samples"]
    assert steps[cols].equals(ref_steps[cols])  # same steps, same sample counts
    assert len(samples) == len(ref_samples)
    # Every step completed before the fault is exactly what a fault-free run records.
    cutoff = ref_steps.t_end[ref_steps.t_end <= t_fault].max()
    before = samples.t_s <= cutoff
    assert before.any()
    assert samples[before].equals(ref_samples[ref_samples.t_s <= cutoff])
    return ev


@pytest.mark.parametrize("kind", RANDOM_KINDS)
def test_fault_kind_is_survived(tmp_path, reference, kind):
    ref_steps, _ = reference
    at, duration = _fault_time(ref_steps, kind)
    proc, db = _run_with(tmp_path, [{"at_s": at, "kind": kind, "duration_s": duration,
                                     "count": 2 if kind == "modbus_busy" else 5}])
    assert proc.returncode == 0, proc.stderr[-3000:]
    ev = _check_same_as_reference(db, reference, at)
    text = "\n".join(ev.message)
    assert f"fault injected: {kind}" in text
    for needle in EVIDENCE[kind]:
        assert needle in text, f"{kind}: no event mentions {needle!r}"


def test_abort_policy_leaves_a_safe_resumable_campaign(tmp_path, reference):
    ref_steps, _ = reference
    at, _ = _fault_time(ref_steps, "modbus_outage")
    proc, db = _run_with(tmp_path, [{"at_s": at, "kind": "table_silent", "duration_s": 60.0}], policy="abort")
    assert proc.returncode == 4, proc.stderr[-3000:]
    with Store.open_existing(db) as store:
        ev = store.events_frame(1)
        assert store.campaign(1).status == "aborted"
    assert ev.message.str.contains("-> safe_stop").any()
    # The silent table cannot be stopped at once: the sequencer keeps trying until it answers.
    assert ev.message.str.contains("safe state not reached yet, trying again").any()
    assert ev.message.str.contains("lab in safe state: table stopped").any()
    proc = cli("resume", db, "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    _check_same_as_reference(db, reference, at)


@pytest.mark.parametrize("kind, trip", [("heater_stuck", "chamber at"), ("table_overspeed", "table at"),
                                        ("imu_overheat", "IMU at")])
def test_interlock_trips_to_safe_state_and_campaign_resumes(tmp_path, reference, kind, trip):
    ref_steps, _ = reference
    when = {"heater_stuck": ("t_end", 4, 1.0), "table_overspeed": ("t_start", 3, -6.0),
            "imu_overheat": ("t_start", 2, 3.0)}[kind]
    at = float(ref_steps.set_index("idx").loc[when[1], when[0]]) + when[2]
    proc, db = _run_with(tmp_path, [{"at_s": at, "kind": kind, "duration_s": 1200.0}])
    assert proc.returncode == 4, proc.stderr[-3000:]
    with Store.open_existing(db) as store:
        ev = store.events_frame(1)
        assert store.campaign(1).status == "aborted"
    inter = ev[ev.kind == "interlock"]
    assert len(inter) == 1 and inter.message.iloc[0].startswith(trip)
    assert ev.message.str.contains("lab in safe state: table stopped").any()
    proc = cli("resume", db, "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    _check_same_as_reference(db, reference, at)
