"""Procedures: the shipped ones expand as the paper says; malformed ones get located messages."""

import pytest

from labrunner.procedure import load_procedure, parse_procedure, triangular_rates
from labrunner.yaml_config import ConfigError

from .conftest import ROOT, cli


def test_paper_campaign_is_the_papers():
    p = load_procedure(ROOT / "procedures" / "paper_campaign.yaml")
    steps = p.steps()
    assert p.model.temperatures.values() == [float(t) for t in range(-25, 56, 5)]  # 17 temperatures
    rates = p.model.rates.values()
    assert len(rates) == 40 and max(rates) == 100 and min(rates) == -100
    assert {o for o, _ in p.orientations()} == {"x_up", "x_down", "y_up", "y_down", "z_up", "z_down"}
    assert len(steps) == 17 * 40 * 6
    assert len(steps) * p.frames_per_record == 12_240_000  # 60 s at 50 Hz
    # Serpentine: up for the first orientation, down for the second.
    assert steps[0].temperature_c == -25 and steps[40 * 17].temperature_c == 55


def test_quick_procedure_loads():
    p = load_procedure(ROOT / "procedures" / "quick.yaml")
    assert len(p.steps()) >= 6 * 4


def test_triangular_schedule():
    assert triangular_rates(100, 50) == [50, 100, 50, 0, -50, -100, -50, 0]


BASE = """name: t
temperatures: {start_c: -10, stop_c: 30, step_c: 10}
orientations: [z_up]
rates: {list_dps: [0, 10]}
"""


@pytest.mark.parametrize("text, expect", [
    (BASE + "soak:\n  tolerance_c: 0\n", "x.yaml:6: soak.tolerance_c must be in 0.01..10 C, got 0"),
    (BASE + "soak:\n  tolerance_c: 0.2\n  max_wait_s: soon\n",
     "x.yaml:7: soak.max_wait_s must be a number in 1..604800 s, got 'soon'"),
    (BASE + "soak: {on_timeout: explode}\n", "x.yaml:5: soak.on_timeout must be one of 'continue', 'pause' or 'abort'"),
    (BASE.replace("[z_up]", "[z_up, sideways]"), "x.yaml:3: orientations[1].name must be one of"),
    (BASE.replace("[z_up]", "[z_up, z_up]"), "orientation z_up is listed twice"),
    (BASE + "record_s: -1\n", "x.yaml:5: record_s must be in 0.01..86400 s, got -1"),
    (BASE + "unknown_key: 3\n", "x.yaml:5: unknown_key is not a known key"),
    (BASE.replace("step_c: 10", "step_c: -10"), "x.yaml:2: temperatures.step_c must be in 0.1..200 C, got -10"),
    (BASE.replace("{list_dps: [0, 10]}", "{list_dps: [0, 500]}"),
     "x.yaml:4: rates 500.0 deg/s exceeds safety.max_rate_dps"),
    (BASE.replace("stop_c: 30", "stop_c: 120"), "outside the safety limits"),
    (BASE.replace("name: t\n", ""), "x.yaml:1: name is required"),
    (BASE + "rates: {triangular: {max_dps: 100, step_dps: 30}}\n", "x.yaml:"),
    ("name: [unclosed\n", "x.yaml:2: not valid YAML"),
    ("- just\n- a list\n", "x.yaml:1: expected a mapping"),
    ("", "x.yaml:1: expected a mapping of keys to values, the file is empty"),
    ("!!python/object/apply:os.system ['echo hacked']\n", "x.yaml:1: not valid YAML"),
])
def test_malformed_procedures_get_located_messages(text, expect):
    with pytest.raises(ConfigError) as info:
        parse_procedure(text, "x.yaml")
    assert expect in str(info.value)


def test_cli_reports_a_bad_procedure_without_traceback(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(BASE + "soak:\n  tolerance_c: -1\n")
    proc = cli("run", bad, "--sim", "--db", tmp_path / "x.db")
    assert proc.returncode == 2
    assert f"{bad}:6: soak.tolerance_c must be in 0.01..10 C, got -1" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "x.db").exists()  # nothing started, nothing written


def test_a_stored_campaign_with_retired_fault_keys_still_resumes(caplog):
    # faults.retries/backoff_s were accepted (and never read) before; now refused when written. A campaign
    # stored with them must still be readable for resume, abort and status.
    text = (ROOT / "procedures" / "quick.yaml").read_text() + "\nfaults:\n  retries: 3\n  backoff_s: 0.5\n"
    with pytest.raises(ConfigError, match="retries"):
        parse_procedure(text, "new.yaml")
    stored = parse_procedure(text, "x.db (campaign 1 procedure)", stored=True)
    assert stored.text == text  # the stored text itself is kept as it was
    assert stored.steps() == load_procedure(ROOT / "procedures" / "quick.yaml").steps()
    assert "faults.retries is no longer read" in caplog.text
